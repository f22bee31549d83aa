"""95% intervals on real Strecha images, through the CLI: `tune evaluate --json` (overall and per scene, `--ci none`,
`--ci-resamples`), then a tiny study end to end: trial attributes, frozen.yaml (interval, selection rule, flat
region), test.json (per-run pair errors, the interval of the mean over runs and how it accounts for run-to-run
variation, the paired comparison with the paper defaults and with itself), `tune table` / `tune results` / the
HTML report. Subsets: entry-P10 images 0000-0004 and Herz-Jesus-P8 0000-0003, 2k SIFT."""
import json

import numpy as np
import pytest
import yaml

from pipeline.metrics.uncertainty import maa_intervals
from tests.conftest import copy_strecha_subset
from tuner.cli import main

ENTRY = [f"{i:04d}.jpg" for i in range(5)]
HERZ = [f"{i:04d}.jpg" for i in range(4)]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("intervals")
    d = copy_strecha_subset(root / "data", ENTRY, scene="entry-P10")
    copy_strecha_subset(root / "data", HERZ, scene="Herz-Jesus-P8")
    return {"data": d, "root": root, "cache": root / "cache"}


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def evaluate(capsys, data, *extra):
    code, out, err = run(capsys, "evaluate", "--data", data["data"], "--scenes", "entry-P10,Herz-Jesus-P8",
                         "--num-features", 2000, "--cache", data["cache"], "--json", "--pairs", *extra)
    assert code == 0, err
    return json.loads(out)["stereo"]


def inside(ci, v) -> bool:
    return ci[0] - 1e-12 <= v <= ci[1] + 1e-12 and 0.0 <= ci[0] <= ci[1] <= 1.0


def test_evaluate_json_intervals_contain_the_estimate(capsys, data):
    st = evaluate(capsys, data)
    for k in ("mAA5", "mAA10"):
        assert inside(st[f"{k}_ci"], st[k]), (k, st[f"{k}_ci"], st[k])
        for name, s in st["scenes"].items():
            assert inside(s[f"{k}_ci"], s[k]), (name, k)
    assert st["ci"]["resamples"] == 2000
    # a real spread of pair errors gives a real interval
    assert st["mAA10_ci"][1] - st["mAA10_ci"][0] > 0.01
    # exactly the stratified bootstrap of the records (seed 0), not some other computation
    recs = [{**r, "err": float(r["err"]) if r["err"] not in (None, "inf") else float("inf")}
            for r in st["pair_records"]]
    ref = maa_intervals(recs, n_resamples=2000, seed=0, scenes=list(st["scenes"]))
    assert np.allclose(ref["mAA10_ci"], st["mAA10_ci"]) and np.allclose(ref["mAA5_ci"], st["mAA5_ci"])
    for name in st["scenes"]:
        assert np.allclose(ref["scenes"][name]["mAA10_ci"], st["scenes"][name]["mAA10_ci"])


def test_ci_none_removes_the_intervals_and_changes_no_number(capsys, data):
    with_ci = evaluate(capsys, data)
    none = evaluate(capsys, data, "--ci", "none")
    assert "mAA10_ci" not in none and "mAA5_ci" not in none and "ci" not in none
    assert all("mAA10_ci" not in s and "mAA5_ci" not in s for s in none["scenes"].values())
    assert none["mAA10"] == with_ci["mAA10"] and none["mAA5"] == with_ci["mAA5"]
    fewer = evaluate(capsys, data, "--ci-resamples", 500)
    assert fewer["ci"]["resamples"] == 500 and inside(fewer["mAA10_ci"], fewer["mAA10"])


def test_bad_ci_options_are_one_line_errors(capsys, data):
    for argv in (["--ci", "bca"], ["--ci-resamples", "5"], ["--ci-resamples", "x"]):
        with pytest.raises(SystemExit) as e:
            main(["evaluate", "--data", str(data["data"]), *argv])
        assert e.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert "Traceback" not in "\n".join(err) and err


def test_readable_table_shows_value_and_interval(capsys, data):
    code, out, err = run(capsys, "evaluate", "--data", data["data"], "--scenes", "entry-P10", "--num-features", 2000,
                         "--cache", data["cache"], "--quiet")
    assert code == 0, err
    rows = [ln for ln in out.splitlines() if ln.startswith("| entry-P10")]  # a wide table is split by columns
    assert sum(r.count("[") for r in rows) == 3 and "95% interval" in out  # mAA5, mAA10 and auc10 as value [lo, hi]
    assert max(len(ln) for ln in out.splitlines() if ln.startswith("|")) <= 100, out


