"""Repeated test runs combined: the mean's interval widened by the run-to-run variation."""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from pipeline.metrics.uncertainty.bags import _bag_unit, _bag_weights
from pipeline.metrics.uncertainty.intervals import _scene_order, _stratified
from pipeline.metrics.uncertainty.paired import _pair_key
from pipeline.metrics.uncertainty.scores import (
    DEFAULT_LEVEL,
    DEFAULT_RESAMPLES,
    STD_DDOF,
    _stats,
    maa_from_errors,
    pair_scores,
    score_range,
)


def combine_bag_runs_interval(runs: Sequence[Sequence[Mapping]], taus: Sequence[int] = (5, 10),
                              n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL) -> dict:
    """:func:`combine_runs_interval` for the multiview task's repeated test runs: ``runs`` one list of bag records
    ("scene", "bag_size", "bag", "errors": the bag's pair errors in degrees) per run. A bag's score is its
    mAA(tau) over its pairs; the bootstrap resamples bags within each (scene, bag size) stratum, weighted as
    :func:`bag_intervals` and the task weigh them, with the same pseudo-scores and run-effect widening. Same
    keys as :func:`combine_runs_interval`."""
    runs = [list(r) for r in runs]
    names = _scene_order([x for run in runs for x in run], None)
    out: dict = {"runs": len(runs), "scenes": {n: {} for n in names}}

    def one(tau, scene_names) -> dict:
        per_run = [{_bag_unit(x): maa_from_errors(x["errors"], tau) for x in run if x["scene"] in scene_names}
                   for run in runs]
        w = _bag_weights((k[0] for pr in per_run for k in pr), scene_names)
        return _combine_runs(per_run, w, n_resamples, seed, level)

    return _per_tau_and_scene(one, taus, names, out)



# ------------------------------------------------------------------------------------------ repeated runs

def _per_tau_and_scene(one, taus, names, out: dict) -> dict:
    """Fill ``out`` (``{"runs", "scenes": {name: {}}}``) with ``one(tau, scene_names)``'s value, interval and std
    per tau, overall and per scene: the keys of :func:`combine_runs_interval`."""
    for tau in taus:
        k = f"mAA{int(tau)}"
        o = one(int(tau), names)
        out[k], out[k + "_ci"], out[k + "_std"] = o["value"], o["ci"], o["std"]
        for n in names:
            o = one(int(tau), [n])
            out["scenes"][n][k], out["scenes"][n][k + "_ci"], out["scenes"][n][k + "_std"] = o["value"], o["ci"], o["std"]
    return out



def _combine_runs(per_run: list[dict], weights: dict, n_resamples: int, seed: int, level: float) -> dict:
    """The estimate of :func:`combine_runs_interval` (steps 1-4) on scores already computed: ``per_run`` one
    ``{(stratum, unit): score}`` per run, ``weights`` {stratum: weight} (summing to 1; a unit weighs its stratum's
    weight / the stratum's unit count). Stereo: strata are scenes, units pairs; multiview: strata are (scene, bag
    size), units bags. Returns {"value", "ci", "std" (the sample std over runs, ddof 1: :data:`STD_DDOF`; 0 for
    one run)}."""
    R = len(per_run)
    z = float(_stats().norm.ppf(0.5 + level / 2))
    keys = list(dict.fromkeys(k for pr in per_run for k in pr))
    groups, wgroups, wpair, vpair = [], [], [], []
    for st, wst in weights.items():
        ks = [k for k in keys if k[0] == st]
        mat = [[pr[k] for pr in per_run if k in pr] for k in ks]
        groups.append(np.array([np.mean(v) for v in mat]) if ks else np.zeros(0))
        wgroups.append(wst)
        for v in mat:
            wpair.append(wst / len(ks))
            vpair.append(np.var(v, ddof=1) if len(v) > 1 else 0.0)
    M = float(sum(w * g.mean() for g, w in zip(groups, wgroups) if g.size))
    run_vals = []
    for pr in per_run:
        run_vals.append(float(sum(wst * np.mean([v for k, v in pr.items() if k[0] == st] or [0.0])
                                  for st, wst in weights.items())))
    (lo, hi), se = _stratified(groups, wgroups, n_resamples, seed, level, pseudo=score_range())
    if R > 1:
        W = float(np.sum(np.square(wpair) * np.asarray(vpair)))
        G = max(0.0, float(np.var(run_vals, ddof=1)) - W)
        if G > 0:
            Vb = se * se  # scipy's bootstrap standard error of the same resampling
            V = Vb + G / R
            # Welch-Satterthwaite: G rests on R - 1 degrees of freedom, V_b on (practically) infinitely many
            df = V * V / ((G / R) ** 2 / (R - 1))
            t = float(_stats().t.ppf(0.5 + level / 2, df))
            if Vb > 0:
                k = t * math.sqrt(V) / (z * math.sqrt(Vb))
                lo, hi = M - (M - lo) * k, M + (hi - M) * k
            else:
                h = t * math.sqrt(V)
                lo, hi = M - h, M + h
    std = float(np.std(run_vals, ddof=STD_DDOF)) if R > STD_DDOF else 0.0
    return {"value": M, "ci": [max(0.0, float(lo)), min(1.0, float(hi))], "std": std}



