"""PoseLib: ``poselib`` (LO-RANSAC on the 7-point solver with non-linear refinement) and ``poselib-e``
(calibrated: 5-point relative pose, ``estimate_relative_pose``).

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
from pipeline.geometry.essential import EssentialEstimator, RawEssential
from pipeline.geometry.registry import ESTIMATORS


class _PoseLib:
    """What the F and E estimators share: the package and the RANSAC options (see the module docstring)."""
    package = "poselib"
    min_iters: int = 1000

    @classmethod
    def check_available(cls) -> None:
        require("poselib", cls.package)

    def _options(self, threshold: float, confidence: float, max_iters: int, seed: int) -> dict:
        """PoseLib's ransac_opt: eta (px), confidence, Gamma (min_iterations min(1000, Gamma)), seed."""
        max_iters = max(int(max_iters), 1)
        return {"max_epipolar_error": float(threshold), "success_prob": float(confidence),
                "max_iterations": max_iters, "min_iterations": min(self.min_iters, max_iters),
                "seed": int(seed) & 0xFFFFFFFF}


@ESTIMATORS.register("poselib")
class PoseLibFundamental(_PoseLib, Estimator):
    """PoseLib LO-RANSAC (7-point + refinement); eta bounds the Sampson distance."""
    name = "poselib"

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        import poselib
        opt = self._options(threshold, confidence, max_iters, seed)
        with timed() as t:
            F, info = poselib.estimate_fundamental(pts1, pts2, opt, {})
        if F is None or int(info.get("num_inliers", 0)) == 0:
            return RawSolution(None, None, t.seconds)
        return RawSolution(np.asarray(F), np.asarray(info["inliers"], dtype=bool), t.seconds)


def _poselib_camera(K: np.ndarray, size: tuple[float, float]) -> dict:
    """A PoseLib PINHOLE camera dict (fx, fy, cx, cy in px) for intrinsics K and image size (w, h)."""
    return {"model": "PINHOLE", "width": int(size[0]), "height": int(size[1]),
            "params": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]}


@ESTIMATORS.register("poselib-e")
class PoseLibEssential(_PoseLib, EssentialEstimator):
    """PoseLib LO-RANSAC on the 5-point solver with non-linear refinement (estimate_relative_pose); eta in px.

    PoseLib takes the cameras and a px threshold (``max_epipolar_error``), which it divides by the mean focal
    length itself before scoring Sampson errors in normalised coordinates; it returns the refined pose
    (R, t: x2 = R x1 + t) and E is formed from it ([t]_x R). Options as for ``poselib``."""
    name = "poselib-e"

    def _solve_e(self, pts1: np.ndarray, pts2: np.ndarray, K1: np.ndarray, K2: np.ndarray, threshold: float,
                 confidence: float, max_iters: int, seed: int, sizes: Sizes) -> RawEssential:
        import poselib
        opt = self._options(threshold, confidence, max_iters, seed)
        cam1, cam2 = _poselib_camera(K1, sizes[0]), _poselib_camera(K2, sizes[1])
        with timed() as t:
            pose, info = poselib.estimate_relative_pose(pts1, pts2, cam1, cam2, opt, {})
        if pose is None or int(info.get("num_inliers", 0)) == 0:
            return RawEssential(None, None, None, None, t.seconds)
        R, tv = np.asarray(pose.R), np.asarray(pose.t).reshape(3)
        tx = np.array([[0, -tv[2], tv[1]], [tv[2], 0, -tv[0]], [-tv[1], tv[0], 0]])
        return RawEssential(tx @ R, R, tv, np.asarray(info["inliers"], dtype=bool), t.seconds)
