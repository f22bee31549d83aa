"""Real short studies on fountain-P11 (2048 SIFT, a few pairs): objective, attributes, resume, freeze,
test.json, tables, the HTML report, two SQLite workers, kill -9 and resume, journal storage."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import DATA, ROOT, copy_studies

STRECHA = DATA / "strecha"
pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")


@pytest.fixture(scope="session")
def tuner_cache(tmp_path_factory):
    """One feature / k-NN cache for every tuner test module (same path in each: basetemp/tuner-cache)."""
    d = tmp_path_factory.getbasetemp() / "tuner-cache"
    d.mkdir(exist_ok=True)
    return str(d)


def tune(*args, cache, timeout=600, check=False):
    env = dict(os.environ, IMTUNE_CACHE=cache)
    r = subprocess.run([sys.executable, "-m", "tuner", *args], capture_output=True, text=True, cwd=ROOT, env=env,
                       timeout=timeout)
    if check:
        assert r.returncode == 0, r.stderr[-3000:]
    return r


def quick(studies_dir, *extra, ransac="degensac", pairs=8):
    return ["--data", str(STRECHA), "--feature", "sift", "--num-features", "2048", "--ransac", ransac,
            "--scenes", "fountain-P11", "--test-scenes", "Herz-Jesus-P8", "--max-pairs", str(pairs),
            "--chunk-pairs", "4", "--budget", "0.1", "--calibration-pairs", "4", "--studies-dir", str(studies_dir),
            *extra]


def load(storage, name):
    import optuna

    from tuner.storage import open_storage
    return optuna.load_study(study_name=name, storage=open_storage(storage, heartbeat=None))


@pytest.fixture(scope="module")
def study_run(tmp_path_factory, tuner_cache):
    """`tune` with 4 trials, then the test scenes: the JSON it prints and where it wrote."""
    d = tmp_path_factory.mktemp("studies")
    r = tune(*quick(d, "--n-trials", "4", "--seed", "3", "--json"), cache=tuner_cache, check=True)
    return {"dir": d, "out": json.loads(r.stdout), "storage": f"sqlite:///{d}/optuna.db",
            "name": "sift-2048-degensac-stereo"}


def test_study_trials_and_attributes(study_run):
    from optuna.trial import TrialState
    out = study_run["out"]
    assert out["study"] == study_run["name"]
    assert out["storage"] == study_run["storage"]
    assert (study_run["dir"] / "optuna.db").is_file()
    st = load(study_run["storage"], study_run["name"])
    finished = [t for t in st.trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]
    assert len(finished) == 4 == len(out["worker"]["trials_run"])
    ua = st.user_attrs
    assert len(ua["data_fingerprint"]) == 16
    assert ua["budget"]["seconds_per_pair"] == 0.1 and ua["budget"]["gamma_max"] >= 100
    assert ua["budget"]["calibration"]["curve"]
    assert ua["code_version"].startswith("0.") or "+" in ua["code_version"]
    assert ua["search_space"]["params"]["max_iters"]["high"] == "calibrated"
    assert ua["search_space_resolved"]["params"]["max_iters"]["high"] == ua["budget"]["gamma_max"]
    assert ua["data"]["val_scenes"] == ["fountain-P11"] and ua["data"]["pairs"] == 8
    for t in st.trials:
        if t.state != TrialState.COMPLETE:
            continue
        assert set(t.params) == {"ratio", "threshold", "max_iters"}
        assert 0.6 <= t.params["ratio"] <= 1.0 and 0.1 <= t.params["threshold"] <= 2.0
        assert t.params["max_iters"] <= ua["budget"]["gamma_max"]
        for k in ("mAA5", "mAA10", "NF", "NM", "NI", "ransac_seconds_median", "ransac_seconds_p90",
                  "match_seconds", "scenes", "failed", "failed_pairs", "feasible", "timing"):
            assert k in t.user_attrs, k
        assert t.user_attrs["mAA10"] == pytest.approx(t.value)
        assert t.user_attrs["NF"] == pytest.approx(2048, rel=0.1)
        assert t.user_attrs["scenes"]["fountain-P11"]["pairs"] == 8
        assert sorted(t.intermediate_values) == [0, 1]  # 8 pairs in chunks of 4: two pruning steps
        assert "budget" in t.constraints
        assert (t.constraints["budget"] <= 0) == t.user_attrs["feasible"]
    assert (study_run["dir"] / "budgets.json").is_file()


def test_frozen_yaml(study_run):
    out = study_run["out"]
    path = study_run["dir"] / study_run["name"] / "frozen.yaml"
    assert out["frozen_path"] == str(path)
    f = yaml.safe_load(path.read_text())
    st = load(study_run["storage"], study_run["name"])
    best = st.trials[f["trial"]]
    assert f["value"] == pytest.approx(best.value)
    assert best.user_attrs["feasible"] and best.constraints["budget"] <= 0
    assert all(best.value >= t.value for t in st.trials if t.value is not None and t.user_attrs.get("feasible"))
    assert f["params"] == pytest.approx(best.params)
    assert f["fixed"] == {"strategy": "both"}
    c = f["config"]
    assert c["matching"]["ratio"] == pytest.approx(f["params"]["ratio"])
    assert c["geometry"]["threshold"] == pytest.approx(f["params"]["threshold"])
    assert c["geometry"]["max_iters"] == f["params"]["max_iters"]
    assert c["feature"]["num_features"] == 2048 and c["geometry"]["confidence"] == 0.999999
    assert f["budget"]["seconds_per_pair"] == 0.1 and f["budget"]["gamma_max"] == st.user_attrs["budget"]["gamma_max"]
    assert f["data"]["fingerprint"] == st.user_attrs["data_fingerprint"]
    assert f["validation"]["mAA10"] == pytest.approx(best.value) and f["validation"]["pairs"] == 8


def test_test_json_three_runs(study_run):
    t = json.loads((study_run["dir"] / study_run["name"] / "test.json").read_text())
    assert t["data"]["scenes"] == ["Herz-Jesus-P8"] and t["data"]["pairs"] == 8
    assert [r["seed"] for r in t["runs"]] == [3, 4, 5]
    assert t["mean"]["mAA10"] == pytest.approx(sum(r["mAA10"] for r in t["runs"]) / 3)
    assert 0.0 <= t["mean"]["mAA10"] <= 1.0 and t["mean"]["NI"] > 0
    assert t["budget"]["test_seconds_per_pair"] == 1.0 and t["budget"]["within_budget"] in (True, False)
    assert study_run["out"]["test"]["mean"]["mAA10"] == pytest.approx(t["mean"]["mAA10"])
    st = load(study_run["storage"], study_run["name"])
    assert st.user_attrs["test"]["mAA10"] == pytest.approx(t["mean"]["mAA10"])


def test_rerun_resumes_and_checks_the_space(study_run, tuner_cache):
    d = study_run["dir"]
    r = tune(*quick(d, "--n-trials", "6", "--no-test", "--json"), cache=tuner_cache, check=True)
    out = json.loads(r.stdout)
    assert len(out["worker"]["trials_run"]) == 2 and min(out["worker"]["trials_run"]) >= 4
    assert out["counts"]["complete"] + out["counts"]["pruned"] == 6
    # same name, different search space / budget: one line, exit 2, nothing run
    for extra, needle in ((["--fix", "strategy=either"], "different search space"),
                          (["--budget", "0.3"], "budget 0.1"),
                          (["--scenes", "entry-P10"], "different validation data")):
        r = tune(*quick(d, "--n-trials", "8", "--no-test", *extra), cache=tuner_cache)
        assert r.returncode == 2, r.stderr
        assert needle in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr
    assert len(load(study_run["storage"], study_run["name"]).trials) == 6
    assert not list((d / study_run["name"]).glob("earlier-*"))  # a resume sets nothing aside


def test_a_new_study_keeps_an_earlier_studys_results_in_its_folder(study_run, tuner_cache, tmp_path):
    """optuna.db deleted (or another --storage on this studies folder): `tune` created the study anew and, once its
    trials had run, overwrote the earlier study's frozen.yaml and test.json without a word. Now they are moved into
    the folder's earlier-<time>/ (said in one warning) before the new study writes anything."""
    d = tmp_path / "st"
    copy_studies(study_run["dir"], d)
    name = study_run["name"]
    before = {f: (d / name / f).read_bytes() for f in ("frozen.yaml", "test.json")}
    (d / "optuna.db").unlink()
    r = tune(*quick(d, "--n-trials", "2", "--seed", "11", "--no-test"), cache=tuner_cache, check=True)
    kept = list((d / name).glob("earlier-*"))
    assert len(kept) == 1 and kept[0].is_dir(), list((d / name).iterdir())
    for f, data in before.items():
        assert (kept[0] / f).read_bytes() == data
    warn = [ln for ln in r.stderr.splitlines() if "earlier study" in ln]
    assert len(warn) == 1 and str(kept[0]) in warn[0] and warn[0].startswith("warning: "), r.stderr
    new = yaml.safe_load((d / name / "frozen.yaml").read_text())
    assert new["study"] == name and yaml.safe_load(before["frozen.yaml"]) != new
    assert not (d / name / "test.json").exists()  # --no-test: the earlier test is not this study's


