"""Pruners (`--pruner median|sha|hyperband|none`, tuner.study.make_pruner) and the over-budget proof rule of the
objective (a trial stops as soon as more than half of ALL its pairs took longer than B), on real short studies
(2048 SIFT, DEGENSAC, real Strecha images, SQLite storage)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.conftest import DATA, ROOT, copy_strecha_subset

STRECHA = DATA / "strecha"
pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("pruner-cache")


@pytest.fixture(scope="module")
def data4(tmp_path_factory):
    return copy_strecha_subset(tmp_path_factory.mktemp("pruner-data4"), ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"])


def test_make_pruner_names():
    import optuna

    from pipeline.errors import ImtuneError
    from tuner.samplers import DEFAULT_PRUNER, PRUNERS, make_pruner
    assert PRUNERS == ("median", "sha", "hyperband", "none") and DEFAULT_PRUNER in PRUNERS
    kinds = {"median": optuna.pruners.MedianPruner, "sha": optuna.pruners.SuccessiveHalvingPruner,
             "hyperband": optuna.pruners.HyperbandPruner, "none": optuna.pruners.NopPruner}
    for name, cls in kinds.items():
        assert isinstance(make_pruner(name), cls)
    with pytest.raises(ImtuneError, match="unknown pruner 'asha'"):
        make_pruner("asha")


def _settings(data, tmp_path, **kw):
    from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
    from tuner.study import TuneSettings
    base = PipelineConfig(feature=FeatureConfig(name="sift", num_features=2048), matching=MatchConfig(ratio=1.0),
                          geometry=GeometryConfig(ransac="degensac"))
    args = dict(base=base, data_root=data, storage=f"sqlite:///{tmp_path}/o.db", studies_dir=tmp_path,
                val_scenes=["fountain-P11"], max_pairs=6, chunk_pairs=2, fixes=["max_iters=20000"], n_trials=1,
                sampler="random", seed=2, pruner="none", progress=False, test=False, jobs=2)
    args.update(kw)
    return TuneSettings(**args)


def test_a_trial_proven_over_budget_stops_early(tmp_path, data4, cache, monkeypatch):
    """B = 1e-5 s: every pair is over B. With the 2 x B rule switched off, the proof rule alone stops the trial
    at the second chunk (4 of its 6 pairs over B > half of 6), not the first (2 of 6 proves nothing)."""
    from optuna.trial import TrialState

    from tuner.study import optimize, setup_study
    monkeypatch.setenv("IMTUNE_CACHE", str(cache))
    s = _settings(data4, tmp_path, budget=1e-5, study_name="proof")
    ctx = setup_study(s)
    ctx.objective.prune_over_budget = 0  # the running-median heuristic off: only the proof
    optimize(ctx, s)
    t = ctx.study.trials[0]
    assert t.state == TrialState.PRUNED, t.user_attrs
    assert t.user_attrs["pruned_at_pairs"] == 4 and sorted(t.intermediate_values) == [0, 1]
    assert t.user_attrs["feasible"] is False and "4 of its 6 pairs already took more than" in t.user_attrs["pruned_reason"]
    # a budget every pair meets: the trial runs to the end
    s2 = _settings(data4, tmp_path, budget=50.0, study_name="roomy")
    ctx2 = setup_study(s2)
    ctx2.objective.prune_over_budget = 0
    optimize(ctx2, s2)
    t2 = ctx2.study.trials[0]
    assert t2.state == TrialState.COMPLETE and t2.user_attrs["feasible"] is True and len(t2.intermediate_values) == 3
    # the 2 x B rule on (the default): it stops the trial at the first chunk, where 2 of 6 pairs over B prove
    # nothing, and its reason says it is a guess (it read "over budget", as a proof does)
    s3 = _settings(data4, tmp_path, budget=1e-5, study_name="guess")
    ctx3 = setup_study(s3)
    assert ctx3.objective.prune_over_budget == 2.0
    optimize(ctx3, s3)
    t3 = ctx3.study.trials[0]
    assert t3.state == TrialState.PRUNED and t3.user_attrs["pruned_at_pairs"] == 2, t3.user_attrs
    why = t3.user_attrs["pruned_reason"]
    assert why.startswith("likely over budget: running median ") and "after 2 of 6 pairs" in why and "not a proof" in why


@pytest.mark.parametrize("pruner", ["sha", "hyperband"])
def test_cli_study_with_each_pruner(tmp_path, data4, cache, pruner):
    import optuna
    from optuna.trial import TrialState

    from tuner.storage import open_storage
    storage = f"sqlite:///{tmp_path}/p.db"
    args = ["--data", data4, "--feature", "sift", "--num-features", "2048", "--scenes", "fountain-P11",
            "--max-pairs", "6", "--chunk-pairs", "2", "--fix", "max_iters=3000", "--budget", "10", "--n-trials", "8",
            "--sampler", "random", "--seed", "4", "--pruner", pruner, "--storage", storage, "--studies-dir", tmp_path,
            "--study", pruner, "--no-test", "--quiet", "--jobs", "2"]
    r = subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], capture_output=True, text=True, cwd=ROOT,
                       env=dict(os.environ, IMTUNE_CACHE=str(cache)), timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    study = optuna.load_study(study_name=pruner, storage=open_storage(storage, heartbeat=None))
    ts = study.trials
    assert len(ts) == 8 and all(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in ts)
    assert all(t.intermediate_values and min(t.intermediate_values) == 0 for t in ts)
    for t in ts:  # a complete trial reported all 3 chunks; a pruned one stopped before the last
        n = len(t.intermediate_values)
        assert (n == 3) if t.state == TrialState.COMPLETE else (1 <= n < 3)
    print(f"PRUNER {pruner}: {sum(t.state == TrialState.PRUNED for t in ts)} of 8 trials pruned")
