"""Intermediate metrics: keypoint repeatability and matching score, as in the IMC benchmark.

With depth maps (IMC-PT ``depth_maps/<key>.h5``; 0 = unknown):
- repeatability at t px: of the keypoints of image 1 that have a depth and project inside image 2, the
  fraction whose nearest keypoint of image 2 lies within t px; averaged over both directions.
- matching score (depth) at t px: the fraction of matches, among those whose two keypoints have a depth,
  whose keypoint in image 2 reprojected into image 1 lies within t px of its partner (the official code's
  definition). Thresholds 1..10 px; 3 px is the headline.
Without depth:
- epipolar matching score: the fraction of matches whose symmetric squared epipolar distance to the
  ground-truth essential matrix, in normalised camera coordinates, is below 1e-4 (the official value).

All pixel quantities are in the frame of the keypoints (the working resolution): give K for that frame.
Depth maps may be at another resolution (the image on disk): pass ``depth_scale`` = (sx, sy) from the
depth map's frame to the keypoints' (working px = (disk px + 0.5) * s - 0.5).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError

PX_THRESHOLDS: tuple[int, ...] = tuple(range(1, 11))
HEADLINE_PX = 3
EPIPOLAR_THRESHOLD = 1e-4


def load_depth(path: Path | str) -> np.ndarray:
    """A depth map (H, W) float from an IMC-PT h5 file (dataset ``depth``) or a .npy file; 0 = unknown."""
    path = Path(path)
    try:
        if path.suffix == ".npy":
            d = np.load(path, allow_pickle=False)
        else:
            import h5py
            with h5py.File(path, "r") as f:
                key = "depth" if "depth" in f else next(iter(f.keys()))
                d = f[key][()]
    except (OSError, KeyError, StopIteration, ValueError) as e:
        raise ImtuneError(f"cannot read depth map {path}: {e}") from None
    d = np.asarray(d, np.float64).squeeze()
    if d.ndim != 2:
        raise ImtuneError(f"depth map {path}: expected a 2D array, got shape {d.shape}")
    d[~np.isfinite(d)] = 0.0
    return d


def depth_at(kpts: np.ndarray, depth: np.ndarray, depth_scale: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Depth of each keypoint (n,) by nearest pixel; 0 where outside the map or unknown.

    ``depth_scale`` (sx, sy) maps depth-map px to keypoint px (see the module docstring)."""
    kpts = np.asarray(kpts, float).reshape(-1, 2)
    sx, sy = depth_scale
    u = np.round((kpts[:, 0] + 0.5) / sx - 0.5).astype(np.int64)
    v = np.round((kpts[:, 1] + 0.5) / sy - 0.5).astype(np.int64)
    h, w = depth.shape
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.zeros(len(kpts))
    out[ok] = depth[v[ok], u[ok]]
    out[~np.isfinite(out) | (out < 0)] = 0.0
    return out


