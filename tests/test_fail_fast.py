"""Fail fast (issue 13 item 3): everything that would stop a study after tuning is a one-line error, exit 2,
naming the flag that fixes it, before any calibration and before any trial; and the warnings about a frozen
optimum (on a search-space bound, Gamma_max at the search ceiling, every trial scoring 0).

Real `tune` subprocesses on tiny copies of the Strecha scenes (3 images of fountain-P11: 3 pairs)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import DATA, ROOT, copy_strecha_subset

STRECHA = DATA / "strecha"
pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")

VAL = ["0004.jpg", "0005.jpg", "0006.jpg"]
TEST = ["0003.jpg", "0004.jpg", "0005.jpg"]


def tune(*args, env_extra=None, timeout=600):
    env = dict(os.environ, **(env_extra or {}))
    env.pop("IMTUNE_DATA", None)
    return subprocess.run([sys.executable, "-m", "tuner", *args], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=timeout)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("ff-cache"))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """fountain-P11 (validation), Herz-Jesus-P8 (test), a one-image Strecha scene (no pairs), a Strecha scene
    with a camera file missing, and a plain image folder (no ground truth at all)."""
    root = tmp_path_factory.mktemp("ff-data")
    copy_strecha_subset(root, VAL, "fountain-P11")
    copy_strecha_subset(root, TEST, "Herz-Jesus-P8")
    copy_strecha_subset(root, ["0000.jpg"], "entry-P10")  # one image: no pair
    src = STRECHA / "fountain-P11"
    broken = root / "broken"
    (broken / "images").mkdir(parents=True)
    (broken / "gt_dense_cameras").mkdir()
    for n in VAL:
        shutil.copy(src / "images" / n, broken / "images" / n)
    for n in VAL[:2]:  # the third image has no camera file: no ground truth for it
        shutil.copy(src / "gt_dense_cameras" / f"{n}.camera", broken / "gt_dense_cameras" / f"{n}.camera")
    nogt = root / "nogt" / "images"
    nogt.mkdir(parents=True)
    for n in VAL[:2]:
        shutil.copy(src / "images" / n, nogt / n)
    return root


@pytest.fixture(scope="module")
def val_only(tmp_path_factory):
    """A data folder with fountain-P11 alone: the default splits have no test scene."""
    return copy_strecha_subset(tmp_path_factory.mktemp("ff-val-only"), VAL, "fountain-P11")


def quick(data_root, studies, *extra):
    return ["--data", str(data_root), "--feature", "sift", "--num-features", "512", "--ransac", "degensac",
            "--scenes", "fountain-P11", "--max-pairs", "3", "--chunk-pairs", "3", "--budget", "0.1",
            "--calibration-pairs", "2", "--studies-dir", str(studies), "--n-trials", "2", *extra]


def trials_in(storage_file: Path) -> int:
    """Trials in the storage (0 when no study was created; the file may not even exist)."""
    if not storage_file.exists():
        return 0
    import optuna
    url = f"sqlite:///{storage_file}"
    return sum(len(optuna.load_study(study_name=s.study_name, storage=url).trials)
               for s in optuna.get_all_study_summaries(url, include_best_trial=False))


def assert_fails_fast(r, studies: Path, *needles):
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("tune: error:")]
    assert len(errors) == 1, r.stderr
    assert "Traceback" not in r.stderr
    err = errors[0]
    for n in needles:
        assert n in err, err
    # before any calibration, feature extraction or trial
    for late in ("budget:", "calibrating", "features:", "validation:", "study "):
        assert late not in r.stderr.replace(err, ""), r.stderr
    assert r.stdout == ""
    assert trials_in(studies / "optuna.db") == 0
    assert not list(studies.glob("*/frozen.yaml"))
    return err


@pytest.mark.parametrize("case, extra, needles", [
    ("unknown test scene", ["--test-scenes", "Herz-Jesus-P88"],
     ["test scene 'Herz-Jesus-P88'", "unknown scene", "available:", "--test-scenes", "--no-test"]),
    ("test scene with no pairs", ["--test-scenes", "entry-P10"],
     ["test scene 'entry-P10'", "nothing for the stereo task", "--test-scenes", "--no-test"]),
    ("camera file missing", ["--test-scenes", "broken"],
     ["test scene 'broken'", "missing camera file", "0006.jpg", "--test-scenes", "--no-test"]),
    ("no ground truth", ["--test-scenes", "Herz-Jesus-P8,nogt"],
     ["test scene 'nogt' has no ground truth", "build-gt", "--test-scenes", "--no-test"]),
])
def test_bad_test_scenes_fail_before_calibration(data, cache, tmp_path, case, extra, needles):
    studies = tmp_path / "studies"
    r = tune(*quick(data, studies, *extra), env_extra={"IMTUNE_CACHE": cache})
    assert_fails_fast(r, studies, *needles)


@pytest.mark.parametrize("case, extra, needles", [
    ("multiview without ground truth", ["--task", "multiview", "--no-test"],  # fountain-P11 here has no built 3D points
     ["validation scene 'fountain-P11' has no ground truth", "no multiview bags and no 3D points", "build-gt",
      "--scenes"]),
])
def test_bad_validation_scenes_fail_before_the_study_exists(data, tmp_path, case, extra, needles):
    """A validation scene the task cannot evaluate: one line before any study, calibration or trial (a multiview
    study without built ground truth was created, and stayed in the storage with one failed trial)."""
    studies = tmp_path / "studies"
    r = tune(*quick(data, studies, *extra), env_extra={"IMTUNE_CACHE": str(tmp_path / "fresh-cache")})
    assert_fails_fast(r, studies, *needles)
    assert not (studies / "optuna.db").exists() or trials_in(studies / "optuna.db") == 0
    import optuna
    if (studies / "optuna.db").exists():
        assert optuna.get_all_study_names(f"sqlite:///{studies / 'optuna.db'}") == []


def test_no_test_split_names_both_flags(val_only, cache, tmp_path):
    studies = tmp_path / "studies"
    r = tune(*quick(val_only, studies), env_extra={"IMTUNE_CACHE": cache})
    err = assert_fails_fast(r, studies, "no test scenes", "--test-scenes", "--no-test", "splits.yaml")
    assert str(val_only) in err


def test_nothing_extracted_before_the_error(data, tmp_path):
    """The check reads metadata only: a fresh cache stays empty."""
    fresh = tmp_path / "cache"
    studies = tmp_path / "studies"
    r = tune(*quick(data, studies, "--test-scenes", "nosuch"), env_extra={"IMTUNE_CACHE": str(fresh)})
    assert_fails_fast(r, studies, "test scene 'nosuch'")
    assert not fresh.exists() or not any(p.is_file() for p in fresh.rglob("*"))


# -- warnings ---------------------------------------------------------------------------------------------

def write_space(path: Path, ratio, threshold) -> Path:
    path.write_text(f"params:\n  ratio: {ratio}\n  threshold: {threshold}\n  max_iters: 2000\n")
    return path


def test_optimum_on_a_bound_warns_once_on_stderr_and_in_the_json(val_only, cache, tmp_path):
    """Grid sampler on eta in {0.3, 3.0} only (r and Gamma pinned, no calibration): the optimum is on a bound
    whichever it is. --no-test also skips the test-split check (this data has no test split)."""
    space = write_space(tmp_path / "space.yaml", 0.85, "{type: float, low: 0.3, high: 3.0, log: true, grid: [0.3, 3.0]}")
    studies = tmp_path / "studies"
    r = tune(*quick(val_only, studies, "--space", str(space), "--sampler", "grid", "--no-test", "--json"),
             env_extra={"IMTUNE_CACHE": cache})
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout)
    eta = out["frozen"]["params"]["threshold"]
    assert eta in (0.3, 3.0)
    side = "lower" if eta == 0.3 else "upper"
    assert len(out["warnings"]) == 1, out["warnings"]
    w = out["warnings"][0]
    assert f"threshold (eta) = {eta:g} px lies on the {side} bound" in w and "[0.3, 3]" in w
    assert ("low: 0.15" if side == "lower" else "high: 6") in w and "--space" in w
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert lines == [f"warning: {w}"]  # one line, even with --json (progress off)
    assert out["test"] is None


def test_every_trial_zero_warns(val_only, cache, tmp_path):
    """r pinned at 0.05: the ratio test keeps (almost) no match, every pair fails, every trial scores 0."""
    space = write_space(tmp_path / "space.yaml", 0.05, "{type: float, low: 0.3, high: 3.0, log: true, grid: [0.3, 3.0]}")
    studies = tmp_path / "studies"
    r = tune(*quick(val_only, studies, "--space", str(space), "--sampler", "grid", "--no-test", "--json"),
             env_extra={"IMTUNE_CACHE": cache})
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout)
    assert out["frozen"]["value"] == 0
    assert len(out["warnings"]) == 1, out["warnings"]  # the bound warning means nothing when all scores are 0
    assert out["warnings"][0].startswith("every trial scored mAA(10°) = 0 (2 completed)")
    assert [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")] == [f"warning: {out['warnings'][0]}"]


def test_no_warning_inside_the_range(val_only, cache, tmp_path):
    """eta searched over [0.1, 10] at the grid's interior points only: the optimum is inside, no warning."""
    space = write_space(tmp_path / "space.yaml", 0.85, "{type: float, low: 0.1, high: 10.0, log: true, grid: [0.5, 1.0]}")
    studies = tmp_path / "studies"
    r = tune(*quick(val_only, studies, "--space", str(space), "--sampler", "grid", "--no-test", "--json"),
             env_extra={"IMTUNE_CACHE": cache})
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout)
    assert out["frozen"]["value"] > 0
    assert out["warnings"] == []
    assert "warning:" not in r.stderr


