"""Calibrated relative-pose estimators: matched points + both cameras' intrinsics -> essential matrix E,
relative pose (R, t), inlier mask, seconds (``model = "E"``).

The same knobs as the F estimators (threshold eta in px, confidence, iteration cap Gamma, seed), so both
families are tuned under the same budget. What differs:

- ``estimate`` takes ``K1, K2`` (3x3, px at the working resolution) and raises ``ImtuneError`` (one line)
  when either is missing: an essential matrix is undefined without the intrinsics;
- the result (:class:`EssentialResult`) carries E (x2n^T E x1n = 0 in normalised coordinates, ||E||_F = 1),
  the pose (R, t) of camera 2 w.r.t. camera 1 (x2 = R x1 + t, |t| = 1) and, for callers that draw epipolar
  geometry, the fundamental matrix it implies, F = K2^-T E K1^-1 (||F||_F = 1);
- when the library returns no pose, it is recovered from E on the inliers (cv2.recoverPose in normalised
  coordinates, cheirality check), as the F path does after E = K2^T F K1;
- eta is in px for every backend; a backend whose library works in normalised coordinates divides it by the
  mean focal length (f1x + f1y + f2x + f2y) / 4 (as hloc and LoFTR do), see :func:`mean_focal`.

Validation and failure rules are the F estimators' (``Estimator.estimate``): degenerate input, a library
exception or fewer than ``min_inliers`` (5) inliers is a failure (E = F = R = t = None, all-False mask).
"""
from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.config import MAX_ITERS
from pipeline.errors import ImtuneError
from pipeline.geometry.base import _LAST, EstimateResult, Estimator, RawSolution, Sizes, sizes_from_points


@dataclass
class EssentialResult(EstimateResult):
    """EstimateResult plus E (3, 3) (x2n^T E x1n = 0, normalised coordinates, ||E||_F = 1), R (3, 3) and
    t (3,) (camera 2 w.r.t. camera 1, unit t); all None on failure. ``F`` is K2^-T E K1^-1."""
    E: np.ndarray | None = None
    R: np.ndarray | None = None
    t: np.ndarray | None = None


@dataclass
class RawEssential:
    """What an E backend's ``_solve_e`` hands back: E (or None), the pose when the library gives one
    (else None: recovered from E on the inliers), the inlier mask (None: recomputed as the Sampson distance
    of F = K2^-T E K1^-1 <= eta, in px), and the seconds of the library call."""
    E: np.ndarray | None
    R: np.ndarray | None
    t: np.ndarray | None
    mask: np.ndarray | None
    seconds: float


def mean_focal(K1: np.ndarray, K2: np.ndarray) -> float:
    """(f1x + f1y + f2x + f2y) / 4 in px: the factor turning a px threshold into a normalised one."""
    return float((K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1]) / 4.0)


