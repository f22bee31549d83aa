"""OpenCV ``cv2.findFundamentalMat``: ``cv-ransac`` (FM_RANSAC), ``cv-usac`` (USAC_DEFAULT),
``cv-magsac`` (USAC_MAGSAC), ``cv-accurate`` (USAC_ACCURATE), ``cv-lmeds`` (FM_LMEDS) and ``cv-8pt``
(FM_8POINT on all matches); calibrated: ``cv-e-ransac`` (findEssentialMat, RANSAC) and ``cv-e-magsac``
(findEssentialMat, USAC_MAGSAC), each followed by recoverPose.

Conventions (opencv-contrib-python-headless 5.0.0, checked on synthetic scenes):
``findFundamentalMat(points1, points2, method, ransacReprojThreshold, confidence, maxIters)`` returns
F with x2^T F x1 = 0 (no transpose needed) and an (N, 1) uint8 mask; F is None (or empty) on failure,
and a (9, 3) stack of up to three solutions when exactly 7 points are given (handled by the base).
- threshold semantics differ: FM_RANSAC marks a match an inlier when its distance to the epipolar
  line is <= eta in *both* images (``threshold_kind = "epipolar-line"``, stricter than Sampson at the
  same eta, by about sqrt(2)); the USAC methods use the Sampson distance.
- FM_LMEDS ignores the threshold (its inlier band comes from the median residual).
- FM_8POINT is a plain least-squares fit on all matches: meant for already-filtered (custom)
  matches; every match is reported as an inlier, threshold and iterations are ignored.
- OpenCV takes no seed argument. We call ``cv2.setRNGSeed(seed)`` before each call, as asked, but
  measured in 5.0.0 it changes nothing: FM_RANSAC / FM_LMEDS and the USAC methods all seed their
  own generators with a fixed value, so every run is reproducible and independent of ``seed``
  (``seed_used = False``). Varying it would need the ``UsacParams`` overload
  (``randomGeneratorState``), which does not reproduce the USAC_* presets exactly; not done.
"""
from __future__ import annotations

import numpy as np

from pipeline.geometry.base import Estimator, RawSolution, Sizes, require, timed
from pipeline.geometry.essential import EssentialEstimator, RawEssential, mean_focal, normalise
from pipeline.geometry.registry import ESTIMATORS


class _OpenCVLibrary:
    """What OpenCV's F and E estimators share: the package, seed_used (see the module docstring), the method flag."""
    package = "opencv-contrib-python-headless"
    seed_used = False
    method_name: str = ""

    @classmethod
    def check_available(cls) -> None:
        require("cv2", cls.package)


class _OpenCV(_OpenCVLibrary, Estimator):

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        import cv2
        method = getattr(cv2, self.method_name)
        cv2.setRNGSeed(int(seed) & 0x7FFFFFFF)
        with timed() as t:
            F, mask = cv2.findFundamentalMat(pts1, pts2, method, float(threshold), float(confidence),
                                             max(int(max_iters), 1))
        if F is None or np.size(F) == 0:
            return RawSolution(None, None, t.seconds)
        return RawSolution(F, None if mask is None else mask.reshape(-1).astype(bool), t.seconds)


@ESTIMATORS.register("cv-ransac")
class CvRansac(_OpenCV):
    """OpenCV FM_RANSAC (classic 7-point RANSAC); eta bounds the point-to-epipolar-line distance."""
    name = "cv-ransac"
    method_name = "FM_RANSAC"
    threshold_kind = "epipolar-line"


@ESTIMATORS.register("cv-usac")
class CvUsac(_OpenCV):
    """OpenCV USAC_DEFAULT (LO-RANSAC with degeneracy check); eta bounds the Sampson distance."""
    name = "cv-usac"
    method_name = "USAC_DEFAULT"


@ESTIMATORS.register("cv-magsac")
class CvMagsac(_OpenCV):
    """OpenCV USAC_MAGSAC (MAGSAC++ in USAC); eta bounds the Sampson distance."""
    name = "cv-magsac"
    method_name = "USAC_MAGSAC"


@ESTIMATORS.register("cv-accurate")
class CvAccurate(_OpenCV):
    """OpenCV USAC_ACCURATE (GC-RANSAC local optimisation in USAC); eta bounds the Sampson distance."""
    name = "cv-accurate"
    method_name = "USAC_ACCURATE"


@ESTIMATORS.register("cv-lmeds")
class CvLmeds(_OpenCV):
    """OpenCV FM_LMEDS (least median of squares); no inlier threshold, needs < 50% outliers."""
    name = "cv-lmeds"
    method_name = "FM_LMEDS"
    uses_threshold = False
    threshold_kind = "none"


@ESTIMATORS.register("cv-8pt")
class Cv8Point(_OpenCV):
    """OpenCV FM_8POINT on all matches, all marked inliers (for already-filtered custom matches)."""
    name = "cv-8pt"
    method_name = "FM_8POINT"
    uses_threshold = False
    uses_iterations = False
    threshold_kind = "none"

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        import cv2
        with timed() as t:
            F, _ = cv2.findFundamentalMat(pts1, pts2, cv2.FM_8POINT)
        if F is None or np.size(F) == 0:
            return RawSolution(None, None, t.seconds)
        return RawSolution(F[:3], np.ones(len(pts1), dtype=bool), t.seconds)


class _OpenCVEssential(_OpenCVLibrary, EssentialEstimator):
    """cv2.findEssentialMat (5-point, Nister) on points normalised by K1, K2 with an identity camera matrix,
    threshold eta (px) divided by the mean focal length; the pose by cv2.recoverPose on the inliers."""

    def _solve_e(self, pts1: np.ndarray, pts2: np.ndarray, K1: np.ndarray, K2: np.ndarray, threshold: float,
                 confidence: float, max_iters: int, seed: int, sizes: Sizes) -> RawEssential:
        import cv2
        method = getattr(cv2, self.method_name)
        # two different cameras: normalise each by its own K (the single-K overload assumes one camera)
        p1n, p2n = normalise(pts1, K1), normalise(pts2, K2)
        cv2.setRNGSeed(int(seed) & 0x7FFFFFFF)
        with timed() as t:
            E, mask = cv2.findEssentialMat(p1n, p2n, np.eye(3), method, float(confidence),
                                           float(threshold) / mean_focal(K1, K2), int(max_iters))
        if E is None or np.size(E) == 0:
            return RawEssential(None, None, None, None, t.seconds)
        E = np.asarray(E)[:3]  # up to 10 stacked 5-point solutions on a minimal sample: the first
        return RawEssential(E, None, None, None if mask is None else mask.reshape(-1).astype(bool), t.seconds)


@ESTIMATORS.register("cv-e-ransac")
class CvEssentialRansac(_OpenCVEssential):
    """OpenCV findEssentialMat, RANSAC (5-point) + recoverPose; eta px (/ mean focal), epipolar-line distance.

    Eta (px) divided by the mean focal length bounds the point-to-epipolar-line distance in normalised
    coordinates."""
    name = "cv-e-ransac"
    method_name = "RANSAC"
    threshold_kind = "epipolar-line"


@ESTIMATORS.register("cv-e-magsac")
class CvEssentialMagsac(_OpenCVEssential):
    """OpenCV findEssentialMat, USAC_MAGSAC (MAGSAC++, 5-point) + recoverPose; eta px (/ mean focal).

    Eta (px) divided by the mean focal length is MAGSAC++'s noise-scale bound in normalised coordinates."""
    name = "cv-e-magsac"
    method_name = "USAC_MAGSAC"
