"""A reconstruction trial's mapping bound (`tune --trial-timeout`): a trial whose mapping runs beyond it is stopped
and recorded as pruned with the reason; a bound it stays within maps in a child process to the same models as the
unbounded mapping; bad values and a task without mapping are one-line errors, exit 2. Real data: a small dataset cut
from ../shared/data/imc2023_heritage (10 images and an outlier), SIFT, real pycolmap and Optuna."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_reconstruction_reference import _conf, _cut

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def one(tmp_path_factory):
    return _cut(tmp_path_factory.mktemp("recon52") / "data", {"hA": (0, 10)})


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    from pipeline.cache import H5Cache
    return H5Cache(tmp_path_factory.mktemp("recon52-cache"))


def test_trial_over_the_bound_is_pruned_with_the_reason(one, cache, tmp_path, monkeypatch):
    """A bound of a millisecond: a spawned process cannot even import pycolmap in it, so the mapping is stopped;
    the trial is PRUNED (not complete, not failed), its reason names the option, the bound and the dataset."""
    import optuna
    from optuna.trial import TrialState

    from pipeline.config import FeatureConfig, PipelineConfig
    from tuner.study import TuneSettings, setup_study
    monkeypatch.setenv("IMTUNE_CACHE", str(cache.root))
    s = TuneSettings(base=PipelineConfig(feature=FeatureConfig(name="sift", num_features=512)), data_root=one,
                     task="reconstruction", storage=f"sqlite:///{tmp_path}/o.db", studies_dir=tmp_path,
                     val_scenes=["hA"], fixes=["max_iters=2000", "ratio=0.9", "threshold=1.0", "min_model_size=3"],
                     n_trials=1, sampler="random", seed=0, progress=False, test=False, workers=1,
                     trial_timeout=0.001)
    ctx = setup_study(s)
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    study = optuna.create_study(direction="maximize", pruner=optuna.pruners.NopPruner())
    study.optimize(ctx.objective, n_trials=1)
    t = study.trials[0]
    assert t.state == TrialState.PRUNED
    why = t.user_attrs["pruned_reason"]
    assert why.startswith("trial timeout: mapping stopped over the bound of 0.001 s (--trial-timeout)"), why
    assert "at dataset hA (1 of 1)" in why and "incremental mapper ran beyond the bound" in why, why
    assert t.user_attrs["trial_timeout"] == 0.001


def test_auto_bound_is_ten_times_the_median_mapping_at_least_a_minute():
    """`--trial-timeout auto` reads the completed trials' mapping seconds: 10 x their median, at least 60 s; no
    bound before a trial completes; pruned trials and non-finite times do not count; one slow measurement among
    many does not move it (it set the whole study's bound when the defaults trial alone was read)."""
    import optuna
    from optuna.distributions import FloatDistribution
    from optuna.trial import TrialState, create_trial

    from tuner.objective import auto_trial_timeout
    optuna.logging.set_verbosity(optuna.logging.ERROR)

    def add(study, secs, start=None, state=TrialState.COMPLETE):
        attrs = {"timing": {"mapping_seconds": secs}, **({"start": start} if start else {})}
        study.add_trial(create_trial(state=state, value=0.5 if state == TrialState.COMPLETE else None,
                                     params={"ratio": 0.8}, distributions={"ratio": FloatDistribution(0.5, 1.0)},
                                     user_attrs=attrs))

    st = optuna.create_study(direction="maximize")
    assert auto_trial_timeout(st) is None
    add(st, 500.0, "task defaults", TrialState.PRUNED)  # not completed
    add(st, float("nan"))  # no time
    assert auto_trial_timeout(st) is None
    add(st, 30.0, "task defaults")
    assert auto_trial_timeout(st) == 300.0
    add(st, 10.0)
    assert auto_trial_timeout(st) == 200.0  # median of 30 and 10
    st2 = optuna.create_study(direction="maximize")
    add(st2, 31.0, "task defaults")  # the defaults timed on a loaded machine
    assert auto_trial_timeout(st2) == 310.0
    for secs in (2.3, 2.4, 2.2, 2.5):
        add(st2, secs)
    assert auto_trial_timeout(st2) == 60.0  # 10 x 2.4, the floor


def test_mapping_within_the_bound_gives_the_unbounded_models(one, cache):
    """The bounded mapping runs in a child process and reads its models back from disk: with one thread and the
    same seed, the same registered images and score as pycolmap in this process."""
    from pipeline.data import load_scene
    from pipeline.tasks.reconstruction import ReconstructionTask
    sc = load_scene(one, "hA")
    conf = _conf(init_min_num_inliers=15, min_model_size=3)  # 512 features: COLMAP's 100 initial inliers are few
    conf = dataclasses.replace(conf, feature=dataclasses.replace(conf.feature, num_features=1024))
    free = ReconstructionTask(workers=1).evaluate([sc], conf, cache).scenes["hA"]
    bounded = ReconstructionTask(workers=1, trial_timeout=3600).evaluate([sc], conf, cache).scenes["hA"]
    assert free["failure"] is None and free["registered"] > 0  # something was mapped, so the comparison means much
    for k in ("score", "mAA", "clusterness", "registered", "clusters"):
        assert bounded[k] == pytest.approx(free[k]), k


def test_test_runs_are_not_bounded(one):
    from pipeline.config import PipelineConfig
    from pipeline.tasks.reconstruction import ReconstructionTask
    t = ReconstructionTask(trial_timeout=5)
    assert t.trial_timeout == 5.0
    assert t.for_run(PipelineConfig(), 1)[0].trial_timeout is None
    assert t.reference_task("colmap").trial_timeout is None


@pytest.mark.parametrize("argv, says", [
    (["--task", "reconstruction", "--trial-timeout", "0"], "argument --trial-timeout: must be > 0, got '0'"),
    (["--task", "reconstruction", "--trial-timeout", "-3"], "argument --trial-timeout: must be > 0, got '-3'"),
    (["--task", "reconstruction", "--trial-timeout", "inf"], "argument --trial-timeout: must be a finite number"),
    (["--task", "reconstruction", "--trial-timeout", "ten"], "argument --trial-timeout: expected a number"),
    (["--task", "reconstruction", "--trial-timeout", "Auto"], "argument --trial-timeout: expected a number"),
    (["--task", "stereo", "--trial-timeout", "5"], "--trial-timeout bounds a reconstruction trial's mapping; the "
                                                   "stereo task has none"),
    (["--task", "stereo", "--trial-timeout", "auto"], "--trial-timeout bounds a reconstruction trial's mapping"),
])
def test_bad_trial_timeout_is_one_line_exit_2(one, tmp_path, argv, says):
    r = subprocess.run([sys.executable, "-m", "tuner", *argv, "--data", str(one), "--studies-dir", str(tmp_path),
                        "--n-trials", "1"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 2, r.stderr
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and says in lines[0], r.stderr
    assert not (tmp_path / "optuna.db").exists()  # refused before a study was made


def test_bad_trial_timeout_in_the_api_is_one_line():
    from pipeline.errors import ImtuneError
    from pipeline.tasks.reconstruction import ReconstructionTask
    for bad in (0, -1.0, float("nan"), "5"):
        with pytest.raises(ImtuneError, match="trial timeout .*: expected a number of seconds > 0"):
            ReconstructionTask(trial_timeout=bad)
