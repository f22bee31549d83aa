"""pymagsac: ``magsac`` (MAGSAC, Barath et al. CVPR 2019) and ``magsac++`` (MAGSAC++, CVPR 2020).

Conventions (pymagsac 0.2.3, checked on synthetic scenes):
``findFundamentalMatrix(correspondences, w1, h1, w2, h2, probabilities, sampler=4,
use_magsac_plus_plus=True, sigma_th=1.0, conf=0.99, min_iters=50, max_iters=1000, partition_num=5)``
takes the matches as one (N, 4) float64 array [x1 y1 x2 y2] plus both image sizes (width first);
returns (F, mask) with x2^T F x1 = 0 (no transpose needed), F None when no model was found.
- ``sigma_th`` is MAGSAC's *maximum* noise scale sigma_max, in px; the returned mask marks matches
  with Sampson distance <= sigma_th. We pass the protocol's threshold eta as sigma_th, as the IMC
  benchmark does, so eta means "Sampson distance bound" for every Sampson-based backend.
- samplers: 0 uniform, 1 PROSAC (needs matches sorted by quality), 2 P-NAPSAC (uses the image
  sizes), 3 NG-RANSAC / importance and 4 AR-sampler (both need per-match ``probabilities``). The
  library default is 4; we use 0 (uniform) because tentative matches come unordered and without
  probabilities. Subclass and set ``sampler`` to change that.
- ``min_iters`` defaults to 50; we pass min(50, max_iters) so the cap Gamma is always honoured.
- no seed is exposed: runs are not reproducible (``seedable = False``).
"""
from __future__ import annotations

import numpy as np

from pipeline.geometry.base import Estimator, RawSolution, Sizes, packed_correspondences, require, timed
from pipeline.geometry.registry import ESTIMATORS


class _PyMagsac(Estimator):
    package = "pymagsac"
    seedable = False
    seed_used = False
    use_magsac_plus_plus: bool = True
    sampler: int = 0
    min_iters: int = 50
    partition_num: int = 5

    @classmethod
    def check_available(cls) -> None:
        require("pymagsac", cls.package)

    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        import pymagsac
        corr, probs = packed_correspondences(pts1, pts2)
        (w1, h1), (w2, h2) = sizes
        max_iters = max(int(max_iters), 1)
        with timed() as t:
            F, mask = pymagsac.findFundamentalMatrix(
                corr, float(w1), float(h1), float(w2), float(h2), probs, sampler=self.sampler,
                use_magsac_plus_plus=self.use_magsac_plus_plus, sigma_th=threshold, conf=confidence,
                min_iters=min(self.min_iters, max_iters), max_iters=max_iters,
                partition_num=self.partition_num)
        return RawSolution(F, mask, t.seconds)


@ESTIMATORS.register("magsac")
class Magsac(_PyMagsac):
    """MAGSAC (pymagsac): sigma-consensus, threshold eta = maximum noise scale sigma_max."""
    name = "magsac"
    use_magsac_plus_plus = False


@ESTIMATORS.register("magsac++")
class MagsacPlusPlus(_PyMagsac):
    """MAGSAC++ (pymagsac): IRLS sigma-consensus++, threshold eta = maximum noise scale sigma_max."""
    name = "magsac++"
    use_magsac_plus_plus = True
