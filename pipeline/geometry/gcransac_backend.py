"""pygcransac: ``gcransac`` (Graph-Cut RANSAC, Barath & Matas CVPR 2018).

Conventions (pygcransac 0.1.1, checked on synthetic scenes):
``findFundamentalMatrix(correspondences, h1, w1, h2, w2, probabilities, threshold=1.0, conf=0.99,
spatial_coherence_weight=0.0, max_iters=10000, min_iters=50, use_sprt=True,
min_inlier_ratio_for_sprt=1e-05, sampler=1, neighborhood=1, neighborhood_size=20.0, lo_number=50,
sampler_variance=0.1, solver=0)``: matches as one (N, 4) float64 array [x1 y1 x2 y2]; image sizes
*height first* (unlike pymagsac); returns (F, mask) with x2^T F x1 = 0 (no transpose needed).
- Known bug: the returned mask is all False even when F is right (also reported upstream,
  danini/graph-cut-ransac issue 54). We recompute the mask from F as Sampson distance <= threshold,
  which is GC-RANSAC's own inlier criterion, outside the timed call.
- samplers: 0 uniform, 1 PROSAC (library default; needs matches sorted by quality), 2 P-NAPSAC,
  3 importance, 4 AR-sampler; we use 0 (uniform), as tentative matches come unordered.
- ``min_iters`` defaults to 50; we pass min(50, max_iters).
- no seed is exposed: runs are not guaranteed reproducible (``seedable = False``).
"""
from __future__ import annotations

import numpy as np

from pipeline.geometry.base import Estimator, RawSolution, Sizes, packed_correspondences, require, timed
from pipeline.geometry.registry import ESTIMATORS


@ESTIMATORS.register("gcransac")
class GCRansac(Estimator):
    """Graph-Cut RANSAC (pygcransac), threshold eta on the Sampson distance."""
    name = "gcransac"
    package = "pygcransac"
    seedable = False
    seed_used = False
    sampler: int = 0
    min_iters: int = 50
    spatial_coherence_weight: float = 0.0  # library default
    use_sprt: bool = True                  # library default

    @classmethod
    def check_available(cls) -> None:
        require("pygcransac", cls.package)

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        import pygcransac
        corr, probs = packed_correspondences(pts1, pts2)
        (w1, h1), (w2, h2) = sizes
        max_iters = max(int(max_iters), 1)
        with timed() as t:
            F, _mask = pygcransac.findFundamentalMatrix(
                corr, int(np.ceil(h1)), int(np.ceil(w1)), int(np.ceil(h2)), int(np.ceil(w2)), probs,
                threshold=threshold, conf=confidence,
                spatial_coherence_weight=self.spatial_coherence_weight, max_iters=max_iters,
                min_iters=min(self.min_iters, max_iters), use_sprt=self.use_sprt, sampler=self.sampler)
        # the library mask is unreliable (always empty in 0.1.1): recomputed from F by the base class
        return RawSolution(F, None, t.seconds)
