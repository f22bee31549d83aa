"""pycolmap: ``colmap`` (COLMAP's LO-RANSAC two-view fundamental matrix estimation).

Conventions (pycolmap 4.2.1, checked on synthetic scenes; the function names changed across
versions): ``pycolmap.estimate_fundamental_matrix(points2D1, points2D2, estimation_options:
RANSACOptions, use_sampson_refinement=True) -> dict | None`` with keys ``F`` (x2^T F x1 = 0, no
transpose needed), ``num_inliers`` and ``inlier_mask``; None when no model was found.
RANSACOptions used: ``max_error`` (eta; COLMAP compares the squared Sampson error with max_error^2),
``confidence``, ``max_num_trials`` (Gamma), ``min_num_trials`` (library default 1000; we pass
min(1000, Gamma)), ``random_seed`` (reproducible for a fixed seed >= 0). ``min_inlier_ratio``
keeps the library default (0.01).
"""
from __future__ import annotations

import numpy as np

from pipeline.geometry.base import Estimator, RawSolution, Sizes, require, timed
from pipeline.geometry.registry import ESTIMATORS


@ESTIMATORS.register("colmap")
class ColmapFundamental(Estimator):
    """COLMAP LO-RANSAC (pycolmap.estimate_fundamental_matrix); eta bounds the Sampson distance."""
    name = "colmap"
    package = "pycolmap"
    min_iters: int = 1000

    @classmethod
    def check_available(cls) -> None:
        require("pycolmap", cls.package)

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        from pipeline.colmap_db import import_pycolmap
        pycolmap = import_pycolmap()
        max_iters = max(int(max_iters), 1)
        opt = pycolmap.RANSACOptions()
        opt.max_error = float(threshold)
        opt.confidence = float(confidence)
        opt.max_num_trials = max_iters
        opt.min_num_trials = min(self.min_iters, max_iters)
        opt.random_seed = int(seed) & 0x7FFFFFFF
        opt.num_threads = 1
        with timed() as t:
            res = pycolmap.estimate_fundamental_matrix(pts1, pts2, opt)
        if res is None:
            return RawSolution(None, None, t.seconds)
        return RawSolution(np.asarray(res["F"]), np.asarray(res["inlier_mask"], dtype=bool), t.seconds)
