"""The paper's breakdowns of pose accuracy: by co-visibility bin, by angular threshold, by scene.

Records are the tasks' per-pair dicts (``err`` in degrees, inf for a failure; ``covisibility`` or None;
``scene``). Everything here returns plain JSON-able dicts and lists.
"""
from __future__ import annotations

import numpy as np

from pipeline.metrics.covisibility import COVISIBILITY_BINS, bin_label
from pipeline.metrics.pose import accuracy_curve, mean_average_accuracy


def by_covisibility(records: list[dict], bins=COVISIBILITY_BINS) -> dict[str, dict]:
    """{"0+": {...}, "0.1+": {...}, ...}: for each edge, the pairs with co-visibility >= edge — pairs
    count, mAA(5), mAA(10), accuracy at 1..10 deg. Pairs of unknown co-visibility are left out (and counted
    under "unknown" when there are any)."""
    out: dict[str, dict] = {}
    known = [r for r in records if r.get("covisibility") is not None]
    for edge in bins:
        errs = [r["err"] for r in known if r["covisibility"] >= edge - 1e-12]
        out[bin_label(edge)] = _acc(errs)
    unknown = [r["err"] for r in records if r.get("covisibility") is None]
    if unknown:
        out["unknown"] = _acc(unknown)
    return out


def by_threshold(errors, tau: int = 10) -> dict[str, float]:
    """Accuracy at every degree 1..tau: {"1": fraction <= 1 deg, ...}."""
    return {str(k + 1): float(a) for k, a in enumerate(accuracy_curve(errors, tau))}


def by_scene(records: list[dict]) -> dict[str, dict]:
    """Per-scene pairs / mAA(5) / mAA(10) / accuracy curve, from records carrying ``scene``."""
    scenes: dict[str, list] = {}
    for r in records:
        scenes.setdefault(r.get("scene", ""), []).append(r["err"])
    return {s: _acc(e) for s, e in scenes.items()}


def _acc(errs) -> dict:
    errs = list(errs)
    return {"pairs": len(errs), "mAA5": mean_average_accuracy(errs, 5) if errs else 0.0,
            "mAA10": mean_average_accuracy(errs, 10) if errs else 0.0,
            "accuracy": [float(x) for x in accuracy_curve(errs, 10)]}


def mean_breakdown(breakdowns: list[dict[str, dict]]) -> dict[str, dict]:
    """Mean over scenes of per-scene co-visibility breakdowns (a bin's mean over the scenes that have pairs
    in it; pair counts summed)."""
    keys: list[str] = []
    for b in breakdowns:
        for k in b:
            if k not in keys:
                keys.append(k)
    out = {}
    for k in keys:
        parts = [b[k] for b in breakdowns if k in b and b[k]["pairs"] > 0]
        if not parts:
            out[k] = _acc([])
            continue
        out[k] = {"pairs": int(sum(p["pairs"] for p in parts)),
                  "mAA5": float(np.mean([p["mAA5"] for p in parts])),
                  "mAA10": float(np.mean([p["mAA10"] for p in parts])),
                  "accuracy": [float(x) for x in np.mean([p["accuracy"] for p in parts], axis=0)]}
    return out