def test_tune_test_command(study_run, tuner_cache):
    r = tune("test", "--study", study_run["name"], "--studies-dir", str(study_run["dir"]), "--runs", "2", "--json",
             cache=tuner_cache, check=True)
    t = json.loads(r.stdout)
    assert len(t["runs"]) == 2 and t["study"] == study_run["name"]
    assert t["reference"] is not None  # the paper defaults, by default
    # asked again without a reference: the result above (same runs, plus its reference) is reused, not re-measured
    r = tune("test", "--study", study_run["name"], "--studies-dir", str(study_run["dir"]), "--runs", "2", "--json",
             "--reference", "none", "--reuse", cache=tuner_cache, check=True)
    assert json.loads(r.stdout) == t
    # ... but with other runs it is not
    r = tune("test", "--study", study_run["name"], "--studies-dir", str(study_run["dir"]), "--runs", "1", "--json",
             "--reference", "none", "--reuse", cache=tuner_cache, check=True)
    again = json.loads(r.stdout)
    assert len(again["runs"]) == 1 and again["reference"] is None
    r = tune("test", "--study", study_run["name"], "--studies-dir", str(study_run["dir"]), "--quiet",
             cache=tuner_cache, check=True)
    assert "Herz-Jesus-P8" in r.stdout and "mAA10" in r.stdout
    assert f"-> {study_run['dir'] / study_run['name'] / 'test.json'}" in r.stdout  # where it wrote, truly



