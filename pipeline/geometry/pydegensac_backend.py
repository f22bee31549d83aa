"""pydegensac (Mishkin's DEGENSAC): ``pyransac`` (plain LO-RANSAC, degeneracy check off) and
``degensac`` (Chum et al. 2005 check for a dominant plane on).

Conventions (pydegensac 0.3.0, checked on synthetic scenes): ``findFundamentalMatrix(pts1, pts2,
px_th, conf, max_iters, laf_consistensy_coef, error_type, symmetric_error_check,
enable_degeneracy_check, seed)`` returns F with x2^T F x1 = 0 (no transpose needed) and a bool mask;
with ``error_type="sampson"`` a match is an inlier when its Sampson distance is <= px_th.
``symmetric_error_check=True`` (the default, and what the official IMC benchmark uses) additionally
drops a few matches; we keep the library default. A zero F means "no model". ``seed`` >= 0 makes a
run reproducible (-1 lets the library pick a seed; we always pass the caller's seed, masked to
0..2^31-1).
"""
from __future__ import annotations

import numpy as np

from pipeline.geometry.base import Estimator, RawSolution, Sizes, require, timed
from pipeline.geometry.registry import ESTIMATORS


class _PyDegensac(Estimator):
    package = "pydegensac"
    enable_degeneracy_check: bool = True
    error_type: str = "sampson"
    symmetric_error_check: bool = True

    @classmethod
    def check_available(cls) -> None:
        require("pydegensac", cls.package)

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        import pydegensac
        with timed() as t:
            F, mask = pydegensac.findFundamentalMatrix(
                pts1, pts2, px_th=threshold, conf=confidence, max_iters=max_iters,
                laf_consistensy_coef=-1.0, error_type=self.error_type,
                symmetric_error_check=self.symmetric_error_check,
                enable_degeneracy_check=self.enable_degeneracy_check, seed=int(seed) & 0x7FFFFFFF)
        if F is None or not np.any(F):
            return RawSolution(None, None, t.seconds)
        return RawSolution(F, mask, t.seconds)


@ESTIMATORS.register("pyransac")
class PyRansac(_PyDegensac):
    """LO-RANSAC from pydegensac with the degeneracy check off (the paper's "PyRANSAC")."""
    name = "pyransac"
    enable_degeneracy_check = False


@ESTIMATORS.register("degensac")
class Degensac(_PyDegensac):
    """DEGENSAC (pydegensac): LO-RANSAC with the dominant-plane degeneracy check on."""
    name = "degensac"
    enable_degeneracy_check = True
