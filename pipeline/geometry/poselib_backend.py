"""PoseLib: ``poselib`` (LO-RANSAC on the 7-point solver with non-linear refinement).

Conventions (poselib 2.0.5, checked on synthetic scenes):
``estimate_fundamental(points2D_1, points2D_2, ransac_opt: dict, bundle_opt: dict, initial_F=None)``
returns (F, info) with x2^T F x1 = 0 (no transpose needed); ``info["inliers"]`` is a list of bool.
Ransac options used: ``max_epipolar_error`` (eta; a Sampson-distance bound in px),
``success_prob`` (confidence), ``max_iterations`` (Gamma), ``min_iterations`` (library default 1000;
we pass min(1000, Gamma) so the cap is honoured), ``seed`` (reproducible for a fixed seed).
The inlier mask is the one PoseLib scored before its final refinement, so a few matches sit just
across the threshold under the returned F.
"""
from __future__ import annotations

import numpy as np

from pipeline.geometry.base import Estimator, RawSolution, Sizes, require, timed
from pipeline.geometry.registry import ESTIMATORS


@ESTIMATORS.register("poselib")
class PoseLibFundamental(Estimator):
    """PoseLib LO-RANSAC (7-point + refinement); eta bounds the Sampson distance."""
    name = "poselib"
    package = "poselib"
    min_iters: int = 1000

    @classmethod
    def check_available(cls) -> None:
        require("poselib", cls.package)

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        import poselib
        max_iters = max(int(max_iters), 1)
        opt = {"max_epipolar_error": float(threshold), "success_prob": float(confidence),
               "max_iterations": max_iters, "min_iterations": min(self.min_iters, max_iters),
               "seed": int(seed) & 0xFFFFFFFF}
        with timed() as t:
            F, info = poselib.estimate_fundamental(pts1, pts2, opt, {})
        if F is None or int(info.get("num_inliers", 0)) == 0:
            return RawSolution(None, None, t.seconds)
        return RawSolution(np.asarray(F), np.asarray(info["inliers"], dtype=bool), t.seconds)
