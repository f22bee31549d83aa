"""pycolmap: ``colmap`` (COLMAP's LO-RANSAC two-view fundamental matrix estimation) and ``colmap-e``
(calibrated: 5-point essential matrix, ``estimate_essential_matrix``).

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
from pipeline.geometry.essential import EssentialEstimator, RawEssential
from pipeline.geometry.registry import ESTIMATORS


class _Colmap:
    """What the F and E estimators share: the package and the RANSAC options (see the module docstring)."""
    package = "pycolmap"
    min_iters: int = 1000

    @classmethod
    def check_available(cls) -> None:
        require("pycolmap", cls.package)

    def _options(self, pycolmap, threshold: float, confidence: float, max_iters: int, seed: int):
        """pycolmap.RANSACOptions: eta (px), confidence, Gamma (min_num_trials min(1000, Gamma)), seed, 1 thread."""
        max_iters = max(int(max_iters), 1)
        opt = pycolmap.RANSACOptions()
        opt.max_error = float(threshold)
        opt.confidence = float(confidence)
        opt.max_num_trials = max_iters
        opt.min_num_trials = min(self.min_iters, max_iters)
        opt.random_seed = int(seed) & 0x7FFFFFFF
        opt.num_threads = 1
        return opt


@ESTIMATORS.register("colmap")
class ColmapFundamental(_Colmap, Estimator):
    """COLMAP LO-RANSAC (pycolmap.estimate_fundamental_matrix); eta bounds the Sampson distance."""
    name = "colmap"

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        from pipeline.colmap_db import import_pycolmap
        pycolmap = import_pycolmap()
        opt = self._options(pycolmap, threshold, confidence, max_iters, seed)
        with timed() as t:
            res = pycolmap.estimate_fundamental_matrix(pts1, pts2, opt)
        if res is None:
            return RawSolution(None, None, t.seconds)
        return RawSolution(np.asarray(res["F"]), np.asarray(res["inlier_mask"], dtype=bool), t.seconds)


def _colmap_camera(pycolmap, K: np.ndarray, size: tuple[float, float]):
    """A pycolmap PINHOLE camera (fx, fy, cx, cy in px) for intrinsics K and image size (w, h)."""
    return pycolmap.Camera(model="PINHOLE", width=int(size[0]), height=int(size[1]),
                           params=[float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])])


@ESTIMATORS.register("colmap-e")
class ColmapEssential(_Colmap, EssentialEstimator):
    """COLMAP LO-RANSAC on the 5-point solver (pycolmap.estimate_essential_matrix); eta in px.

    pycolmap takes both cameras and a px ``max_error``, which it converts to normalised coordinates with each
    camera's focal length (``CamFromImgThreshold``, averaged over the two cameras); it decomposes E with the
    cheirality check and returns ``cam2_from_cam1`` (R, t: x2 = R x1 + t). Options as for ``colmap``."""
    name = "colmap-e"

    def _solve_e(self, pts1: np.ndarray, pts2: np.ndarray, K1: np.ndarray, K2: np.ndarray, threshold: float,
                 confidence: float, max_iters: int, seed: int, sizes: Sizes) -> RawEssential:
        from pipeline.colmap_db import import_pycolmap
        pycolmap = import_pycolmap()
        opt = self._options(pycolmap, threshold, confidence, max_iters, seed)
        cam1, cam2 = _colmap_camera(pycolmap, K1, sizes[0]), _colmap_camera(pycolmap, K2, sizes[1])
        with timed() as t:
            res = pycolmap.estimate_essential_matrix(pts1, pts2, cam1, cam2, opt)
        if res is None:
            return RawEssential(None, None, None, None, t.seconds)
        pose = res["cam2_from_cam1"]
        return RawEssential(np.asarray(res["E"]), np.asarray(pose.rotation.matrix()),
                            np.asarray(pose.translation).reshape(3), np.asarray(res["inlier_mask"], dtype=bool),
                            t.seconds)
