"""`tune --task multiview` on real data: a tiny multiview study (6 images of Strecha fountain-P11 with
their built ground truth, 1024 SIFT, 3 bags of 5, 2 trials) through the CLI, real pycolmap; the study's
attributes, frozen.yaml, `tune test`, `tune table` (r_multiview) and `tune plot`. Skips when
../shared/data/strecha is absent."""
import json
import os

import pytest
import yaml

from tests.conftest import copy_strecha_subset

IMAGES = ["0002.jpg", "0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg", "0007.jpg"]
STUDY = "sift-1024-degensac-multiview"


@pytest.fixture(scope="module")
def mv_study(tmp_path_factory):
    root = copy_strecha_subset(tmp_path_factory.mktemp("data"), IMAGES)
    cache = tmp_path_factory.mktemp("cache")
    studies = tmp_path_factory.mktemp("studies")
    saved = {k: os.environ.pop(k, None) for k in ("IMTUNE_CACHE", "IMTUNE_GT", "IMTUNE_STUDIES")}
    os.environ["IMTUNE_CACHE"] = str(cache)  # ground truth goes to $IMTUNE_CACHE/gt
    try:
        from tuner.cli import main
        assert main(["data", "build-gt", "--data", str(root), "--num-features", "1024", "--max-image-size", "1024",
                     "--quiet"]) == 0
        import contextlib
        import io
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            assert main(["--data", str(root), "--feature", "sift", "--num-features", "1024", "--ransac", "degensac",
                         "--task", "multiview", "--bags", "5:3", "--workers", "1", "--n-trials", "2",
                         "--scenes", "fountain-P11", "--test-scenes", "fountain-P11", "--no-test",
                         "--studies-dir", str(studies), "--quiet"]) == 0
        # no estimator budget applies to a multiview study: its trial counts said "(0 over budget)"
        assert "trials: 2 complete, 0 pruned" in printed.getvalue() and "over budget" not in printed.getvalue(), \
            printed.getvalue()
        yield root, studies
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def run_cli(args, capsys):
    from tuner.cli import main
    capsys.readouterr()
    rc = main(args)
    return rc, capsys.readouterr().out


def test_multiview_study_trials_and_frozen(mv_study):
    import optuna
    from optuna.trial import TrialState
    root, studies = mv_study
    st = optuna.load_study(study_name=STUDY, storage=f"sqlite:///{studies / 'optuna.db'}")
    assert st.user_attrs["task"] == "multiview"
    assert st.user_attrs["task_options"]["bags"] == [[5, 3]]
    done = st.get_trials(states=(TrialState.COMPLETE,))
    assert len(done) == 2
    for t in done:
        assert set(t.params) == {"ratio"}  # no eta / Gamma: COLMAP runs its own RANSAC
        ua = t.user_attrs
        for k in ("mAA5", "mAA10", "SR", "RC", "NL", "TL", "bags", "accuracy", "by_size", "scenes"):
            assert k in ua, k
        assert ua["bags"] == 3 and list(ua["by_size"]) == ["5"]
        # its timing said {"pairs": 3, "budget": 0.5, "ransac_seconds_total": 0.0}: 3 bags, no budget, nothing timed
        assert ua["timing"]["bags"] == 3 and not {"pairs", "budget", "ransac_seconds_total"} & set(ua["timing"]), ua
        assert t.value == pytest.approx(ua["mAA10"]) and 0.0 <= t.value <= 1.0
        assert len(ua["scenes"]["fountain-P11"]["accuracy"]) == 10
    frozen = yaml.safe_load((studies / STUDY / "frozen.yaml").read_text())
    assert frozen["task"] == "multiview" and 0.6 <= frozen["params"]["ratio"] <= 1.0
    assert "threshold" not in frozen["fixed"] and "max_iters" not in frozen["fixed"]
    assert frozen["task_options"]["bags"] == [[5, 3]]