def test_tune_test_keeps_the_studys_pairs_per_scene(study_run, tuner_cache):
    """`tune test --study NAME` (README: "reruns it") of a study tuned and tested with --max-pairs 8 tested every
    pair of the test scenes: Task.from_options let the command's unset --max-pairs (None) wipe the study's 8. It
    now tests the study's pairs unless --max-pairs is given."""
    from pipeline.tasks.stereo import StereoTask
    assert StereoTask.from_options({"min_covisibility": 0.1, "max_pairs": 8}, max_pairs=None).max_pairs == 8
    assert StereoTask.from_options({"min_covisibility": 0.1, "max_pairs": 8}, max_pairs=3).max_pairs == 3
    r = tune("test", "--study", study_run["name"], "--studies-dir", str(study_run["dir"]), "--runs", "1", "--json",
             "--reference", "none", "--quiet", cache=tuner_cache, check=True)
    t = json.loads(r.stdout)
    assert t["task_options"]["max_pairs"] == 8 and t["mean"]["scenes"]["Herz-Jesus-P8"]["pairs"] == 8, t["task_options"]


def test_a_test_on_the_validation_scene_says_it_is_not_held_out(study_run, tuner_cache, tmp_path):
    """Allowed, and said (as `tune run` says it for --test-scenes); on a copy of the frozen file in another studies
    folder, so the study's own test.json stays as the other tests read it."""
    src = study_run["dir"] / study_run["name"] / "frozen.yaml"
    (tmp_path / study_run["name"]).mkdir()
    shutil.copy(src, tmp_path / study_run["name"] / "frozen.yaml")
    r = tune("test", "--study", study_run["name"], "--studies-dir", str(tmp_path), "--quiet", "--runs", "1",
             "--reference", "none", "--scenes", "fountain-P11", "--max-pairs", "2", cache=tuner_cache, check=True)
    assert "warning: test scene fountain-P11 is also a validation scene" in r.stderr and "not held out" in r.stderr
    assert (tmp_path / study_run["name"] / "test.json").is_file()


@pytest.fixture(scope="module")
def two_studies(study_run, tuner_cache):
    """A second estimator on the same storage (magsac++), for the tables."""
    tune(*quick(study_run["dir"], "--n-trials", "3", "--json", ransac="magsac++"), cache=tuner_cache, check=True)
    return study_run


def test_settings_table_formats(two_studies, tuner_cache):
    d = two_studies["dir"]
    md = tune("table", "--studies-dir", str(d), cache=tuner_cache, check=True).stdout
    head = md.splitlines()[0]
    for col in ("feature", "features", "eta degensac", "eta magsac++", "| r "):
        assert col in head, head
    rows = [ln for ln in md.splitlines() if ln.startswith("| sift")]
    assert len(rows) == 1 and "2048" in rows[0]
    csv_out = tune("table", "--studies-dir", str(d), "--format", "csv", cache=tuner_cache, check=True).stdout
    import csv
    import io
    recs = list(csv.DictReader(io.StringIO(csv_out)))
    assert recs[0]["feature"] == "sift" and 0.1 <= float(recs[0]["eta degensac"]) <= 2.0
    assert 0.5 <= float(recs[0]["eta magsac++"]) <= 10.0 and 0.6 <= float(recs[0]["r"]) <= 1.0
    tex = tune("table", "--studies-dir", str(d), "--format", "latex", cache=tuner_cache, check=True).stdout
    assert tex.startswith(r"\begin{table}") and r"\caption{" in tex and r"\begin{tabular}" in tex
    assert r"\toprule" in tex and r"\bottomrule" in tex and r"$\Gamma$ degensac" in tex
    js = json.loads(tune("table", "--studies-dir", str(d), "--format", "json", cache=tuner_cache, check=True).stdout)
    assert set(js[0]["studies"]) == {"degensac", "magsac++"}
    bad = tune("table", "--studies-dir", str(d), "--format", "xml", cache=tuner_cache)
    assert bad.returncode == 2 and "unknown format" in bad.stderr
    # the paper's table names the multiview r even when no multiview study was run; `--task stereo` asks for the
    # stereo settings alone and had an empty r_multiview column
    assert "| r_multiview |" in head
    st = tune("table", "--studies-dir", str(d), "--task", "stereo", cache=tuner_cache, check=True).stdout
    assert "r_multiview" not in st and "| eta degensac |" in st.splitlines()[0], st


