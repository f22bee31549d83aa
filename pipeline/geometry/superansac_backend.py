"""SupeRANSAC (``pysuperansac``): ``superansac`` (fundamental matrix) and ``superansac-e`` (calibrated
essential matrix, 5-point), both with the library's default pipeline (PROSAC sampler, MAGSAC scoring,
nested-RANSAC local optimisation, iterated least-squares final fit).

Conventions (pysuperansac 1.0, checked on synthetic scenes):
``estimateFundamentalMatrix(correspondences (M, 4) [x1 y1 x2 y2] float64, image_sizes [w1, h1, w2, h2],
probabilities=[], config=RANSACSettings) -> (F, inlier indices, score, iterations)`` with x2^T F x1 = 0;
``estimateEssentialMatrix(correspondences, K1, K2, image_sizes, probabilities, config)`` -> (E, ...) with
x2n^T E x1n = 0 in normalised coordinates. In both, ``config.inlier_threshold`` is in px (the E estimator
normalises the points and the threshold by the intrinsics itself: at 1 px noise the inlier counts of E and
F at the same threshold agree), and with MAGSAC scoring it is the noise-scale bound (a MAGSAC-like eta).
Settings used: ``inlier_threshold`` (eta), ``confidence``, ``max_iterations`` (Gamma), ``min_iterations``
(library default 1000; we pass min(1000, Gamma)). SupeRANSAC takes no seed (``seedable = False``).
The pose of ``superansac-e`` comes from cv2.recoverPose on its inliers.
"""
from __future__ import annotations

import numpy as np

from pipeline.geometry.base import Estimator, RawSolution, Sizes, require, timed
from pipeline.geometry.essential import EssentialEstimator, RawEssential
from pipeline.geometry.registry import ESTIMATORS


def _settings(threshold: float, confidence: float, max_iters: int, min_iters: int):
    import pysuperansac
    c = pysuperansac.RANSACSettings()
    c.inlier_threshold = float(threshold)
    c.confidence = float(confidence)
    c.max_iterations = int(max_iters)
    c.min_iterations = min(int(min_iters), int(max_iters))
    return c


def _mask(indices, m: int) -> np.ndarray:
    mask = np.zeros(m, dtype=bool)
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    mask[idx[(idx >= 0) & (idx < m)]] = True
    return mask


class _SupeRansac:
    """What the F and E estimators share: the package, no seed, the library's inputs."""
    package = "pysuperansac"
    seedable = False
    seed_used = False
    min_iters: int = 1000

    @classmethod
    def check_available(cls) -> None:
        require("pysuperansac", cls.package)

    def _inputs(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float, max_iters: int,
                sizes: Sizes) -> tuple:
        """(correspondences (M, 4), config, [w1, h1, w2, h2]) as pysuperansac takes them."""
        corr = np.ascontiguousarray(np.concatenate([pts1, pts2], axis=1))
        cfg = _settings(threshold, confidence, max_iters, self.min_iters)
        wh = [float(sizes[0][0]), float(sizes[0][1]), float(sizes[1][0]), float(sizes[1][1])]
        return corr, cfg, wh


@ESTIMATORS.register("superansac")
class SupeRansacFundamental(_SupeRansac, Estimator):
    """SupeRANSAC fundamental matrix (7-point, MAGSAC scoring); eta in px (MAGSAC-like noise bound)."""
    name = "superansac"

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        import pysuperansac
        corr, cfg, wh = self._inputs(pts1, pts2, threshold, confidence, max_iters, sizes)
        with timed() as t:
            F, inliers, _score, _iters = pysuperansac.estimateFundamentalMatrix(corr, wh, config=cfg)
        if F is None or len(inliers) == 0:
            return RawSolution(None, None, t.seconds)
        return RawSolution(np.asarray(F), _mask(inliers, len(pts1)), t.seconds)


@ESTIMATORS.register("superansac-e")
class SupeRansacEssential(_SupeRansac, EssentialEstimator):
    """SupeRANSAC essential matrix (5-point, MAGSAC scoring) given K1, K2, + recoverPose; eta in px.

    The library normalises the points and the px threshold by the intrinsics itself."""
    name = "superansac-e"

    def _solve_e(self, pts1: np.ndarray, pts2: np.ndarray, K1: np.ndarray, K2: np.ndarray, threshold: float,
                 confidence: float, max_iters: int, seed: int, sizes: Sizes) -> RawEssential:
        import pysuperansac
        corr, cfg, wh = self._inputs(pts1, pts2, threshold, confidence, max_iters, sizes)
        with timed() as t:
            E, inliers, _score, _iters = pysuperansac.estimateEssentialMatrix(
                corr, np.ascontiguousarray(K1), np.ascontiguousarray(K2), wh, config=cfg)
        if E is None or len(inliers) == 0:
            return RawEssential(None, None, None, None, t.seconds)
        return RawEssential(np.asarray(E), None, None, _mask(inliers, len(pts1)), t.seconds)
