"""Tentative matches from cached k-NN tables: ratio test, strategy, distance threshold, FGINN.

    from pipeline.matching.filter import filter_matches
    matches, dist = filter_matches(tables, MatchConfig(ratio=0.8, strategy="both"))
    # matches (M, 2) int32: [i in image 1, j in image 2], sorted by i (then j); dist (M,) float32

This runs in every tuning trial, so it is vectorised numpy on the (N, k) tables only: tens of microseconds
for 8k x 8k (no descriptor is touched; see ``knn.py`` for the search itself).

Conventions (the official IMC benchmark's ``methods/feature_matching/nn.py``):

- Lowe's ratio test on each direction with threshold r keeps a nearest neighbour when ``d1 <= r * d2``
  (evaluated in float64; d2 = inf, i.e. no second neighbour, passes). r = 1 is no test: every nearest
  neighbour is kept.
- "both": the intersection of the two directional lists, i.e. mutual nearest neighbours that survive the
  ratio test (and the distance threshold) in both directions. "either": their union (deduplicated).
  "uni": image 1 -> image 2 only.
- distance_threshold: a direction's match is dropped when its descriptor distance exceeds it (``d1 <= t``
  is kept), before the two directions are combined, as in the official code.
- FGINN (first geometrically inconsistent nearest neighbour, Mishkin et al.): the "second neighbour" of
  the ratio test is the first neighbour, in ranking order, whose keypoint in the target image lies more than
  ``fginn_px`` from the nearest neighbour's keypoint. If every listed neighbour is within ``fginn_px``, the
  last listed one is used (the official loop accepts iff the ratio holds against some listed neighbour
  before the first far one, i.e. against the last one). Needs tables with k > 2 (``knn_tables(..., k=10)``)
  and the keypoints of both images.
"""
from __future__ import annotations

import numpy as np

from pipeline.config import MatchConfig
from pipeline.errors import ImtuneError


def _keypoints(kpts, n: int, which: str) -> tuple[np.ndarray, np.ndarray]:
    if kpts is None:
        raise ImtuneError(f"FGINN needs the keypoints of {which} (pass kpts1 and kpts2 to filter_matches)")
    k = np.asarray(kpts)
    if k.ndim != 2 or k.shape[0] != n or k.shape[1] < 2:
        raise ImtuneError(f"FGINN: keypoints of {which} must be ({n}, 2+) to match the k-NN table, got {k.shape}")
    return np.ascontiguousarray(k[:, 0], np.float64), np.ascontiguousarray(k[:, 1], np.float64)


def _fginn_second(idx: np.ndarray, dist: np.ndarray, kpts_target: tuple, px: float) -> np.ndarray:
    """Distance of the first neighbour lying > px from the nearest one (else of the last listed one; inf if none)."""
    n = idx.shape[0]
    kx, ky = kpts_target
    j0 = np.maximum(idx[:, 0], 0)
    rest = idx[:, 1:]
    listed = rest >= 0
    all_listed = bool(listed.all())
    safe = rest if all_listed else np.where(listed, rest, j0[:, None])
    dx = np.take(kx, safe) - np.take(kx, j0)[:, None]
    dy = np.take(ky, safe) - np.take(ky, j0)[:, None]
    far = dx * dx + dy * dy > float(px) ** 2
    if not all_listed:
        far &= listed
    rows = np.arange(n)
    rest_d = dist[:, 1:]
    first_far = far.argmax(1)
    if all_listed:
        d2 = rest_d[:, -1]
    else:  # missing neighbours (-1) only ever trail the listed ones
        last = np.count_nonzero(listed, axis=1) - 1
        d2 = np.where(last >= 0, rest_d[rows, np.maximum(last, 0)], np.inf)
    return np.where(far[rows, first_far], rest_d[rows, first_far], d2)


def _direction(idx, dist, conf: MatchConfig, kpts_target) -> np.ndarray:
    """Mask of the rows whose nearest neighbour survives the ratio test and the distance threshold."""
    nn = idx[:, 0]
    d1 = dist[:, 0].astype(np.float64)
    keep = nn >= 0
    r = float(conf.ratio)
    if conf.fginn:
        d2 = _fginn_second(idx, dist, kpts_target, conf.fginn_px).astype(np.float64)
        keep &= d1 <= r * d2
    elif r < 1.0 and idx.shape[1] >= 2:  # r = 1 is no test (rows are sorted, so d1 <= d2 always)
        keep &= d1 <= r * dist[:, 1].astype(np.float64)
    if conf.distance_threshold is not None:
        keep &= d1 <= float(conf.distance_threshold)
    return keep


def filter_matches(tables, conf: MatchConfig, kpts1=None, kpts2=None) -> tuple[np.ndarray, np.ndarray]:
    """Tentative matches of a pair from its k-NN tables (``KnnTables``; see the module docstring).

    conf: ratio r in (0, 1], strategy both|either|uni, distance_threshold (descriptor distance units, None =
    off), fginn / fginn_px (px). kpts1 (N1, 2+), kpts2 (N2, 2+): keypoints in pixels, needed only for FGINN.
    Returns (matches (M, 2) int32 [i in image 1, j in image 2] sorted by i then j, distances (M,) float32).
    """
    idx12 = np.asarray(tables.idx12)
    dist12 = np.asarray(tables.dist12)
    idx21 = np.asarray(tables.idx21)
    dist21 = np.asarray(tables.dist21)
    n1, n2 = idx12.shape[0], idx21.shape[0]
    empty = (np.zeros((0, 2), np.int32), np.zeros(0, np.float32))
    if n1 == 0 or n2 == 0 or idx12.ndim != 2 or idx12.shape[1] == 0:
        return empty
    kp1: tuple[np.ndarray, np.ndarray] | None = None  # keypoints (FGINN only)
    kp2: tuple[np.ndarray, np.ndarray] | None = None
    if conf.fginn:
        k = idx12.shape[1]
        if k < 3 or idx21.shape[1] < 3:
            raise ImtuneError(f"FGINN needs k-NN tables with k > 2 (got k = {k}); compute them with "
                              f"knn_tables(..., k=10)")
        kp1 = _keypoints(kpts1, n1, "image 1")
        kp2 = _keypoints(kpts2, n2, "image 2")

    keep12 = _direction(idx12, dist12, conf, kp2)
    nn12 = idx12[:, 0]
    if conf.strategy == "uni":
        i = np.flatnonzero(keep12)
        return np.stack([i, nn12[i]], 1).astype(np.int32), dist12[i, 0].astype(np.float32)

    keep21 = _direction(idx21, dist21, conf, kp1)
    nn21 = idx21[:, 0]
    if conf.strategy == "both":
        i = np.flatnonzero(keep12)
        j = nn12[i]
        mutual = keep21[j] & (nn21[j] == i)
        i, j = i[mutual], j[mutual]
        return np.stack([i, j], 1).astype(np.int32), dist12[i, 0].astype(np.float32)

    # either: the union of the two lists, each pair once, sorted by i then j
    i1 = np.flatnonzero(keep12)
    j2 = np.flatnonzero(keep21)
    i2 = nn21[j2]
    new = ~(keep12[i2] & (nn12[i2] == j2))  # 2 -> 1 matches not already found 1 -> 2
    j2, i2 = j2[new], i2[new]
    keys = np.concatenate([i1.astype(np.int64) * n2 + nn12[i1], i2.astype(np.int64) * n2 + j2])
    d = np.concatenate([dist12[i1, 0], dist21[j2, 0]])
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    return (np.stack([keys // n2, keys % n2], 1).astype(np.int32), d[order].astype(np.float32))