def test_results_table(two_studies, tuner_cache):
    d = two_studies["dir"]
    md = tune("results", "--studies-dir", str(d), cache=tuner_cache, check=True).stdout
    head = md.splitlines()[0]
    for col in ("rank", "NF", "NI degensac", "mAA10 degensac", "NI magsac++", "mAA10 magsac++"):
        assert col in head, head
    js = json.loads(tune("results", "--studies-dir", str(d), "--format", "json", cache=tuner_cache,
                         check=True).stdout)
    assert js[0]["rank"] == 1 and js[0]["NF"] == pytest.approx(2048, rel=0.1)
    assert 0 <= js[0]["mAA10 degensac"] <= 1 and 0 <= js[0]["mAA10 magsac++"] <= 1


def _nan_pair_error(p: Path) -> None:
    d = json.loads(p.read_text())
    d["runs"][0]["pair_errors"][0][2] = float("nan")  # json.dumps writes NaN
    p.write_text(json.dumps(d))


@pytest.mark.parametrize("damage, why", [
    (b'{"study": "cut sho', "not valid JSON"),
    (b"[]", "not a test result"),
    (b"\xff\xfe\x00binary", "not UTF-8 text"),
    (_nan_pair_error, "a pair error of nan degrees"),
], ids=["cut-short", "json-list", "binary", "nan-pair-error"])
def test_a_damaged_test_json_is_said_never_a_crash_or_silence(damage, why, two_studies, tuner_cache, tmp_path):
    """A test.json cut short, binary or a JSON list was skipped without a word (tune results then took the interval
    from the stored summary and ranked ties unpaired), a NaN pair error went into the bootstrap, and `tune test`
    / `tune findings` rechecking a list crashed ('list' object has no attribute 'get'). Now: a warning naming the
    file and what to run, the study's row kept from its stored summary, the report says so, the test is rerun."""
    d = tmp_path / "st"
    copy_studies(two_studies["dir"], d)
    name = two_studies["name"]
    p = d / name / "test.json"
    assert p.is_file()
    good = json.loads(tune("results", "--studies-dir", str(d), "--format", "json", cache=tuner_cache,
                           check=True).stdout)
    damage(p) if callable(damage) else p.write_bytes(damage)
    r = tune("results", "--studies-dir", str(d), "--format", "json", cache=tuner_cache)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    # (another test of this module may have retested a study on other pairs: that warning is not this test's)
    warn = [ln for ln in r.stderr.splitlines() if ln.startswith("warning: ") and "different test sets" not in ln]
    assert len(warn) == 1 and str(p) in warn[0] and why in warn[0], r.stderr
    assert f"rerun `tune test --study {name}`" in warn[0]
    rows = json.loads(r.stdout)
    assert rows[0]["mAA10 degensac"] == pytest.approx(good[0]["mAA10 degensac"])  # the stored summary's value
    rep = tune("plot", "--study", name, "--studies-dir", str(d), cache=tuner_cache, check=True)
    assert f"test.json cannot be read ({why.split(':')[0]}" in Path(rep.stdout.strip()).read_text() or callable(damage)
    if damage == b"[]":  # --reuse rechecks the file: it is rerun and rewritten, not a crash
        t = tune("test", "--study", name, "--studies-dir", str(d), "--reuse", "--runs", "1", "--quiet",
                 cache=tuner_cache)
        assert t.returncode == 0 and "Traceback" not in t.stderr, t.stderr
        assert isinstance(json.loads(p.read_text()), dict)