def combine_runs_interval(runs: Sequence[Sequence[Mapping]], taus: Sequence[int] = (5, 10),
                          n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL) -> dict:
    """Interval of the mean mAA of repeated test runs (same pairs, different estimator seeds), accounting
    for both the sampling of pairs and the run-to-run variation.

    runs: one list of stereo pair records per run. Exactly:

    1. score_{p,r}: pair p's mAA(tau) score in run r; s_p = its mean over the runs that have p. The point
       estimate M = sum_p w_p s_p (w_p = 1 / (n_scenes * n_pairs_in_scene)) is the mean of the runs' mAAs.
    2. [lo, hi]: stratified percentile bootstrap of M over pairs (of the run-averaged scores s_p, with the
       pseudo-scores of :data:`SCORE_RANGE`), with bootstrap variance V_b. It already contains the per-pair seed noise (s_p varies with the seeds).
    3. What it cannot see is a run effect shared by all pairs (machine load under a time budget, a seed
       that is good everywhere). Moment estimate: s2_run = sample variance (ddof 1) of the R runs' mAAs;
       its pair-independent part is W = sum_p w_p^2 v_p, v_p = sample variance of score_{p,r} over runs;
       shared-run variance G = max(0, s2_run - W). Total variance V = V_b + G / R.
    4. The interval is widened about M by k = t_df sqrt(V) / (z sqrt(V_b)): lo' = M - (M - lo) k,
       hi' = M + (hi - M) k, clipped to [0, 1] (z: the normal quantile of ``level``; t_df: Student's t
       with the Welch-Satterthwaite df = V^2 / ((G / R)^2 / (R - 1)), since G rests on R - 1 degrees of
       freedom); where V_b = 0, M -/+ t_df sqrt(V). G = 0 or one run: the bootstrap interval as is.

    Returns ``{"mAA5": M, "mAA5_ci": [lo', hi'], "mAA5_std": the sample std over runs (ddof 1, as the test
    run's "std": :data:`STD_DDOF`; 0 for one run), ..., "runs": R, "scenes": {name: the same per scene}}``."""
    runs = [list(r) for r in runs]
    names = _scene_order([x for run in runs for x in run], None)
    out: dict = {"runs": len(runs), "scenes": {n: {} for n in names}}

    def one(tau, scene_names) -> dict:
        per_run = []  # {(scene, pair): score}
        for run in runs:
            recs = [x for x in run if x["scene"] in scene_names]
            keys = [(x["scene"], _pair_key(x["pair"])) for x in recs]
            per_run.append(dict(zip(keys, pair_scores([x["err"] for x in recs], tau))))
        return _combine_runs(per_run, {n: 1.0 / len(scene_names) for n in scene_names}, n_resamples, seed, level)

    return _per_tau_and_scene(one, taus, names, out)
