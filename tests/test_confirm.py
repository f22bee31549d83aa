"""Confirming the best trials at more seeds before freezing (`tune --confirm N`, tuner.confirm).

Known truth: a simulated study whose settings have known true scores and a known run-to-run noise, run through
`confirm_candidates` with a synthetic task (a stand-in for imtune's Task seam: `for_run` and `evaluate`, nothing of a
library), shows the winner's curse and that the confirmed rule freezes settings whose true score is higher than the
best single evaluation's. Real data: a reconstruction study on 10 heritage images with real pycolmap and Optuna
freezes the candidate with the highest confirmed mean and records every value. Bad options: one line, exit 2."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import optuna
import pytest
from optuna.distributions import IntDistribution
from optuna.trial import create_trial

from tests.test_reconstruction_reference import _cut

ROOT = Path(__file__).resolve().parents[1]


class _NoisyTask:
    """Setting x scores TRUE[x] + N(0, sd) at seed k (seeded by (x, k): a seed's run is reproducible)."""
    objective = "score"

    def __init__(self, true: np.ndarray, sd: float, k: int = 0, salt: int = 0):
        self.true, self.sd, self.k, self.salt = true, sd, k, salt

    def for_run(self, conf, k):
        return _NoisyTask(self.true, self.sd, k, self.salt), conf

    def evaluate(self, scenes, conf, cache):
        x = int(conf["x"])
        rng = np.random.default_rng([self.salt, x, self.k])
        return SimpleNamespace(summary={"score": float(self.true[x] + rng.normal(0.0, self.sd))})


def _simulated_study(rng, salt: int, n: int = 30, sd: float = 0.03, defaults: float = 0.78):
    """Setting 0 is the task's defaults (true score ``defaults``, near the top as measured ones are); the others
    are uniform over 0.70-0.80."""
    true = rng.uniform(0.70, 0.80, n)
    true[0] = defaults
    task = _NoisyTask(true, sd, salt=salt)
    study = optuna.create_study(direction="maximize")
    for x in range(n):
        v = task.evaluate(None, {"x": x}, None).summary["score"]  # the search's own evaluation, seed k = 0
        study.add_trial(create_trial(params={"x": x}, distributions={"x": IntDistribution(0, n - 1)}, value=v,
                                     user_attrs={"start": "task defaults"} if x == 0 else {}))
    ctx = SimpleNamespace(study=study, objective=SimpleNamespace(task=task, config=dict, vs=SimpleNamespace(
        scene_objs=[]), cache=None))
    return ctx, true


def test_confirmation_beats_the_winners_curse_under_known_truth():
    from tuner.confirm import confirm_candidates, pick
    from tuner.select import select_trial
    rng = np.random.default_rng(0)
    best_true, confirmed_true, best_lift = [], [], []
    for sim in range(300):
        ctx, true = _simulated_study(rng, sim)
        best, _ = select_trial(ctx.study, "best", objective="score")
        best_true.append(true[best.params["x"]])
        best_lift.append(best.value - true[best.params["x"]])
        block = confirm_candidates(ctx, 5, 3)
        assert set(block["trials"]) >= {str(best.number), "0"}  # the best and the defaults are candidates
        t, info = pick(ctx.study)
        top = max(block["trials"].items(), key=lambda kv: kv[1]["mean"])
        if t.number != int(top[0]):  # the defaults kept: the top's lead is within one se of the paired differences
            assert t.number == 0 and info["lead_over_defaults"] <= info["lead_se"]
        confirmed_true.append(true[t.params["x"]])
    # the winner's curse: the best single evaluation overstates its setting's true score
    assert np.mean(best_lift) > 0.02
    # confirmation freezes truly better settings on average (paired over the same simulated studies)
    d = np.array(confirmed_true) - np.array(best_true)
    assert d.mean() > 3 * d.std(ddof=1) / np.sqrt(len(d)), (d.mean(), d.std(ddof=1))


def test_defaults_are_kept_unless_a_candidate_leads_them_by_more_than_one_se():
    """By hand: candidate #1 leads the defaults (#0) by +0.01 with paired differences 0.03, -0.01, 0.01 (se
    0.01155): kept defaults; with 0.03, 0.02, 0.03 (mean 0.0267, se 0.00333) the candidate is frozen."""
    from tuner.confirm import ATTR, pick
    for cand, want in (([0.83, 0.79, 0.81], 0), ([0.83, 0.82, 0.83], 1)):
        study = optuna.create_study(direction="maximize")
        for x, v in ((0, 0.80), (1, cand[0])):
            study.add_trial(create_trial(params={"x": x}, distributions={"x": IntDistribution(0, 1)}, value=v))
        study.set_user_attr(ATTR, {"n": 1, "seeds": 2, "trials": {
            "0": {"values": [0.80, 0.80, 0.80], "mean": 0.80, "defaults": True},
            "1": {"values": cand, "mean": float(np.mean(cand)), "defaults": False}}})
        t, info = pick(study)
        assert t.number == want, info
        assert info["lead_over_defaults"] == pytest.approx(np.mean(cand) - 0.80)


def test_values_by_seed_are_the_tasks_and_a_rerun_reuses_them():
    from tuner.confirm import confirm_candidates
    rng = np.random.default_rng(1)
    ctx, true = _simulated_study(rng, 7, n=6)
    block = confirm_candidates(ctx, 2, 2)
    for num, row in block["trials"].items():
        x = ctx.study.trials[int(num)].params["x"]
        want = [_NoisyTask(true, 0.03, k, 7).evaluate(None, {"x": x}, None).summary["score"] for k in (0, 1, 2)]
        assert row["values"] == pytest.approx(want) and row["mean"] == pytest.approx(np.mean(want))
    ctx.objective.task = None  # a rerun with the same n, seeds and candidates must not evaluate anything
    assert confirm_candidates(ctx, 2, 2) == block


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return _cut(tmp_path_factory.mktemp("confirm") / "data", {"hA": (0, 10)})


def test_reconstruction_study_freezes_the_confirmed_candidate(small, tmp_path, monkeypatch):
    from pipeline.config import FeatureConfig, PipelineConfig
    from tuner.study import TuneSettings, tune
    monkeypatch.setenv("IMTUNE_CACHE", str(tmp_path / "cache"))
    s = TuneSettings(base=PipelineConfig(feature=FeatureConfig(name="sift", num_features=512)), data_root=small,
                     task="reconstruction", storage=f"sqlite:///{tmp_path}/o.db", studies_dir=tmp_path,
                     val_scenes=["hA"], fixes=["max_iters=2000", "threshold=1.0", "min_model_size=3"],
                     n_trials=3, sampler="random", seed=0, progress=False, test=False, workers=1,
                     confirm=1, confirm_seeds=1, select="confirmed")
    out = tune(s)
    study = optuna.load_study(study_name=out["study"], storage=s.storage)
    block = study.user_attrs["confirmation"]
    assert block["n"] == 1 and block["seeds"] == 1
    for num, row in block["trials"].items():
        assert len(row["values"]) == 2 and row["values"][0] == pytest.approx(study.trials[int(num)].value)
    from tuner.confirm import pick
    assert out["frozen"]["trial"] == pick(study)[0].number  # the rule's pick (by hand above), frozen
    assert out["frozen"]["selection"]["rule"] == "confirmed"
    assert str(out["frozen"]["trial"]) in block["trials"]


@pytest.mark.parametrize("args, msg", [
    (["--confirm", "-1"], "--confirm -1: give 0"),
    (["--confirm", "2", "--confirm-seeds", "0"], "--confirm-seeds 0: give 1"),
    (["--confirm", "2", "--select", "one-se"], "--confirm 2 with --select one-se"),
    (["--select", "confirmed"], "--select confirmed needs --confirm N"),
])
def test_bad_confirm_options_are_one_line_exit_2(args, msg, tmp_path):
    r = subprocess.run([sys.executable, "-m", "tuner", "--data", str(tmp_path / "none"), *args], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert msg in r.stderr and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.parametrize("task, select, want_confirm, want_select", [
    ("reconstruction", None, 3, "confirmed"),      # the task's default: its runs are noisy
    ("reconstruction", "one-se", 0, "one-se"),     # another rule asked for: no confirmation
    ("stereo", None, 0, None),                     # stereo keeps its recorded / default rule
])
def test_the_tasks_default_confirmation(task, select, want_confirm, want_select):
    from tuner.commands.study import _select
    args = SimpleNamespace(task=task, confirm=None, confirm_seeds=2, select=select)
    assert _select(args) == want_select and args.confirm == want_confirm