def test_results_says_when_studies_were_tested_on_different_test_sets(two_studies, tuner_cache, tmp_path):
    """`tune test --scenes` on one study left `tune results` ranking its mAA(10), measured on other pairs, beside
    the others' without a word. Now a warning naming the test sets, and a 'test set' column."""
    d = tmp_path / "st"
    copy_studies(two_studies["dir"], d)
    same = tune("results", "--studies-dir", str(d), cache=tuner_cache, check=True)
    sets = {(tuple(t["scenes"]), t["pairs"]) for t in (json.loads((d / n / "test.json").read_text())["data"]
                                                       for n in ("sift-2048-degensac-stereo", "sift-2048-magsac++-stereo"))}
    if len(sets) == 1:  # as the fixture made them (another test of this module may retest one on other pairs)
        assert "test set" not in same.stdout and "different test sets" not in same.stderr
    earlier = json.loads((d / "sift-2048-magsac++-stereo" / "test.json").read_text())
    t = tune("test", "--study", "sift-2048-magsac++-stereo", "--studies-dir", str(d), "--scenes", "entry-P10",
             "--runs", "1", "--max-pairs", "3", "--quiet", cache=tuner_cache, check=True)
    # the earlier test (another test set) is kept aside, not replaced, and said
    kept = list((d / "sift-2048-magsac++-stereo").glob("earlier-*/test.json"))
    assert len(kept) == 1 and json.loads(kept[0].read_text()) == earlier
    said = [ln for ln in t.stderr.splitlines() if "earlier test.json" in ln]
    assert len(said) == 1 and str(kept[0]) in said[0] and "Herz-Jesus-P8" in said[0], t.stderr
    r = tune("results", "--studies-dir", str(d), "--format", "json", cache=tuner_cache, check=True)
    warn = [ln for ln in r.stderr.splitlines() if "different test sets" in ln]
    assert len(warn) == 1 and "entry-P10 (3 pairs)" in warn[0] and "Herz-Jesus-P8 (" in warn[0], r.stderr
    row = json.loads(r.stdout)[0]
    best = row["best"]
    assert row["test set"] == "entry-P10 (3 pairs)" if best == "magsac++" else row["test set"].startswith(
        "Herz-Jesus-P8 ("), row


def _edit_test_json(edit):
    def damage(p: Path) -> None:
        d = json.loads(p.read_text())
        edit(d)
        p.write_text(json.dumps(d))
    return damage


@pytest.mark.parametrize("damage, why", [
    (_edit_test_json(lambda d: d["mean"].__setitem__("mAA10", "high")), "mean.mAA10 is not a number: 'high'"),
    (_edit_test_json(lambda d: d.__setitem__("mean", [1])), "mean is not an object"),
    (_edit_test_json(lambda d: d["mean"].__setitem__("scenes", "entry-P10")), "mean.scenes is not an object"),
    (_edit_test_json(lambda d: d["data"].__setitem__("scenes", "entry-P10")), "data.scenes is not a list"),
], ids=["mean-value-text", "mean-list", "scenes-text", "data-scenes-text"])
def test_a_test_json_with_figures_of_the_wrong_type_is_said(damage, why, two_studies, tuner_cache, tmp_path):
    """A hand-edited test.json whose figures are of the wrong type ("mAA10": "high", "mean": [1], ...) passed the
    reader's check and was "tune: internal error: ValueError / AttributeError" in tune results, tune plot and
    tune test --reuse. Now it is a damaged test.json like any other: named in a warning, rerun by --reuse."""
    d = tmp_path / "st"
    copy_studies(two_studies["dir"], d)
    name = two_studies["name"]
    p = d / name / "test.json"
    damage(p)
    r = tune("results", "--studies-dir", str(d), "--format", "json", cache=tuner_cache)
    assert r.returncode == 0 and "internal error" not in r.stderr, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if ln.startswith("warning: ") and "different test sets" not in ln]
    assert len(warn) == 1 and f"{p} cannot be read ({why}" in warn[0], r.stderr
    rep = tune("plot", "--study", name, "--studies-dir", str(d), cache=tuner_cache)
    assert rep.returncode == 0, rep.stderr
    t = tune("test", "--study", name, "--studies-dir", str(d), "--reuse", "--runs", "1", "--quiet", cache=tuner_cache)
    assert t.returncode == 0 and "internal error" not in t.stderr, t.stderr
    from tuner.freeze import load_test_file
    assert load_test_file(p)[1] is None  # rerun and rewritten whole