# -- the warning rules, on crafted Optuna studies (a real SQLite storage, trials added by hand) ----------------

def crafted_study(folder, trials, *, gamma_max=50_000, space=None):
    """A study with the user attributes imtune writes and the given (params, value) trials; and its frozen dict."""
    import optuna
    from optuna.distributions import FloatDistribution, IntDistribution

    from tuner.budget import GAMMA_CEILING
    folder.mkdir(parents=True, exist_ok=True)
    st = optuna.create_study(study_name="crafted", storage=f"sqlite:///{folder / 'c.db'}", direction="maximize")
    dists = {"ratio": FloatDistribution(0.6, 1.0), "threshold": FloatDistribution(0.1, 2.0, log=True),
             "max_iters": IntDistribution(1000, gamma_max, log=True)}
    spec = space or {"params": {"ratio": {"type": "float", "low": 0.6, "high": 1.0, "log": False},
                                "threshold": {"type": "float", "low": 0.1, "high": 2.0, "log": True},
                                "max_iters": {"type": "int", "low": 1000, "high": gamma_max, "log": True}},
                     "fixed": {}}
    st.set_user_attr("task", "stereo")
    st.set_user_attr("search_space", {"params": {**spec["params"], "max_iters": {**spec["params"]["max_iters"],
                                                                                   "high": "calibrated"}}})
    st.set_user_attr("search_space_resolved", spec)
    st.set_user_attr("search_space_source", "search_spaces/degensac.yaml")
    st.set_user_attr("budget", {"seconds_per_pair": 0.5, "gamma_max": gamma_max,
                                "calibration": {"ceiling": GAMMA_CEILING}})
    for p, v in trials:
        st.add_trial(optuna.trial.create_trial(params=p, distributions={k: dists[k] for k in p}, value=v))
    best = max(st.trials, key=lambda t: t.value)
    frozen = {"task": "stereo", "params": best.params, "search_space": spec,
              "budget": {"seconds_per_pair": 0.5, "gamma_max": gamma_max}}
    return st, frozen