def normalise(pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(M, 2) px -> (M, 2) normalised image coordinates K^-1 [x y 1]^T (no distortion)."""
    return cv2.undistortPoints(pts.reshape(-1, 1, 2).astype(np.float64), K, None).reshape(-1, 2)


def pose_from_E(E: np.ndarray, p1n: np.ndarray, p2n: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(R, t) from E and normalised inlier points by cv2.recoverPose (cheirality); (None, None) on failure."""
    if len(p1n) < 5:
        return None, None
    try:
        _, R, t, _ = cv2.recoverPose(np.ascontiguousarray(E, dtype=np.float64), p1n, p2n, np.eye(3))
    except cv2.error:
        return None, None
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None, None
    return R, t.reshape(3)


def checked_intrinsics(name: str, K1, K2) -> tuple[np.ndarray, np.ndarray]:
    """K1, K2 as (3, 3) float64, or a one-line ImtuneError naming the estimator."""
    out = []
    for which, K in (("K1", K1), ("K2", K2)):
        arr = None if K is None else np.asarray(K, dtype=np.float64)
        if arr is None or arr.shape != (3, 3) or not np.all(np.isfinite(arr)) or arr[0, 0] <= 0 or arr[1, 1] <= 0:
            raise ImtuneError(f"estimator {name} estimates an essential matrix and needs both cameras' intrinsics, "
                              f"but {which} is {'missing' if K is None else 'not a valid 3x3 camera matrix'}: "
                              "give the scene its intrinsics or use an F estimator (e.g. degensac)")
        out.append(arr)
    return out[0], out[1]


class EssentialEstimator(Estimator):
    """Base of every E estimator: implement ``_solve_e``. See the module docstring for the conventions."""
    model = "E"
    min_inliers: int = 5

    def estimate(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,  # type: ignore[override]
                 max_iters: int, seed: int = 0, *, sizes: Sizes | None = None, K1: np.ndarray | None = None,
                 K2: np.ndarray | None = None) -> EssentialResult:
        """Estimate E and the relative pose. pts1, pts2: (M, 2) px; threshold: eta in px; K1, K2: (3, 3) px
        (required: ImtuneError without them); the other arguments as :meth:`Estimator.estimate`."""
        K1, K2 = checked_intrinsics(self.name, K1, K2)
        p1, p2, m = self._checked_points(pts1, pts2)
        if p1 is None or p2 is None:
            return self._fail(m)
        if sizes is None:
            sizes = sizes_from_points(p1, p2)
        try:
            max_iters = min(max(int(max_iters), 1), MAX_ITERS)
            _LAST.timer = None
            raw = self._solve_e(p1, p2, K1, K2, float(threshold), float(confidence), max_iters, int(seed), sizes)
        except ImtuneError:
            raise
        except Exception:  # noqa: BLE001 - a library error is a recorded failure, never a crash
            return self._fail(m)
        res = self._finish_e(raw, p1, p2, K1, K2, float(threshold))
        t = getattr(_LAST, "timer", None)  # the backend's ``timed()``: its wall time beside the CPU seconds
        res.wall_seconds = float(t.wall_seconds) if t is not None else 0.0
        return res

    def _solve(self, pts1, pts2, threshold, confidence, max_iters, seed, sizes) -> RawSolution:
        raise ImtuneError(f"estimator {self.name} estimates an essential matrix: call estimate(..., K1=, K2=)")

    @abstractmethod
    def _solve_e(self, pts1: np.ndarray, pts2: np.ndarray, K1: np.ndarray, K2: np.ndarray, threshold: float,
                 confidence: float, max_iters: int, seed: int, sizes: Sizes) -> RawEssential:
        """The library call (timed with ``timed()``); pts in px, validated; threshold eta in px."""

    def _fail(self, m: int, seconds: float = 0.0) -> EssentialResult:
        return EssentialResult(F=None, inliers=np.zeros(max(int(m), 0), dtype=bool), seconds=float(seconds))

    def _finish_e(self, raw: RawEssential, p1: np.ndarray, p2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
                  threshold: float) -> EssentialResult:
        from pipeline.geometry.base import sampson_distance
        m = p1.shape[0]
        E = None if raw.E is None else np.asarray(raw.E, dtype=np.float64)
        if E is None or E.shape != (3, 3) or not np.all(np.isfinite(E)) or np.linalg.norm(E) <= 0:
            return self._fail(m, raw.seconds)
        E = E / np.linalg.norm(E)
        F = np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)
        F = F / np.linalg.norm(F)
        mask = None if raw.mask is None else np.asarray(raw.mask).reshape(-1).astype(bool)
        if mask is None or mask.shape[0] != m:
            mask = sampson_distance(F, p1, p2) <= threshold
        if int(np.count_nonzero(mask)) < self.min_inliers:
            return self._fail(m, raw.seconds)
        R, t = raw.R, raw.t
        if R is None or t is None:
            R, t = pose_from_E(E, normalise(p1[mask], K1), normalise(p2[mask], K2))
        else:
            R, t = np.asarray(R, dtype=np.float64).reshape(3, 3), np.asarray(t, dtype=np.float64).reshape(3)
            n = np.linalg.norm(t)
            t = t / n if n > 0 else t
        if R is None or t is None or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            return self._fail(m, raw.seconds)
        return EssentialResult(F=F, inliers=mask, seconds=float(raw.seconds), E=E, R=R, t=t)
