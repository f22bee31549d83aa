"""Pose errors and mean average accuracy, exactly as the IMC protocol defines them.

Rotation error: the angle of R_gt^T R, in degrees. Translation error: the angle between the estimated
and true translation directions, sign-agnostic (arccos |t . t_gt|, both unit), in degrees — stereo
recovers t only up to scale and sign. Pair error = max of the two; a failed pair is +inf.
mAA(tau) = mean over thresholds 1, 2, ..., tau degrees of the fraction of pairs with error <= threshold.
"""
from __future__ import annotations

import numpy as np


def rotation_error_deg(R_gt: np.ndarray, R: np.ndarray) -> float:
    """Geodesic angle between two rotations, degrees.

    atan2(sin, cos) of the relative rotation rather than arccos of the trace: arccos loses all
    precision below ~0.01 deg, where well-conditioned pairs live."""
    M = np.asarray(R_gt, float).T @ np.asarray(R, float)
    cos = (np.trace(M) - 1.0) / 2.0
    sin = 0.5 * np.linalg.norm([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    return float(np.degrees(np.arctan2(sin, cos)))


def translation_error_deg(t_gt: np.ndarray, t: np.ndarray) -> float:
    """Sign-agnostic angle between translation directions, degrees; inf if either is ~zero."""
    a = np.asarray(t_gt, float).reshape(3)
    b = np.asarray(t, float).reshape(3)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-12 or nb < 1e-12 or not np.isfinite(na * nb):
        return float("inf")
    cos = abs(float(a @ b)) / float(na * nb)
    return float(np.degrees(np.arccos(min(1.0, cos))))


def pose_error_deg(R_gt, t_gt, R, t) -> tuple[float, float, float]:
    """(max error, rotation error, translation error) in degrees; all inf when R or t is None."""
    if R is None or t is None:
        return float("inf"), float("inf"), float("inf")
    er = rotation_error_deg(R_gt, R)
    et = translation_error_deg(t_gt, t)
    return max(er, et), er, et


def accuracy_curve(errors, tau: int = 10) -> np.ndarray:
    """Fraction of pairs with error <= k degrees, for k = 1..tau (inf errors count as failures)."""
    e = np.asarray(list(errors), float)
    if e.size == 0:
        return np.zeros(tau)
    return np.array([(e <= k).mean() for k in range(1, tau + 1)])


def mean_average_accuracy(errors, tau: int = 10) -> float:
    """mAA(tau): mean over thresholds 1..tau degrees of the accuracy. 0 for no pairs."""
    return float(accuracy_curve(errors, tau).mean())