def test_a_test_json_of_another_study_is_never_taken_for_this_ones(two_studies, tuner_cache, tmp_path):
    """A study folder's test.json copied from another study (a folder copied under a new name): `tune results` took
    its pair errors for this study's interval and paired ties (this study's mAA10 with the other's interval) and
    `tune plot` drew the other study's test as this one's, without a word. Now it is named in a warning (report: a
    red line) and the study's numbers come from its own stored summary."""
    d = tmp_path / "st"
    copy_studies(two_studies["dir"], d)
    name = two_studies["name"]
    other = next(p.parent.name for p in d.glob("*/test.json") if p.parent.name != name)
    good = json.loads(tune("results", "--studies-dir", str(d), "--format", "json", cache=tuner_cache,
                           check=True).stdout)
    p = d / name / "test.json"
    shutil.copyfile(d / other / "test.json", p)
    r = tune("results", "--studies-dir", str(d), "--format", "json", cache=tuner_cache)
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if ln.startswith("warning: ") and "different test sets" not in ln]
    assert len(warn) == 1 and f"{p} cannot be read (it holds the test of study {other!r}, not {name!r}" in warn[0], \
        r.stderr
    assert json.loads(r.stdout)[0]["mAA10 degensac"] == pytest.approx(good[0]["mAA10 degensac"])
    rep = tune("plot", "--study", name, "--studies-dir", str(d), cache=tuner_cache, check=True)
    html = Path(rep.stdout.strip()).read_text()
    assert "test.json cannot be read (it holds the test of study" in html


def test_plot_html_report(two_studies, tuner_cache):
    d = two_studies["dir"]
    r = tune("plot", "--study", two_studies["name"], "--studies-dir", str(d), cache=tuner_cache, check=True)
    path = Path(r.stdout.strip())
    assert path == d / two_studies["name"] / "report.html"
    html = path.read_text()
    assert two_studies["name"] in html and "plotly" in html.lower()
    for section in ("Optimization history", "Parameter importances", "over inlier threshold eta and ratio test r",
                    "vs estimator CPU time per pair", "vs RANSAC iteration cap Gamma", "vs inlier threshold eta"):
        assert section in html, section
    assert html.count('class="plotly-graph-div"') >= 4
    # the across-studies eta curves include the other study when it has 2 trials within budget (its 3 trials can
    # all time over B on a loaded machine: then the rule leaves it out, which is checked instead)
    rows = json.loads(tune("studies", "--studies-dir", str(d), "--json", cache=tuner_cache, check=True).stdout)
    other = [r for r in rows if r["study"] == "sift-2048-magsac++-stereo"]
    assert len(other) == 1, rows
    ok = other[0]["complete"] - other[0]["infeasible"]  # its trials within budget (each searches eta)
    assert ("magsac++" in html) == (ok >= 2), other


def test_no_feasible_trial(tmp_path, tuner_cache):
    args = quick(tmp_path, "--n-trials", "2", "--budget", "0.000001", "--study", "hopeless")
    r = tune(*args, cache=tuner_cache)
    assert r.returncode == 2 and "no feasible completed trial" in r.stderr, r.stderr
    # the line says what became of each trial, as the storage holds them (a CI failure once read only "all over
    # the budget, pruned or failed", and nobody could tell which)
    import re

    from optuna.trial import TrialState
    trials = load(f"sqlite:///{tmp_path}/optuna.db", "hopeless").get_trials()
    over = sum(t.state == TrialState.COMPLETE for t in trials)
    pruned = sum(t.state == TrialState.PRUNED for t in trials)
    assert len(trials) == 2 and over + pruned == 2, [t.state for t in trials]
    line = r.stderr.strip().splitlines()[-1]
    assert "(2 trials: " in line, line
    assert (f"{over} over the 1e-06 s budget [fastest median " in line) == (over > 0), line
    assert (f"{pruned} pruned [#" in line) == (pruned > 0), line
    if over:
        fastest = min(t.user_attrs["ransac_seconds_median"] for t in trials if t.state == TrialState.COMPLETE)
        assert float(re.search(r"fastest median ([0-9.e+-]+) s", line).group(1)) == pytest.approx(fastest, rel=1e-2)
    r = tune("test", "--study", "hopeless", "--studies-dir", str(tmp_path), cache=tuner_cache)
    assert r.returncode == 2 and "no feasible completed trial" in r.stderr and "(2 trials: " in r.stderr
    assert r.stderr.strip().count("\n") == 0
    assert not (tmp_path / "hopeless" / "frozen.yaml").exists()


def _finished_numbers(storage, name):
    from optuna.trial import TrialState
    st = load(storage, name)
    return st, sorted(t.number for t in st.trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED))


