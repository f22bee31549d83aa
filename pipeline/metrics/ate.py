"""Absolute trajectory error (ATE) of a reconstruction's camera centres after a similarity alignment.

The reconstruction's frame and scale are arbitrary, so its camera centres are aligned to the ground
truth's by the least-squares similarity transform (Umeyama, PAMI 1991): dst ~= s R src + t. ATE is the
root mean square of the remaining centre distances, in ground-truth units (metres on Strecha; arbitrary
on SfM pseudo ground truth). At least 3 cameras are needed; fewer gives None (no ATE for that bag).

Note: the official IMC benchmark aligns with a 3-point RANSAC and caps the error at the scene's extent;
this is the plain least-squares alignment over all registered cameras.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

MIN_CAMERAS = 3


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (s, R, t) minimising sum ||dst_k - (s R src_k + t)||^2.

    src, dst: (n, 3). R is a proper rotation (det +1). With ``with_scale`` False, s = 1 (rigid)."""
    src = np.asarray(src, float).reshape(-1, 3)
    dst = np.asarray(dst, float).reshape(-1, 3)
    if len(src) != len(dst) or len(src) == 0:
        raise ValueError("umeyama: src and dst must be non-empty and the same length")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if (with_scale and var_s > 0) else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


@dataclass
class ATEResult:
    """ate: RMSE of centre distances after alignment (GT units); mean / median / max of the same distances;
    scale: the aligned reconstruction's scale factor; n: number of cameras used."""
    ate: float
    mean: float
    median: float
    max: float
    scale: float
    n: int


def absolute_trajectory_error(est_centers: ArrayLike, gt_centers: ArrayLike) -> ATEResult | None:
    """ATE of estimated camera centres (n, 3) against ground-truth centres (n, 3), rows corresponding.

    None when fewer than ``MIN_CAMERAS`` cameras or any centre is non-finite."""
    est = np.asarray(est_centers, float).reshape(-1, 3)
    gt = np.asarray(gt_centers, float).reshape(-1, 3)
    if len(est) < MIN_CAMERAS or len(est) != len(gt) or not (np.isfinite(est).all() and np.isfinite(gt).all()):
        return None
    s, R, t = umeyama(est, gt, with_scale=True)
    d = np.linalg.norm(gt - (s * (R @ est.T).T + t), axis=1)
    return ATEResult(ate=float(np.sqrt((d ** 2).mean())), mean=float(d.mean()), median=float(np.median(d)),
                     max=float(d.max()), scale=s, n=len(d))


def camera_center(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centre C = -R^T t of a world-to-camera pose."""
    R = np.asarray(R, float).reshape(3, 3)
    return -R.T @ np.asarray(t, float).reshape(3)
