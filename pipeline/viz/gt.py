"""Error of each match against the ground truth, in px at the working resolution.

Two measures, chosen per pair by :func:`match_errors`:

- ``"depth"`` (the scene has depth maps, IMC-PT ``depth_maps/<key>.h5``): the reprojection error through the
  ground-truth depth. A keypoint of image 1 is lifted with its depth (nearest depth pixel; 0 = unknown), moved
  by the ground-truth relative pose and projected into image 2; the error is its distance to the matched
  keypoint there. Both directions are computed; the error is their mean where both keypoints have a depth,
  the one available direction otherwise, and NaN (not computable) where neither has one. A lifted point
  that lands behind the other camera has error +inf.
- ``"epipolar"`` (no depth maps): the symmetric epipolar distance to the ground-truth fundamental matrix
  F = K2^-T [t]x R K1^-1 (ground-truth relative pose, intrinsics scaled to the working resolution): the mean of
  the distance of x2 to the epipolar line F x1 and of x1 to the line F^T x2.

Without a ground-truth pose every error is NaN (kind ``"none"``).
"""
from __future__ import annotations

import numpy as np

from pipeline.data.scene import Pair, Scene

ERROR_KINDS = {
    "depth": "reprojection error through the ground-truth depth maps",
    "epipolar": "symmetric epipolar distance to the ground-truth F",
    "none": "no ground truth: errors not computable",
}


def skew(t: np.ndarray) -> np.ndarray:
    x, y, z = np.asarray(t, float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def gt_fundamental(K1: np.ndarray, K2: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """F with x2^T F x1 = 0 from the relative pose (x_2 = R x_1 + t) and the intrinsics; ||F||_F = 1."""
    E = skew(t) @ np.asarray(R, float)
    F = np.linalg.inv(np.asarray(K2, float)).T @ E @ np.linalg.inv(np.asarray(K1, float))
    n = np.linalg.norm(F)
    return F / n if n > 0 else F


def epipolar_distances(F: np.ndarray, pts1: np.ndarray, pts2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance of x1 to the line F^T x2, distance of x2 to the line F x1), px, each (M,)."""
    p1 = np.asarray(pts1, float).reshape(-1, 2)
    p2 = np.asarray(pts2, float).reshape(-1, 2)
    h1 = np.c_[p1, np.ones(len(p1))]
    h2 = np.c_[p2, np.ones(len(p2))]
    l2 = h1 @ np.asarray(F, float).T  # lines in image 2
    l1 = h2 @ np.asarray(F, float)    # lines in image 1
    num = np.abs(np.sum(h2 * l2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = num / np.hypot(l2[:, 0], l2[:, 1])
        d1 = num / np.hypot(l1[:, 0], l1[:, 1])
    return d1, d2


def symmetric_epipolar_distance(F: np.ndarray, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
    """Mean of the two point-to-epipolar-line distances, px, (M,)."""
    d1, d2 = epipolar_distances(F, pts1, pts2)
    return 0.5 * (d1 + d2)


def _one_way(p_src, p_dst, depth, scale, K_src, K_dst, R, t):
    from pipeline.metrics.repeatability import depth_at, transfer
    if depth is None:
        return np.full(len(p_src), np.nan)
    z = depth_at(p_src, depth, scale)
    err = np.full(len(p_src), np.nan)
    ok = z > 0
    if ok.any():
        proj, z2 = transfer(p_src[ok], z[ok], K_src, K_dst, R, t)
        e = np.linalg.norm(proj - p_dst[ok], axis=1)
        e[~(z2 > 0) | ~np.isfinite(e)] = np.inf
        err[ok] = e
    return err


def depth_reprojection_errors(pts1: np.ndarray, pts2: np.ndarray, K1: np.ndarray, K2: np.ndarray, R: np.ndarray,
                              t: np.ndarray, depth1: np.ndarray | None = None, depth2: np.ndarray | None = None,
                              depth_scale1: tuple[float, float] = (1.0, 1.0),
                              depth_scale2: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Reprojection error (px) of each match through the depth maps (see the module docstring), (M,).

    R, t: pose of camera 2 w.r.t. camera 1 (x_2 = R x_1 + t, same units as the depth); K*: intrinsics at the
    keypoints' resolution; depth_scale*: (sx, sy) from depth-map px to keypoint px."""
    p1 = np.asarray(pts1, float).reshape(-1, 2)
    p2 = np.asarray(pts2, float).reshape(-1, 2)
    R = np.asarray(R, float)
    t = np.asarray(t, float).reshape(3)
    e12 = _one_way(p1, p2, depth1, depth_scale1, K1, K2, R, t)
    e21 = _one_way(p2, p1, depth2, depth_scale2, K2, K1, R.T, -R.T @ t)
    has12, has21 = ~np.isnan(e12), ~np.isnan(e21)
    with np.errstate(invalid="ignore"):
        return np.where(has12 & has21, 0.5 * (e12 + e21), np.where(has12, e12, e21))


def match_errors(scene: Scene, pair: Pair, pts1: np.ndarray, pts2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                 sizes: tuple[tuple[int, int], tuple[int, int]], use_depth: bool = True) -> tuple[np.ndarray, str]:
    """(errors (M,) px, kind) of matches of ``pair`` (keypoints at the working resolution).

    K1, K2: intrinsics at the working resolution; sizes: ((w1, h1), (w2, h2)) working px (to scale depth maps).
    kind: "depth" where either image has a depth map (and ``use_depth``), else "epipolar"; "none" without a
    ground-truth pose (errors all NaN)."""
    from pipeline.metrics.repeatability import load_depth
    m = len(np.asarray(pts1).reshape(-1, 2))
    try:
        R, t = scene.relative_pose(pair)
    except (ValueError, KeyError, TypeError):
        return np.full(m, np.nan), "none"
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return np.full(m, np.nan), "none"
    d1p = scene.images[pair.i].depth_path if pair.i in scene.images else None
    d2p = scene.images[pair.j].depth_path if pair.j in scene.images else None
    if use_depth and (d1p is not None or d2p is not None):
        d1 = load_depth(d1p) if d1p is not None else None
        d2 = load_depth(d2p) if d2p is not None else None

        def scale(d, size):
            return (1.0, 1.0) if d is None else (size[0] / d.shape[1], size[1] / d.shape[0])
        e = depth_reprojection_errors(pts1, pts2, K1, K2, R, t, d1, d2, scale(d1, sizes[0]), scale(d2, sizes[1]))
        return e, "depth"
    if np.linalg.norm(t) < 1e-12:
        return np.full(m, np.nan), "none"  # pure rotation: F is undefined
    return symmetric_epipolar_distance(gt_fundamental(K1, K2, R, t), pts1, pts2), "epipolar"