def test_multiview_test_table_and_plot(mv_study, capsys):
    root, studies = mv_study
    # the test bags are the validation bags here: every bag record comes from the cache
    rc, out = run_cli(["test", "--study", STUDY, "--studies-dir", str(studies), "--data", str(root),
                       "--scenes", "fountain-P11", "--runs", "1", "--workers", "1", "--json", "--quiet"], capsys)
    assert rc == 0
    res = json.loads(out)
    assert res["task"] == "multiview" and res["mean"]["bags"] == 3 and 0.0 <= res["mean"]["mAA10"] <= 1.0
    assert (studies / STUDY / "test.json").is_file()
    rc, out = run_cli(["table", "--studies-dir", str(studies), "--format", "json"], capsys)
    assert rc == 0
    rows = json.loads(out)
    sift = [r for r in rows if r["feature"] == "sift" and r["features"] == 1024]
    assert len(sift) == 1 and 0.6 <= sift[0]["r_multiview"] <= 1.0
    rc, out = run_cli(["plot", "--study", STUDY, "--studies-dir", str(studies)], capsys)
    assert rc == 0
    html = (studies / STUDY / "report.html").read_text()
    assert "Accuracy vs angular threshold" in html and "fountain-P11 - test" in html
    assert "1 run, trial" in html and "1 runs" not in html  # it read "test (1 runs, trial 0)"


def test_multiview_test_table_has_no_empty_column(mv_study, capsys):
    """`tune test` of a multiview study printed a 'seconds' column of '-' in every row (the test runs' figures
    never carry the bags' seconds): a column the test result has no value for is left out."""
    root, studies = mv_study
    rc, out = run_cli(["test", "--study", STUDY, "--studies-dir", str(studies), "--data", str(root),
                       "--scenes", "fountain-P11", "--runs", "1", "--workers", "1", "--quiet"], capsys)
    assert rc == 0
    lines = out.splitlines()
    starts = [i for i, ln in enumerate(lines) if ln.startswith("| scene")]  # a wide table is split by columns
    seen, empty = [], []
    for s in starts:
        table = [ln for ln in lines[s:] if ln.startswith("|")]
        table = table[:next((k for k, ln in enumerate(table[1:], 1) if ln.startswith("| scene")), len(table))]
        header = [c.strip() for c in table[0].strip("|").split("|")]
        cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in table[2:]]
        assert cells, out
        seen += header
        empty += [h for i, h in enumerate(header) if all(row[i] in ("-", "") for row in cells)]
    assert "mAA10" in seen and not empty, (empty, out)


def test_multiview_reference_names_only_what_the_task_uses(mv_study, capsys):
    """The test of a multiview study said "vs paper defaults (r 0.85 both, eta 0.5 px, Gamma 50,000)": COLMAP
    runs its own RANSAC, eta and Gamma play no part in it. The label names what the reference sets: r and the
    strategy."""
    root, studies = mv_study
    rc, out = run_cli(["test", "--study", STUDY, "--studies-dir", str(studies), "--data", str(root),
                       "--scenes", "fountain-P11", "--runs", "1", "--workers", "1", "--quiet"], capsys)
    assert rc == 0
    assert "vs paper defaults (r 0.85 both):" in out and "Gamma 50,000" not in out, out


def test_a_multiview_study_label_names_no_estimator_setting(mv_study):
    """`tune viz --study <multiview study>` titled its bags "... · degensac eta 0.5 px, Gamma 1000": values the
    study never used (COLMAP verifies the matches with its own RANSAC). Its label names COLMAP instead."""
    from tuner.sources import load_study_source
    root, studies = mv_study
    label = load_study_source(STUDY, studies).label
    assert "COLMAP" in label and "Γ" not in label and "η" not in label and "Gamma" not in label, label
    from pipeline.config_files import load_config_file
    label = load_config_file(studies / STUDY / "frozen.yaml").label
    assert "COLMAP" in label and "Γ" not in label, label


def _tested_results(mv_study, capsys) -> str:
    """`tune test` of the module's study (1 run on fountain-P11), then `tune results --task multiview`: its output."""
    root, studies = mv_study
    rc, _ = run_cli(["test", "--study", STUDY, "--studies-dir", str(studies), "--data", str(root),
                     "--scenes", "fountain-P11", "--runs", "1", "--workers", "1", "--quiet"], capsys)
    assert rc == 0
    rc, out = run_cli(["results", "--task", "multiview", "--studies-dir", str(studies)], capsys)
    assert rc == 0
    return out