def test_tiny_study_end_to_end(capsys, data):
    studies = data["root"] / "studies"
    code, out, err = run(capsys, "run", "--data", data["data"], "--scenes", "entry-P10", "--test-scenes",
                         "Herz-Jesus-P8", "--num-features", 2000, "--cache", data["cache"], "--studies-dir", studies,
                         "--study", "tiny", "--n-trials", 4, "--test-runs", 2, "--calibration-pairs", 3,
                         "--select", "one-se", "--quiet")
    assert code == 0, err
    frozen = yaml.safe_load((studies / "tiny" / "frozen.yaml").read_text())
    v = frozen["validation"]
    assert inside(v["mAA10_ci"], v["mAA10"]) and inside(v["scenes"]["entry-P10"]["mAA10_ci"], v["mAA10"])
    assert frozen["selection"]["rule"] == "one-se" and frozen["trial"] in frozen["selection"]["within_one_se"]
    rob = frozen["robustness"]
    assert 1 <= rob["trials"] <= rob["of"] and set(rob["params"]) <= {"threshold", "ratio", "max_iters"}
    assert isinstance(frozen["warnings"], list)
    assert "flat region" in out and "selection: one-se" in out

    t = json.loads((studies / "tiny" / "test.json").read_text())
    assert len(t["runs"]) == 2 and all(len(r["pair_errors"]) == t["data"]["pairs"] for r in t["runs"])
    m = t["mean"]
    assert inside(m["mAA10_ci"], m["mAA10"]) and inside(m["scenes"]["Herz-Jesus-P8"]["mAA10_ci"], m["mAA10"])
    assert "run-to-run" in t["interval"]["method"] and t["interval"]["consistent_with_mean"]
    assert "mAA10" in t["std"]
    ref = t["reference"]
    assert "paper defaults" in ref["label"] and ref["config"]["geometry"]["threshold"] == 0.5
    c = ref["comparison"]
    assert c["pairs"] == t["data"]["pairs"]
    assert c["difference"] == pytest.approx(m["mAA10"] - ref["mAA10"], abs=1e-9)
    assert "frozen - reference" in out

    # compared with itself: difference 0, p = 1
    code, out, err = run(capsys, "test", "--study", "tiny", "--studies-dir", studies, "--data", data["data"],
                         "--cache", data["cache"], "--runs", 2, "--reference", studies / "tiny" / "frozen.yaml",
                         "--json", "--quiet")
    assert code == 0, err
    same = json.loads(out)["reference"]["comparison"]
    assert same["difference"] == 0.0 and same["p_value"] == 1.0 and same["ci"] == [0.0, 0.0]

    code, out, err = run(capsys, "results", "--studies-dir", studies)
    assert code == 0 and "[" in out, err
    code, out, err = run(capsys, "table", "--studies-dir", studies)
    assert code == 0 and "[" in out.splitlines()[2], err
    code, out, err = run(capsys, "plot", "--study", "tiny", "--studies-dir", studies)
    assert code == 0, err
    html = (studies / "tiny" / "report.html").read_text()
    assert "95% interval" in html and "flat region" in html and "frozen - reference" in html


def _bag(scene, size, k, errors):
    return {"scene": scene, "bag_size": size, "bag": k, "success": True, "RC": 100.0, "NL": 10, "TL": 3.0,
            "ATE": 0.1, "NM": 50.0, "seconds": 1.0, "errors": list(errors)}


def test_multiview_bag_intervals_are_those_of_the_task_summary(monkeypatch):
    """The multiview wiring (pipeline.tasks.multiview: summarize_scene -> combine, then add_intervals with
    bag_intervals) on bag records with known errors: with every bag of a (scene, size) group alike and no
    pseudo-bags the interval is degenerate and must equal the task's own mAA exactly (same weights: bag sizes,
    then scenes, unequal bag counts); with varied bags, or the pseudo-bags of small groups, it contains it."""
    from pipeline.metrics import uncertainty
    from pipeline.metrics.uncertainty import bag_intervals
    monkeypatch.setattr(uncertainty, "SCORE_RANGE", ())
    from pipeline.tasks.multiview import combine, summarize_scene
    from pipeline.tasks.stereo import add_intervals
    alike = ([_bag("a", 5, k, [0.5, 3.0, 20.0]) for k in range(4)] + [_bag("a", 10, k, [1.5] * 6) for k in range(2)]
             + [_bag("b", 5, k, [7.0, float("inf")]) for k in range(3)])
    rng = np.random.default_rng(0)
    varied = [_bag(r["scene"], r["bag_size"], r["bag"], rng.exponential(5.0, 6)) for r in alike]
    for recs, degenerate in ((alike, True), (varied, False)):
        per = {n: summarize_scene([r for r in recs if r["scene"] == n]) for n in ("a", "b")}
        summary = combine(per)
        add_intervals(summary, per, bag_intervals(recs, n_resamples=500, scenes=["a", "b"]), 500)
        for k in ("mAA5", "mAA10"):
            lo, hi = summary[f"{k}_ci"]
            if degenerate:
                assert lo == pytest.approx(summary[k], abs=1e-12) and hi == pytest.approx(summary[k], abs=1e-12)
            else:
                assert lo < summary[k] < hi
            for n in ("a", "b"):
                assert inside(per[n][f"{k}_ci"], per[n][k])
    monkeypatch.undo()
    per = {n: summarize_scene([r for r in alike if r["scene"] == n]) for n in ("a", "b")}
    summary = combine(per)
    add_intervals(summary, per, bag_intervals(alike, n_resamples=500, scenes=["a", "b"]), 500)
    assert summary["mAA10_ci"][0] < summary["mAA10"] < summary["mAA10_ci"][1]
