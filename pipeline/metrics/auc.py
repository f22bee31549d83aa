"""Pose AUC at 5/10/20 degrees, exactly as SuperGlue / LoFTR / LightGlue / glue-factory compute it.

``pose_auc``: sort the pair errors (max of rotation and sign-agnostic translation angle, degrees,
:func:`pipeline.metrics.pose.pose_error_deg`), recall = (1..n) / n, prepend the point (0, 0), integrate the
piecewise-linear recall curve with the trapezoid rule up to the threshold (the curve is held flat from the last
error below the threshold to the threshold) and divide by the threshold. Failed pairs (inf) and pairs without a
pose (NaN) count as errors above every threshold. Written out here (not imported) because glue-factory is not a
dependency; the loop form is glue-factory's ``pose_auc`` line for line, the vectorised form is the same sum.

Overall AUC = mean over scenes of the per-scene AUC (as the stereo task averages mAA). Intervals: the same
stratified percentile bootstrap as the mAA's (:func:`pipeline.metrics.uncertainty.maa_intervals`): pairs are
resampled within each scene, each scene's resample holds two pseudo-pairs (one perfect, error 0, one failed, inf),
and the interval is centred at the plain estimate and clipped to [0, 1]. The AUC is not a mean of per-pair scores
(the trapezoid joins neighbouring errors), so each resample's AUC is recomputed from its sorted errors.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

THRESHOLDS = (5, 10, 20)  # degrees; keys auc5, auc10, auc20 (+ _ci)


def _clean(errors) -> np.ndarray:
    e = np.asarray(list(errors), float)
    return np.where(np.isnan(e), np.inf, e)


def pose_auc(errors, thresholds: Sequence[float] = THRESHOLDS) -> list[float]:
    """AUC of the recall curve of ``errors`` (degrees) up to each threshold, in [0, 1]; 0 for no errors."""
    e = _clean(errors)
    if e.size == 0:
        return [0.0 for _ in thresholds]
    e = np.sort(e)
    recall = (np.arange(e.size) + 1) / e.size
    e = np.r_[0.0, e]
    recall = np.r_[0.0, recall]
    out = []
    for t in thresholds:
        last = int(np.searchsorted(e, t))
        r = np.r_[recall[:last], recall[last - 1]]
        x = np.r_[e[:last], t]
        out.append(float(np.trapezoid(r, x=x) / t))
    return out


def _auc_rows(E: np.ndarray, t: float) -> np.ndarray:
    """pose_auc of each row of E (m, n), rows sorted ascending, no NaN: sum of the trapezoids of the segments
    that end below t, plus the flat piece from the last error below t to t."""
    m, n = E.shape
    mask = E < t
    prev = np.concatenate([np.zeros((m, 1)), E[:, :-1]], axis=1)
    k = np.arange(1, n + 1)
    with np.errstate(invalid="ignore"):
        trap = np.where(mask, (E - prev) * (2 * k - 1) / (2 * n), 0.0)
    c = mask.sum(axis=1)
    last = np.where(c > 0, np.take_along_axis(E, np.maximum(c - 1, 0)[:, None], axis=1)[:, 0], 0.0)
    return (trap.sum(axis=1) + (t - last) * c / n) / t


def auc_summary(errors, thresholds: Sequence[float] = THRESHOLDS) -> dict[str, float]:
    """``{"auc5": ..., "auc10": ..., "auc20": ...}`` of one group of pair errors."""
    return {f"auc{int(t)}": v for t, v in zip(thresholds, pose_auc(errors, thresholds))}


def auc_intervals(records: Sequence[Mapping], thresholds: Sequence[float] = THRESHOLDS, n_resamples: int = 2000,
                  seed: int = 0, level: float = 0.95, *, scenes: Sequence[str] | None = None) -> dict:
    """Bootstrap intervals of the stereo AUC, overall and per scene (see module doc).

    records: stereo pair records (``scene``, ``err`` in degrees). Returns ``{"auc5_ci": [lo, hi], ...,
    "scenes": {name: {"auc5_ci": ..., ...}}}``; a scene without records is the constant 0."""
    names = list(scenes) if scenes is not None else []
    for r in records:
        if r["scene"] not in names:
            names.append(r["scene"])
    per = {n: _clean([r["err"] for r in records if r["scene"] == n]) for n in names}
    out: dict = {"scenes": {n: {} for n in names}}
    if not names:
        return {**{f"auc{int(t)}_ci": [0.0, 0.0] for t in thresholds}, **out}
    a = (1.0 - level) / 2.0
    for t in thresholds:
        key = f"auc{int(t)}_ci"
        total = np.zeros(n_resamples)
        point = aug = 0.0
        for i, n in enumerate(names):
            e = per[n]
            if e.size == 0:
                out["scenes"][n][key] = [0.0, 0.0]
                continue
            p = pose_auc(e, [t])[0]
            x = np.r_[e, 0.0, np.inf]  # the two pseudo-pairs
            rng = np.random.default_rng([seed, i, int(t * 1000)])
            R = np.sort(x[rng.integers(0, x.size, size=(n_resamples, x.size))], axis=1)
            v = _auc_rows(R, t)
            c = pose_auc(x, [t])[0]
            out["scenes"][n][key] = _centred(v, p, c, a)
            total += v
            point += p
            aug += c
        k = len(names)
        out[key] = _centred(total / k, point / k, aug / k, a)
    return out


def _centred(v: np.ndarray, point: float, centre: float, a: float) -> list[float]:
    """Percentile interval of v, shifted from the augmented estimate to the plain one, clipped to [0, 1]."""
    lo, hi = np.quantile(v, [a, 1.0 - a])
    lo, hi = point - (centre - lo), point + (hi - centre)
    return [float(min(point, max(lo, 0.0))), float(max(point, min(hi, 1.0)))]