def test_two_sqlite_workers(tmp_path, tuner_cache):
    args = quick(tmp_path, "--n-trials", "8", "--no-test", "--json", "--study", "shared")
    env = dict(os.environ, IMTUNE_CACHE=tuner_cache)
    procs = [subprocess.Popen([sys.executable, "-m", "tuner", *args], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (_so, se) in zip(procs, outs):
        assert p.returncode == 0, se[-2000:]
        assert "database is locked" not in se
    runs = [set(json.loads(so)["worker"]["trials_run"]) for so, _ in outs]
    assert runs[0] and runs[1] and not (runs[0] & runs[1])  # both worked, no trial twice
    st, numbers = _finished_numbers(f"sqlite:///{tmp_path}/optuna.db", "shared")
    assert set(numbers) == runs[0] | runs[1]  # every trial recorded, none lost
    assert len(numbers) == 8  # exactly the target (tuner/workers.py)
    # a trial two workers created in the same instant is a surplus trial: failed unevaluated, no parameter
    left = [t for t in st.trials if t.number not in set(numbers)]
    assert all(t.state.name == "FAIL" and t.user_attrs.get("surplus") and not t.params for t in left), left
    assert len({t.number for t in st.trials}) == len(st.trials)


def test_kill9_then_resume(tmp_path, tuner_cache):
    from optuna.trial import TrialState
    storage = f"sqlite:///{tmp_path}/optuna.db"
    # slow-ish trials (Gamma pinned high, eta small) so the kill lands inside a trial
    args = quick(tmp_path, "--n-trials", "6", "--no-test", "--study", "killme", "--heartbeat", "1",
                 "--fix", "max_iters=150000", "--fix", "threshold=0.2", "--budget", "5", "--chunk-pairs", "8")
    env = dict(os.environ, IMTUNE_CACHE=tuner_cache)
    p = subprocess.Popen([sys.executable, "-m", "tuner", *args, "--quiet"], cwd=ROOT, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    before = []
    try:
        deadline = time.time() + 300
        while time.time() < deadline and p.poll() is None:
            time.sleep(0.2)
            if not (tmp_path / "optuna.db").exists():
                continue
            try:
                _, before = _finished_numbers(storage, "killme")
            except Exception:  # noqa: BLE001 - study not created yet
                continue
            if len(before) >= 2:
                break
        assert p.poll() is None, "the worker ended before it could be killed"
        os.kill(p.pid, signal.SIGKILL)
        p.wait(timeout=30)
    finally:
        if p.poll() is None:
            os.kill(p.pid, signal.SIGKILL)
    st, after_kill = _finished_numbers(storage, "killme")
    assert set(before) <= set(after_kill)  # nothing committed was lost
    assert len(after_kill) < 6
    time.sleep(3.5)  # past the grace period (3 heartbeats of 1 s): the interrupted trial is dead
    r = tune(*args, "--json", cache=tuner_cache, check=True)
    out = json.loads(r.stdout)
    st, final = _finished_numbers(storage, "killme")
    assert set(after_kill) <= set(final) and len(final) == 6
    states = [t.state for t in st.trials]
    assert TrialState.RUNNING not in states and TrialState.WAITING not in states
    assert out["frozen"]["trial"] in final
    # a trial the kill interrupted was failed by the heartbeat check and its parameters retried once
    for t in st.trials:
        if t.state == TrialState.FAIL:
            assert any(u.system_attrs.get("failed_trial") == t.number for u in st.trials), t.number


def test_journal_storage_and_password_free_attrs(tmp_path, tuner_cache):
    j = tmp_path / "journal" / "optuna.log"
    r = tune(*quick(tmp_path, "--n-trials", "2", "--no-test", "--json", "--storage", f"journal:{j}"),
             cache=tuner_cache, check=True)
    out = json.loads(r.stdout)
    assert out["storage"] == f"journal:{j}" or str(j) in out["storage"]
    assert j.is_file()
    st = load(f"journal:{j}", out["study"])
    assert len(st.trials) == 2
    # user attributes never carry a storage URL (so never a password)
    assert "://" not in json.dumps(st.user_attrs).replace("sqlite:", "")


def test_calibrate_command(tmp_path, tuner_cache):
    args = ["calibrate", "--data", str(STRECHA), "--feature", "sift", "--num-features", "2048", "--ransac", "degensac",
            "--scenes", "fountain-P11", "--max-pairs", "8", "--pairs", "4", "--budget", "0.02", "--budget", "0.08",
            "--studies-dir", str(tmp_path), "--json"]
    r = tune(*args, cache=tuner_cache, check=True)
    out = json.loads(r.stdout)
    g = out["gamma_max"]
    assert set(g) == {"0.02", "0.08"} and 1 <= g["0.02"] <= g["0.08"] <= 1_000_000
    curve = out["calibration"]["curve"]
    assert len(curve) >= 2 and [c[0] for c in curve] == sorted(c[0] for c in curve)
    assert curve[-1][1] > 0.08 or curve[-1][0] >= 1_000_000  # measured past the largest budget
    stored = json.loads((tmp_path / "budgets.json").read_text())
    assert len(stored) == 1 and next(iter(stored.values()))["estimator"] == "degensac"
    again = json.loads(tune(*args, cache=tuner_cache, check=True).stdout)  # reused, not re-measured
    assert again["calibration"]["created"] == out["calibration"]["created"]
    md = tune(*args[:-1], "--quiet", cache=tuner_cache, check=True).stdout
    assert "Gamma_max(0.08 s)" in md and "max_iters" in md
    bad = tune("calibrate", "--ransac", "nosuch", "--data", str(STRECHA), "--studies-dir", str(tmp_path), cache=tuner_cache)
    assert bad.returncode == 2 and "unknown estimator 'nosuch'" in bad.stderr


@pytest.mark.parametrize("sampler", ["grid", "random", "cmaes"])
def test_other_samplers(tmp_path, tuner_cache, sampler):
    if sampler == "cmaes":
        pytest.importorskip("cmaes", reason="Optuna's CMA-ES sampler needs the cmaes package (pip install cmaes)")
    space = tmp_path / "small.yaml"
    space.write_text("params:\n"
                     "  ratio: {low: 0.7, high: 0.9, grid: [0.75, 0.85]}\n"
                     "  threshold: {low: 0.3, high: 1.0, log: true, grid: [0.4, 0.8]}\n"
                     "  max_iters: {type: int, low: 1000, high: calibrated, log: true}\n")
    n = [] if sampler == "grid" else ["--n-trials", "3"]
    r = tune(*quick(tmp_path, "--sampler", sampler, "--space", str(space), "--no-test", "--json", *n, pairs=4),
             cache=tuner_cache, check=True)
    out = json.loads(r.stdout)
    # CMA-ES printed Optuna's "Constraints have been set, but CmaEsSampler will not use them" after every trial
    assert "Warning" not in r.stderr and "optuna_warn" not in r.stderr, r.stderr
    st = load(f"sqlite:///{tmp_path}/optuna.db", out["study"])
    params = [(t.params["ratio"], t.params["threshold"]) for t in st.trials]
    if sampler == "grid":  # the whole 2 x 2 grid, each point once, Gamma at the cap
        assert sorted(params) == [(0.75, 0.4), (0.75, 0.8), (0.85, 0.4), (0.85, 0.8)]
        assert {t.params["max_iters"] for t in st.trials} == {st.user_attrs["budget"]["gamma_max"]}
    else:
        assert len(params) == 3 and all(0.7 <= r <= 0.9 and 0.3 <= e <= 1.0 for r, e in params)
    assert st.user_attrs["sampler"] == sampler


def test_ctrl_c_keeps_completed_trials(tmp_path, tuner_cache):
    from optuna.trial import TrialState
    args = quick(tmp_path, "--n-trials", "50", "--no-test", "--study", "interrupted", "--budget", "5",
                 "--fix", "max_iters=150000", "--fix", "threshold=0.2", "--chunk-pairs", "8")
    env = dict(os.environ, IMTUNE_CACHE=tuner_cache)
    p = subprocess.Popen([sys.executable, "-m", "tuner", *args, "--quiet"], cwd=ROOT, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    storage = f"sqlite:///{tmp_path}/optuna.db"
    deadline = time.time() + 300
    done = []
    while time.time() < deadline and p.poll() is None:
        time.sleep(0.2)
        try:
            st, done = _finished_numbers(storage, "interrupted")
        except Exception:  # noqa: BLE001 - not created yet
            continue
        if len(done) >= 2 and any(t.state == TrialState.RUNNING and t.params for t in st.trials):
            break  # a trial is under way with its parameters drawn (tests/test_interrupt_window.py: before that)
    p.send_signal(signal.SIGINT)  # one Ctrl-C: also one landing in a weakref callback stops it (tuner/cli.py)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130 and "interrupted" in err and "Traceback" not in err, (p.returncode, err[-2000:])
    assert "Exception ignored" not in err, err
    st, after = _finished_numbers(storage, "interrupted")
    assert set(done) <= set(after)
    assert not [t for t in st.trials if t.state == TrialState.RUNNING]  # the interrupted trial is FAIL, not RUNNING
    # the interrupted trial's parameters are the resume's first trial
    failed = [t for t in st.trials if t.state == TrialState.FAIL]
    waiting = [t for t in st.trials if t.state == TrialState.WAITING]
    assert len(failed) == 1 and failed[0].params, [(t.number, t.state, t.params) for t in st.trials]
    assert [(t.params, t.system_attrs.get("retry_history")) for t in waiting] == [(failed[0].params, [failed[0].number])]
    resume = [a if a != "50" else str(len(after) + 1) for a in args]
    r = subprocess.run([sys.executable, "-m", "tuner", *resume, "--quiet"], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    st, again = _finished_numbers(storage, "interrupted")
    assert len(again) == len(after) + 1
    retry = st.trials[waiting[0].number]
    assert retry.state == TrialState.COMPLETE and retry.params == failed[0].params