def test_multiview_results_table_has_no_empty_column(mv_study, capsys):
    """`tune results --task multiview` showed 'NF' and 'NI degensac' columns of '-' in every row (a multiview test
    records neither features per image nor estimator inliers): a column no row has a value for is left out."""
    out = _tested_results(mv_study, capsys)
    table = [ln for ln in out.splitlines() if ln.startswith("|")]
    header = [c.strip() for c in table[0].strip("|").split("|")]
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in table[2:]]
    assert "rank" in header and cells, out
    empty = [h for i, h in enumerate(header) if all(row[i] in ("-", "") for row in cells) and h != "ties"]
    assert not empty, (empty, out)
    # COLMAP reconstructs the bags: the column was headed 'mAA10 degensac', the caption spoke of NF, NI and pairs
    assert "mAA10 COLMAP" in header and "mAA10 degensac" not in header, out
    assert "over bags and runs" in out and "inliers per pair" not in out, out


@pytest.mark.parametrize("how", ["sigint", "sigterm"])
def test_interrupting_a_multiview_study_stops_its_colmap_workers_at_once(mv_study, tmp_path, how):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) or `kill PID` (SIGTERM to the parent alone)
    during a multiview trial: one line, exit 130 / 143, the COLMAP worker processes gone at once (no wait for the
    bags in flight or queued, no traceback per worker), the study resumable."""
    import signal
    import subprocess
    import sys
    import time

    from tests.conftest import ROOT
    from tests.test_parallel_pairs import _alive, wait_for_workers
    root, _ = mv_study
    studies = tmp_path / "studies"
    env = dict(os.environ)  # the fixture's IMTUNE_CACHE: the built ground truth and the features
    # 5:6: every distinct bag of 5 of the 6 images (asking 40 gave the same 6, and now a warning line saying so)
    args = ["--data", str(root), "--feature", "sift", "--num-features", "1024", "--ransac", "degensac",
            "--task", "multiview", "--bags", "5:6", "--workers", "2", "--n-trials", "20", "--scenes", "fountain-P11",
            "--no-test", "--studies-dir", str(studies), "--quiet"]
    p = subprocess.Popen([sys.executable, "-m", "tuner", *args], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        workers = wait_for_workers(p, 2)
        assert len(workers) == 2, ("the COLMAP pool never started", p.poll(), p.stderr.read() if p.poll() else "")
        time.sleep(3.0)  # inside their bags
        t0 = time.time()
        if how == "sigint":
            os.killpg(p.pid, signal.SIGINT)
        else:
            p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=60)
        stopped = time.time() - t0
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    assert p.returncode == {"sigint": 130, "sigterm": 143}[how], err[-2000:]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    said = {"sigint": "interrupted", "sigterm": "terminated (SIGTERM)"}[how]
    assert lines == [f"tune: {said}; completed trials are kept, rerun the same command to resume"], err[-3000:]
    deadline = time.time() + 10
    while time.time() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.1)
    assert not any(_alive(w) for w in workers), "COLMAP workers outlived the run"
    import optuna
    st = optuna.load_study(study_name=STUDY, storage=f"sqlite:///{studies / 'optuna.db'}")
    assert st.trials and not [t for t in st.trials if t.state.name == "RUNNING"]  # the interrupted trial: FAIL
    print(f"MULTIVIEW {how.upper()}: exit {p.returncode} after {stopped:.1f} s, workers {workers} gone")


@pytest.mark.parametrize("how", ["import_pycolmap", "require", "build_gt"])
def test_using_colmap_keeps_the_sigterm_handler(how, mv_study, tmp_path):
    """pycolmap's glog takes SIGTERM over when it loads (a stack trace, then death), which bypassed tune's graceful
    stop in any process that had used COLMAP (the full findings run died so after its multiview study, leaving its
    pool workers). Through the adapter the process keeps its own handler: a real SIGTERM reaches it."""
    import signal
    import subprocess
    import sys
    import time

    from tests.conftest import ROOT
    root, _ = mv_study
    call = {"import_pycolmap": "from pipeline.colmap_db import import_pycolmap; import_pycolmap()",
            "require": "from pipeline.geometry.base import require; require('pycolmap', 'pycolmap')",
            # what `tune findings` does in its own process before the multiview study: COLMAP triangulation
            "build_gt": ("from pathlib import Path; from tuner.evaluate import load_scenes; "
                         "from pipeline.data.ground_truth import GTConfig, build_ground_truth; "
                         f"(sc,) = load_scenes(Path({str(root)!r}), ['fountain-P11'], ground_truth=False); "
                         f"build_ground_truth(sc, {str(tmp_path / 'gt')!r}, GTConfig(num_features=1024), force=True)"),
            }[how]
    code = ("import signal, sys, time\n"
            "signal.signal(signal.SIGTERM, lambda s, f: sys.exit(7))\n"
            f"{call}\n"
            "import pycolmap; assert pycolmap.__version__\n"
            "print('ready', flush=True)\n"
            "time.sleep(60)\n")
    p = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    try:
        assert p.stdout.readline().strip() == "ready", p.stderr.read()[-3000:]
        time.sleep(0.2)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert p.returncode == 7 and "Aborted" not in err, (p.returncode, err[-2000:])


def test_evaluate_config_of_a_multiview_study_with_task_stereo_says_what_was_never_tuned(mv_study, capsys):
    """`tune evaluate --config STUDY --task stereo` of a multiview study ran its r with an eta and Gamma never
    tuned, unsaid (tune test / tune compare warn about the same): one warning line naming what runs untuned."""
    from tuner.cli import main
    root, studies = mv_study
    capsys.readouterr()
    rc = main(["evaluate", "--config", STUDY, "--studies-dir", str(studies), "--task", "stereo", "--data", str(root),
               "--scenes", "fountain-P11", "--jobs", "1", "--quiet", "--json"])
    err = capsys.readouterr().err
    assert rc == 0, err
    said = [ln for ln in err.splitlines() if ln.startswith("warning: --config")]
    assert len(said) == 1 and "is a multiview study" in said[0] and "not for the stereo evaluation" in said[0], err
    assert "never tuned" in said[0] and "px" in said[0], err
    capsys.readouterr()
    assert main(["evaluate", "--config", STUDY, "--studies-dir", str(studies), "--data", str(root), "--scenes",
                 "fountain-P11", "--workers", "1", "--quiet", "--json"]) == 0  # its own task: nothing to say
    assert "warning: --config" not in capsys.readouterr().err


def test_multiview_test_has_an_interval_and_a_paired_comparison(mv_study, capsys):
    """A multiview `tune test` had no 95% interval (test.json's interval null) and no paired comparison with the
    reference ("no per-pair errors in multiview records"), though every stereo test has both. Each run now keeps
    its bags' pair errors; the mean over runs gets the interval and the reference is compared on the same bags."""
    root, studies = mv_study
    rc, out = run_cli(["test", "--study", STUDY, "--studies-dir", str(studies), "--data", str(root),
                       "--scenes", "fountain-P11", "--runs", "2", "--workers", "1", "--json", "--quiet"], capsys)
    assert rc == 0
    res = json.loads(out)
    assert res["interval"] and res["interval"]["runs"] == 2 and res["interval"]["consistent_with_mean"]
    assert "bags" in res["interval"]["method"]
    for run in res["runs"]:
        assert len(run["bag_errors"]) == 3 and all(len(b[3]) == 10 for b in run["bag_errors"])  # 3 bags of 5: 10 pairs
    m = res["mean"]
    lo, hi = m["mAA10_ci"]
    assert 0.0 <= lo <= m["mAA10"] <= hi <= 1.0
    assert m["scenes"]["fountain-P11"]["mAA10_ci"] == pytest.approx([lo, hi])  # one scene: the same interval
    cmp = res["reference"]["comparison"]
    assert cmp is not None and cmp["pairs"] == 3 and cmp["units"] == "bags"
    # B - A is the frozen mean minus the reference's, as the task averaged them
    assert cmp["difference"] == pytest.approx(m["mAA10"] - res["reference"]["mean"]["mAA10"], abs=1e-9)
    rc, text = run_cli(["test", "--study", STUDY, "--studies-dir", str(studies), "--data", str(root),
                        "--scenes", "fountain-P11", "--runs", "2", "--workers", "1", "--quiet"], capsys)
    assert rc == 0 and "no paired comparison" not in text and "intervals: 95%" in text, text


def test_a_multiview_report_says_its_test_interval_is_over_bags(mv_study, capsys):
    """The HTML report of a multiview study said "test (2 runs, trial 0): mAA(10°) = 0.868 [95% interval 0.644,
    1.000, over pairs and runs]" (a real run on Strecha), though that interval resamples bags
    (combine_bag_runs_interval), as `tune test` says beside the same number."""
    root, studies = mv_study
    rc, out = run_cli(["test", "--study", STUDY, "--studies-dir", str(studies), "--data", str(root),
                       "--scenes", "fountain-P11", "--runs", "2", "--workers", "1", "--quiet"], capsys)
    assert rc == 0 and "intervals: 95%, over bags and runs" in out, out
    rc, _ = run_cli(["plot", "--study", STUDY, "--studies-dir", str(studies)], capsys)
    assert rc == 0
    html = (studies / STUDY / "report.html").read_text()
    assert "2 runs, trial" in html and "over bags and runs]" in html and "over pairs and runs" not in html


def test_the_multiview_results_table_names_no_estimator_as_best(mv_study, capsys):
    """`tune results --task multiview` had a column 'best' reading 'degensac' in every row: the study's estimator,
    which COLMAP's reconstruction never used (its column is already headed 'mAA10 COLMAP')."""
    studies = mv_study[1]
    out = _tested_results(mv_study, capsys)
    header = [c.strip() for c in out.splitlines()[0].strip("|").split("|")]
    assert "mAA10 COLMAP" in header and "best" not in header and "degensac" not in out, out
    rc, out = run_cli(["results", "--task", "multiview", "--studies-dir", str(studies), "--format", "json"], capsys)
    assert rc == 0
    rows = json.loads(out)
    assert rows and all("best" not in r for r in rows), rows


def test_a_multiview_frozen_yaml_counts_no_bag_as_a_pair(mv_study):
    """frozen.yaml's validation of a multiview study said 'pairs: 6' beside 'bags: 6' (a real study: 4 bags of 5
    and 2 of 10 images, 130 pairs): the trial's count of evaluated units, bags, under the stereo name. Here 3 bags
    of 5 images: 3 bags, 30 pairs, and no 'pairs: 3'."""
    root, studies = mv_study
    frozen = yaml.safe_load((studies / STUDY / "frozen.yaml").read_text())
    v = frozen["validation"]
    assert v["bags"] == 3
    assert v.get("pairs") in (None, 30), v.get("pairs")


def test_evaluating_a_multiview_study_prints_no_estimator_setting(mv_study, capsys):
    """`tune evaluate --config <multiview study>` headed its bag table 'sift (2000) | r=0.93 both | degensac
    eta=0.5px Gamma=1000 | data ...' (a real study on Strecha): estimator values the multiview task never used
    (COLMAP verifies the matches with its own RANSAC). The line names COLMAP's RANSAC instead; a stereo
    evaluation of the same settings still shows them."""
    root, studies = mv_study
    rc, out = run_cli(["evaluate", "--config", STUDY, "--studies-dir", str(studies), "--data", str(root), "--scenes",
                       "fountain-P11", "--workers", "1", "--quiet"], capsys)
    assert rc == 0
    head = [ln for ln in out.splitlines() if ln.startswith("sift (1024) |")]
    assert len(head) == 1 and "COLMAP" in head[0] and "eta" not in head[0] and "Gamma" not in head[0], out
    rc, out = run_cli(["evaluate", "--feature", "sift", "--num-features", "1024", "--data", str(root), "--scenes",
                       "fountain-P11", "--max-iters", "500", "--quiet"], capsys)
    assert rc == 0 and "degensac eta=0.5px Gamma=500" in out, out


def test_a_multiview_selection_note_names_no_budget_eta_or_gamma(mv_study):
    """A multiview study's frozen selection note read 'the highest validation value within the budget' (no budget
    applies: COLMAP runs its own RANSAC, every trial is feasible) and, with --select one-se / smooth, 'the one
    closest to their centre in normalised (log eta, r, log Gamma)' of a study that searched r alone. The notes now
    name what the study has: no budget, normalised (r)."""
    import optuna

    from tuner.select import select_trial
    root, studies = mv_study
    st = optuna.load_study(study_name=STUDY, storage=f"sqlite:///{studies / 'optuna.db'}")
    notes = {rule: select_trial(st, rule)[1]["note"] for rule in ("best", "one-se", "smooth")}
    assert notes["best"] == "the highest validation value", notes
    for rule in ("one-se", "smooth"):
        assert "eta" not in notes[rule] and "Gamma" not in notes[rule] and "normalised (r)" in notes[rule], notes
    from tuner.plots import write_report
    page = write_report(f"sqlite:///{studies / 'optuna.db'}", STUDY, studies / "r.html", studies_dir=studies).read_text()
    assert "budget" not in page[page.index("<h1>"):page.index("</p>", page.index("optimum"))].replace(
        "no estimator budget", ""), page[:3000]


def test_multiview_ranks_pair_the_bags_two_studies_were_tested_on(mv_study, capsys, tmp_path):
    """`tune results --task multiview` of two features (real studies on Strecha) shared a rank 'not significantly
    different (95% intervals overlap (no pair errors in test.json: unpaired))', though both test.json hold every
    run's bag errors; then 'the ranks of multiview tests do not pair their bags'. Both were tested on the same 3
    bags (one bag draw of the same images and ground truth): each test.json now records its bags' images, and the
    ranks compare the two studies bag by bag (paired bootstrap and sign-flip test on the test bags)."""
    import shutil
    root, studies = mv_study
    mine = tmp_path / "studies"
    shutil.copytree(studies, mine)
    common = ["--studies-dir", str(mine), "--data", str(root), "--workers", "1", "--quiet"]
    assert run_cli(["test", "--study", STUDY, "--scenes", "fountain-P11", "--runs", "1", *common], capsys)[0] == 0
    rc, _ = run_cli(["--feature", "rootsift", "--num-features", "1024", "--ransac", "degensac", "--task", "multiview",
                     "--bags", "5:3", "--n-trials", "1", "--scenes", "fountain-P11", "--test-scenes", "fountain-P11",
                     "--test-runs", "1", "--reference", "none", *common], capsys)
    assert rc == 0
    rc, out = run_cli(["results", "--task", "multiview", "--studies-dir", str(mine)], capsys)
    assert rc == 0
    rows = [ln for ln in out.splitlines() if ln.startswith("|")][2:]
    assert len(rows) == 2, out
    assert "no pair errors in test.json" not in out and "unpaired" not in out, out
    from tuner.freeze import study_dir
    bags = [sorted(tuple(b[4]) for b in json.loads((study_dir(mine, name) / "test.json").read_text())["runs"][0]
                   ["bag_errors"]) for name in (STUDY, "rootsift-1024-degensac-multiview")]
    assert bags[0] == bags[1] and len(bags[0]) == 3, bags
    second = rows[1]
    # 3 common bags: no paired test rejects on 3 units (the interval is [-1, 1]), so the rank is shared
    assert "rank shared" in second and "paired bootstrap and sign-flip test on the test bags" in second, out


def test_tune_studies_shows_no_infeasible_count_for_a_multiview_study(mv_study, capsys):
    """`tune studies` listed a multiview study with 'infeasible 0': a count of trials over the estimator budget,
    which a multiview study (COLMAP's own RANSAC, nothing of ours timed) does not have. The column is left out
    when no study listed has a budget, and null in the JSON."""
    root, studies = mv_study
    rc, out = run_cli(["studies", "--studies-dir", str(studies)], capsys)
    assert rc == 0
    header = [c.strip() for c in out.splitlines()[0].strip("|").split("|")]
    assert "complete" in header and "infeasible" not in header, out
    rc, out = run_cli(["studies", "--studies-dir", str(studies), "--json"], capsys)
    assert rc == 0
    row = next(r for r in json.loads(out) if r["study"] == STUDY)
    assert row["infeasible"] is None and row["complete"] == 2, row


def test_compare_of_a_multiview_study_with_other_bags_says_so(mv_study, tmp_path, capsys):
    """`tune compare STUDY B --bags 5:2` of a study tested on bags 5:3: the typed bags are used as given, and a warning
    names the study tested on others (its numbers here are not its test's). Without --bags the study's recorded
    bags are used (test_compare_of_a_multiview_study_pairs_its_bags)."""
    root, studies = mv_study
    other = tmp_path / "r99.yaml"
    other.write_text(yaml.safe_dump({"config": {"feature": {"name": "sift", "num_features": 1024},
                                                "matching": {"ratio": 0.99}}}))
    from tuner.cli import main
    capsys.readouterr()
    rc = main(["compare", STUDY, str(other), "--data", str(root), "--scenes", "fountain-P11", "--studies-dir",
               str(studies), "--workers", "1", "--quiet", "--ci-resamples", "200", "--json", "--bags", "5:2"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert json.loads(out)["overall"]["pairs"] == 2, out[-500:]
    assert (f"warning: {STUDY} was tested with bags 5:3 (here 5:2); all are compared on these bags (as given)"
            in err), err


def test_compare_of_a_multiview_study_pairs_its_bags(mv_study, tmp_path, capsys):
    """`tune compare STUDY B` of a multiview study evaluated it on stereo pairs, with an eta and Gamma it never
    tuned, where a researcher asks how its tuned r reconstructs. A multiview study is now compared on the same
    multiview bags (COLMAP), paired over the bags (uncertainty.paired_bags, as `tune results --task multiview`); with
    no --bags, on the bags the study was tested on (its frozen task options: 5:3; before, the protocol's defaults:
    7 bags of this scene, unsaid)."""
    root, studies = mv_study
    other = tmp_path / "r99.yaml"  # the same features, no ratio test: other matches, the same bags
    other.write_text(yaml.safe_dump({"config": {"feature": {"name": "sift", "num_features": 1024},
                                                "matching": {"ratio": 0.99}}}))
    common = ["--data", str(root), "--scenes", "fountain-P11", "--studies-dir", str(studies),
              "--workers", "1", "--quiet", "--ci-resamples", "200"]  # no --bags: the study's 5:3
    from tuner.cli import main
    capsys.readouterr()
    rc = main(["compare", STUDY, str(other), STUDY, *common, "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    res = json.loads(out)
    assert [c["task"] for c in res] == ["multiview"] * 2 and "stereo pairs" not in err, err
    assert "was tested with" not in err, err
    vs_other, vs_self = (c["overall"] for c in res)
    assert vs_other["pairs"] == 3 and vs_self["pairs"] == 3  # the 3 bags of 5, common to all
    assert vs_self["difference"] == 0.0 and vs_self["p_value"] == 1.0 and vs_self["ci"] == [0.0, 0.0]
    assert vs_other["ci_level"] == 0.975 and vs_other["comparisons"] == 2  # two comparisons: adjusted together
    rc = main(["compare", STUDY, str(other), *common])
    out = capsys.readouterr().out
    assert rc == 0 and "multiview bags (COLMAP; paired over the same bags)" in out and "(3 bags)" in out, out
    b_line = next(ln for ln in out.splitlines() if ln.startswith("B: r99"))
    assert "COLMAP" in b_line and "degensac" not in b_line and "Γ" not in b_line, b_line  # not the unused estimator
    header = next(ln for ln in out.splitlines() if ln.startswith("| scene"))
    assert [c.strip() for c in header.split("|")][1:3] == ["scene", "bags"], out  # bags counted, not pairs