def test_rules_on_crafted_studies(tmp_path):
    from tuner.budget import GAMMA_CEILING
    from tuner.diagnostics import optimum_warnings
    inside = {"ratio": 0.8, "threshold": 0.5, "max_iters": 50_000}  # Gamma at its calibrated cap: not warned
    st, fr = crafted_study(tmp_path / "a", [(inside, 0.7), ({**inside, "ratio": 0.7}, 0.6)])
    assert optimum_warnings(st, fr) == []
    # eta at the lower bound (within 2% of the log range), r at its upper bound 1.0 = no ratio test (its own
    # limit: nothing wider to search), Gamma at the lower bound
    edge = {"ratio": 1.0, "threshold": 0.1 * (20 ** 0.01), "max_iters": 1000}
    st, fr = crafted_study(tmp_path / "b", [(edge, 0.7), (inside, 0.6)])
    ws = optimum_warnings(st, fr)
    assert len(ws) == 2, ws
    assert "threshold (eta) = 0.103 px lies on the lower bound" in ws[0] and "low: 0.05" in ws[0]
    assert "search_spaces/degensac.yaml" in ws[0]
    assert "max_iters (Gamma) = 1000 lies on the lower bound" in ws[1] and "low: 500" in ws[1]
    # r at an upper bound below 1: widen towards 1, never past it
    space = {"params": {"ratio": {"type": "float", "low": 0.6, "high": 0.9, "log": False},
                        "threshold": {"type": "float", "low": 0.1, "high": 2.0, "log": True},
                        "max_iters": {"type": "int", "low": 1000, "high": 50_000, "log": True}}, "fixed": {}}
    st, fr = crafted_study(tmp_path / "c", [({**inside, "ratio": 0.9}, 0.7)], space=space)
    (w,) = optimum_warnings(st, fr)
    assert "ratio (r) = 0.9 lies on the upper bound" in w and "high: 1 in a --space file" in w
    # Gamma_max at the ceiling: the budget never bound
    top = {**inside, "max_iters": 400_000}
    st, fr = crafted_study(tmp_path / "d", [(top, 0.7)], gamma_max=GAMMA_CEILING)
    (w,) = optimum_warnings(st, fr)
    assert w.startswith("Gamma_max = 1,000,000 is the search ceiling") and "0.5 s per pair" in w
    assert "so the budget never bound Gamma" in w
    # ... but with trials timed over B (DEGENSAC 2k SIFT: Gamma 431k and 930k at 1.3 s per pair, 2 of 12) the
    # budget did bind: 'never bound Gamma' beside them was false
    import optuna
    from optuna.distributions import FloatDistribution, IntDistribution
    st, fr = crafted_study(tmp_path / "d2", [(top, 0.7)], gamma_max=GAMMA_CEILING)
    slow = {**inside, "max_iters": 930_000}
    st.add_trial(optuna.trial.create_trial(  # median 1.34 s per pair, B 0.5 s: as a run records an over-budget trial
        params=slow, value=0.8, user_attrs={"feasible": False, "ransac_seconds_median": 1.34},
        distributions={"ratio": FloatDistribution(0.6, 1.0), "threshold": FloatDistribution(0.1, 2.0, log=True),
                       "max_iters": IntDistribution(1000, GAMMA_CEILING, log=True)}))
    (w,) = optimum_warnings(st, fr)
    assert w.startswith("Gamma_max = 1,000,000 is the search ceiling") and "never bound" not in w, w
    assert "yet 1 of 2 completed trials ran over it" in w, w
    # every trial 0: that warning alone (the optimum's position means nothing)
    st, fr = crafted_study(tmp_path / "e", [(edge, 0.0), (inside, 0.0)])
    (w,) = optimum_warnings(st, fr)
    assert w.startswith("every trial scored mAA(10°) = 0 (2 completed)")
    # one non-zero trial: no zero warning
    st, fr = crafted_study(tmp_path / "f", [(inside, 0.0), (inside, 0.01)])
    assert optimum_warnings(st, fr) == []
