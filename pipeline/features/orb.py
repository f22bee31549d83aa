"""ORB (Rublee et al. 2011), OpenCV ``ORB_create``; 256-bit descriptors (32 bytes, uint8, Hamming).

ORB spreads its ``nfeatures`` over the pyramid levels itself, ranking FAST corners by Harris score, so
the budget is passed to OpenCV as ``nfeatures``. ``low_threshold`` sets fastThreshold to 0 (default
20, grey levels) so that enough FAST candidates exist on every level to fill the budget.
"""
from __future__ import annotations

from typing import Any

from pipeline.features._opencv import OPENCV_VERSION, OpenCVExtractor, cv_factory
from pipeline.features.registry import EXTRACTORS

ORB_LOW_FAST, ORB_DEFAULT_FAST = 0, 20

ORB_OPTIONS: dict[str, Any] = {
    "fast_threshold": None,    # grey levels; None: 0 with low_threshold, else 20
    "scale_factor": 1.2,       # pyramid decimation ratio between levels
    "n_levels": 8,             # pyramid levels
    "edge_threshold": 31,      # border (px) where no feature is detected
    "patch_size": 31,          # BRIEF patch side (px) at level 0
}
ORB_BOUNDS = {"fast_threshold": ">=0", "scale_factor": ">1", "n_levels": ">=1", "edge_threshold": ">=0",
              "patch_size": ">=2"}


def make_orb_detector(opts: dict[str, Any], low_threshold: bool, nfeatures: int):
    ft = opts["fast_threshold"]
    if ft is None:
        ft = ORB_LOW_FAST if low_threshold else ORB_DEFAULT_FAST
    return cv_factory("ORB_create")(nfeatures=int(nfeatures), scaleFactor=float(opts["scale_factor"]),
                                    nlevels=int(opts["n_levels"]), edgeThreshold=int(opts["edge_threshold"]),
                                    patchSize=int(opts["patch_size"]), fastThreshold=int(ft))


@EXTRACTORS.register("orb", "ORB, OpenCV; 256-bit binary")
class ORB(OpenCVExtractor):
    """ORB, OpenCV; 256-bit binary (32 bytes)."""
    # 2: descriptor rows realigned with their keypoints (ORB's compute() groups the keypoints by pyramid level);
    # version 1 cache entries hold misaligned rows and are never read again
    version = f"2+opencv-{OPENCV_VERSION}"
    factories = ("ORB_create",)
    option_defaults = ORB_OPTIONS
    option_bounds = ORB_BOUNDS
    binary = True

    def _make_detector(self):
        return make_orb_detector(self.opts, self.conf.low_threshold, self.conf.num_features)
