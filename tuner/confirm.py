"""Confirm the best trials at more seeds before freezing (``tune --confirm N``): the winner's curse, measured away.

    from tuner.confirm import confirm_candidates
    block = confirm_candidates(ctx, n=3, seeds=2)   # the study's user attribute "confirmation"

A study scores each trial once, at the study's seed. Where the task's own run-to-run noise (reconstruction: COLMAP's
seed and the estimator's) is as large as the differences between good settings, the best of N trials is partly the
luckiest one, and its lead does not hold at another seed nor on a dataset the study never saw
(``benchmarks/reconstruction_noise.py`` measured it: a 30-trial study's best, 0.027 above the defaults at its own
seed, was 0.010 below them over five seeds). Confirmation re-evaluates the ``n`` best feasible trials, and the
task's defaults when the study started from them, at ``seeds`` more seeds each (the task's ``for_run`` k = 1 ..
seeds, as test runs vary theirs), on the same validation data; the ``confirmed`` selection rule
(:mod:`tuner.select`) then freezes the candidate with the highest mean over its own value and those runs. This is
the re-evaluation of incumbents that SMAC's intensification and "racing" do; Optuna has no such step, so it is
written here, on the study's own task, validation set and cache.

The block is stored in the study (user attribute ``confirmation``: candidates, their values by seed and means) and
reused by a rerun with the same ``n`` and ``seeds`` when the candidates are the same.
"""
from __future__ import annotations

import numpy as np

from pipeline.errors import ImtuneError
from tuner.select import CONFIRMATION_ATTR as ATTR
from tuner.select import _value, feasible_trials
from tuner.select import pick_confirmed as pick

MAX_CANDIDATES = 20
MAX_SEEDS = 10


def check(n: int, seeds: int) -> None:
    if not 0 <= int(n) <= MAX_CANDIDATES:
        raise ImtuneError(f"--confirm {n}: give 0 (no confirmation) to {MAX_CANDIDATES} candidates")
    if not 1 <= int(seeds) <= MAX_SEEDS:
        raise ImtuneError(f"--confirm-seeds {seeds}: give 1 to {MAX_SEEDS} more seeds per candidate")


def candidates(study, n: int) -> list:
    """The ``n`` best feasible completed trials by value (ties: the earlier), and the task's defaults trial (user
    attribute ``start`` "task defaults") when it is feasible and not among them."""
    feas = feasible_trials(study)
    best = sorted(feas, key=lambda t: (-(_value(t) or 0.0), t.number))[:n]
    defaults = [t for t in feas if t.user_attrs.get("start") == "task defaults" and t not in best]
    return best + defaults[:1]


def confirm_candidates(ctx, n: int, seeds: int, say=None) -> dict | None:
    """Evaluate :func:`candidates` at ``seeds`` more seeds each (module docstring); store and return the block
    ``{"n", "seeds", "objective", "trials": {number: {"values": [own, run 1, ...], "mean"}}}``. None when n is 0.
    A rerun with the same n, seeds and candidates returns the stored block without evaluating."""
    check(n, seeds)
    if n == 0:
        return None
    study, obj = ctx.study, ctx.objective
    task = obj.task
    cands = candidates(study, n)
    stored = study.user_attrs.get(ATTR)
    wanted = sorted(t.number for t in cands)
    if isinstance(stored, dict) and stored.get("n") == n and stored.get("seeds") == seeds \
            and sorted(int(k) for k in stored.get("trials", {})) == wanted:
        return stored
    trials: dict = {}
    for i, t in enumerate(cands, 1):
        conf = obj.config(dict(t.params))
        values = [float(_value(t) or 0.0)]  # a feasible completed trial has a value
        for k in range(1, seeds + 1):
            task_k, conf_k = task.for_run(conf, k)
            if hasattr(task_k, "trial_timeout"):
                task_k.trial_timeout = None  # a candidate completed within the search's bound; confirm it whole
            res = task_k.evaluate(obj.vs.scene_objs, conf_k, obj.cache)
            values.append(float(res.summary[task.objective]))
        trials[str(t.number)] = {"values": values, "mean": float(np.mean(values)),
                                 "defaults": t.user_attrs.get("start") == "task defaults"}
        if say is not None:
            say(f"confirm {i}/{len(cands)}: trial #{t.number} {task.objective} "
                + ", ".join(f"{v:.3f}" for v in values) + f" (mean {np.mean(values):.3f})")
    block = {"n": int(n), "seeds": int(seeds), "objective": task.objective, "trials": trials,
             "method": f"each candidate's own value and {seeds} more runs at the task's k-th seeds (k = 1 .. "
                       f"{seeds}); the mean decides"}
    study.set_user_attr(ATTR, block)
    return block


__all__ = ["ATTR", "candidates", "check", "confirm_candidates", "pick"]