def transfer(kpts: np.ndarray, depth: np.ndarray, K1: np.ndarray, K2: np.ndarray, R_12: np.ndarray,
             t_12: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of image 1 (n, 2) with depths (n,) -> their projections in image 2 (n, 2) and depths there.

    R_12, t_12: relative pose (x_2 = R_12 x_1 + t_12)."""
    kpts = np.asarray(kpts, float).reshape(-1, 2)
    h = np.c_[kpts, np.ones(len(kpts))]
    X1 = (np.linalg.inv(K1) @ h.T).T * np.asarray(depth, float).reshape(-1, 1)
    X2 = (np.asarray(R_12, float) @ X1.T).T + np.asarray(t_12, float).reshape(1, 3)
    z = X2[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (K2 @ X2.T).T
        p = x[:, :2] / x[:, 2:3]
    return p, z


def _inside(p: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    return np.isfinite(p).all(1) & (p[:, 0] >= -0.5) & (p[:, 0] < w - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] < h - 0.5)


def _one_way_repeatability(p: np.ndarray, kpts2: np.ndarray, thresholds) -> np.ndarray:
    if len(p) == 0 or len(kpts2) == 0:
        return np.zeros(len(thresholds))
    from scipy.spatial import cKDTree
    d, _ = cKDTree(np.asarray(kpts2, float)).query(p, k=1)
    return np.array([(d < t).mean() for t in thresholds])


def repeatability(kpts1, kpts2, depth1, depth2, K1, K2, R_12, t_12, size1, size2,
                  thresholds=PX_THRESHOLDS, depth_scale1=(1.0, 1.0), depth_scale2=(1.0, 1.0)) -> np.ndarray:
    """Repeatability at each threshold (px), averaged over both directions (see the module docstring).

    kpts*: (n, 2) px; depth*: depth maps; K*: intrinsics in keypoint px; R_12, t_12: pose of 2 w.r.t. 1;
    size*: (w, h) of the images in keypoint px."""
    R_12 = np.asarray(R_12, float)
    t_12 = np.asarray(t_12, float).reshape(3)
    R_21, t_21 = R_12.T, -R_12.T @ t_12
    out = []
    for ka, kb, da, Ka, Kb, R, t, sb, sa in ((kpts1, kpts2, depth1, K1, K2, R_12, t_12, size2, depth_scale1),
                                             (kpts2, kpts1, depth2, K2, K1, R_21, t_21, size1, depth_scale2)):
        ka = np.asarray(ka, float).reshape(-1, 2)
        z = depth_at(ka, da, sa)
        p, z2 = transfer(ka, z, Ka, Kb, R, t)
        ok = (z > 0) & (z2 > 0) & _inside(p, sb)
        out.append(_one_way_repeatability(p[ok], kb, thresholds))
    return (out[0] + out[1]) / 2.0


def match_reprojection_errors(kpts1, kpts2, matches, depth1, depth2, K1, K2, R_12, t_12,
                              depth_scale1=(1.0, 1.0), depth_scale2=(1.0, 1.0)) -> np.ndarray:
    """Per match (among those with a depth at both keypoints): the distance (px) in image 1 between the
    keypoint of image 1 and its partner of image 2 reprojected through image 2's depth."""
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    if len(m) == 0:
        return np.zeros(0)
    a = np.asarray(kpts1, float).reshape(-1, 2)[m[:, 0]]
    b = np.asarray(kpts2, float).reshape(-1, 2)[m[:, 1]]
    za = depth_at(a, depth1, depth_scale1)
    zb = depth_at(b, depth2, depth_scale2)
    ok = (za > 0) & (zb > 0)
    R_12 = np.asarray(R_12, float)
    t_12 = np.asarray(t_12, float).reshape(3)
    p, z = transfer(b[ok], zb[ok], K2, K1, R_12.T, -R_12.T @ t_12)
    d = np.linalg.norm(p - a[ok], axis=1)
    d[~np.isfinite(d) | (z <= 0)] = np.inf
    return d


def matching_score(errors: np.ndarray, thresholds=PX_THRESHOLDS) -> np.ndarray:
    """Fraction of matches with error below each threshold; zeros when there are no matches."""
    e = np.asarray(errors, float).reshape(-1)
    if e.size == 0:
        return np.zeros(len(thresholds))
    return np.array([(e < t).mean() for t in thresholds])


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def symmetric_epipolar_distance(x1n: np.ndarray, x2n: np.ndarray, R_12: np.ndarray, t_12: np.ndarray) -> np.ndarray:
    """Symmetric squared epipolar distance of normalised correspondences (n, 2) under E = [t]x R."""
    E = _skew(np.asarray(t_12, float).reshape(3)) @ np.asarray(R_12, float)
    h1 = np.c_[np.asarray(x1n, float).reshape(-1, 2), np.ones(len(x1n))]
    h2 = np.c_[np.asarray(x2n, float).reshape(-1, 2), np.ones(len(x2n))]
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    num = np.einsum("ij,ij->i", h2, Ex1) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = num * (1.0 / (Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2) + 1.0 / (Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2))
    d[~np.isfinite(d)] = np.inf
    return d


def epipolar_matching_score(kpts1, kpts2, matches, K1, K2, R_12, t_12, threshold: float = EPIPOLAR_THRESHOLD) -> float:
    """Fraction of matches whose symmetric squared epipolar distance (normalised coordinates) < threshold."""
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    if len(m) == 0:
        return 0.0
    t = np.asarray(t_12, float).reshape(3)
    n = np.linalg.norm(t)
    if n < 1e-12:
        raise ImtuneError("epipolar matching score undefined for a pure rotation (zero baseline)")

    def norm(k, K):
        h = np.c_[np.asarray(k, float).reshape(-1, 2), np.ones(len(k))]
        return (np.linalg.inv(K) @ h.T).T[:, :2]
    x1 = norm(np.asarray(kpts1, float).reshape(-1, 2)[m[:, 0]], np.asarray(K1, float))
    x2 = norm(np.asarray(kpts2, float).reshape(-1, 2)[m[:, 1]], np.asarray(K2, float))
    d = symmetric_epipolar_distance(x1, x2, R_12, t / n)
    return float((d < threshold).mean())


def pair_intermediate(kpts1, kpts2, matches, K1, K2, R_12, t_12, size1, size2, depth1=None, depth2=None,
                      depth_scale1=(1.0, 1.0), depth_scale2=(1.0, 1.0), thresholds=PX_THRESHOLDS) -> dict:
    """Every intermediate metric that the pair's ground truth allows, as one record:
    {"repeatability": [..], "matching_score": [..]} with depth maps; {"epipolar_matching_score": x} always."""
    rec: dict = {"thresholds_px": list(thresholds)}
    try:
        rec["epipolar_matching_score"] = epipolar_matching_score(kpts1, kpts2, matches, K1, K2, R_12, t_12)
    except ImtuneError:  # zero baseline: no epipolar geometry
        rec["epipolar_matching_score"] = None
    if depth1 is not None and depth2 is not None:
        rec["repeatability"] = [float(x) for x in repeatability(
            kpts1, kpts2, depth1, depth2, K1, K2, R_12, t_12, size1, size2, thresholds, depth_scale1, depth_scale2)]
        err = match_reprojection_errors(kpts1, kpts2, matches, depth1, depth2, K1, K2, R_12, t_12,
                                        depth_scale1, depth_scale2)
        rec["matching_score"] = [float(x) for x in matching_score(err, thresholds)]
    return rec


def mean_intermediate(recs: list[dict], thresholds) -> dict:
    out: dict = {"pairs": len(recs), "thresholds_px": list(thresholds)}
    eps = [r["epipolar_matching_score"] for r in recs if r.get("epipolar_matching_score") is not None]
    out["epipolar_matching_score"] = float(np.mean(eps)) if eps else None
    for key in ("repeatability", "matching_score"):
        vals = [r[key] for r in recs if key in r]
        if vals:
            curve = np.mean(vals, axis=0)
            out[key] = [float(x) for x in curve]
            if HEADLINE_PX in thresholds:
                out[f"{key}_{HEADLINE_PX}px"] = float(curve[list(thresholds).index(HEADLINE_PX)])
            out[f"{key}_pairs"] = len(vals)
    return out


def mean_of_scenes(parts: list[dict], thresholds) -> dict:
    out: dict = {"pairs": int(sum(p["pairs"] for p in parts)), "thresholds_px": list(thresholds)}
    eps = [p["epipolar_matching_score"] for p in parts if p.get("epipolar_matching_score") is not None]
    out["epipolar_matching_score"] = float(np.mean(eps)) if eps else None
    for key in ("repeatability", "matching_score"):
        vals = [p[key] for p in parts if key in p]
        if vals:
            curve = np.mean(vals, axis=0)
            out[key] = [float(x) for x in curve]
            if HEADLINE_PX in thresholds:
                out[f"{key}_{HEADLINE_PX}px"] = float(curve[list(thresholds).index(HEADLINE_PX)])
    return out
