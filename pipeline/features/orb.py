"""ORB (Rublee et al. 2011), OpenCV ``ORB_create``; 256-bit descriptors (32 bytes, uint8, Hamming).

ORB spreads its ``nfeatures`` over the pyramid levels itself, ranking FAST corners by Harris score, so
the budget is passed to OpenCV as ``nfeatures``. ``low_threshold`` sets fastThreshold to 0 (default
20, grey levels) so that enough FAST candidates exist on every level to fill the budget.
"""
from __future__ import annotations

from typing import Any

import numpy as np

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


def orb_pixel_centre(xy: np.ndarray, level: np.ndarray, shape: tuple[int, int], scale_factor: float) -> np.ndarray:
    """OpenCV ORB keypoint positions (N, 2) -> the pixel-centre convention of the image of ``shape`` (H, W).

    ORB detects FAST corners at integer pixels u of pyramid level l (KeyPoint.octave), the image resized by a
    pixel-centre resize to (round(W / s), round(H / s)) with s = scale_factor^l (float32, as OpenCV's
    getScale), and reports u * s; the pixel-centre position of u is (u + 0.5) * W / round(W / s) - 0.5 (the
    level-to-level resizes compose exactly). Uncorrected: about -(s - 1) / 2 px plus the rounding of the level
    size, up to -1.3 px at level 7."""
    xy = np.asarray(xy, np.float64)
    h, w = shape
    s = np.power(np.float32(scale_factor), np.asarray(level, np.float32)).astype(np.float64)
    s = np.asarray(s, np.float32).astype(np.float64)
    u = np.round(xy / s[:, None])  # the level pixel
    wl = np.maximum(np.round(w / s), 1.0)
    hl = np.maximum(np.round(h / s), 1.0)
    return np.stack([(u[:, 0] + 0.5) * (w / wl) - 0.5, (u[:, 1] + 0.5) * (h / hl) - 0.5], 1).astype(np.float32)


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
    # 3: keypoints at the pixel-centre position of their pyramid-level pixel (orb_pixel_centre), not at u * s
    version = f"3+opencv-{OPENCV_VERSION}"
    factories = ("ORB_create",)
    option_defaults = ORB_OPTIONS
    option_bounds = ORB_BOUNDS
    binary = True

    def _output_positions(self, xy, octave, shape):
        return orb_pixel_centre(xy, octave, shape, float(self.opts["scale_factor"]))

    def _make_detector(self):
        return make_orb_detector(self.opts, self.conf.low_threshold, self.conf.num_features)
