"""SIFT and RootSIFT (OpenCV ``SIFT_create``; in the main cv2 module since OpenCV 4.4).

Descriptors: 128-D float32. ``low_threshold`` sets contrastThreshold to 1e-5 (OpenCV default 0.04,
a contrast on the [0, 1] intensity scale divided by the number of octave layers) so that a 1024 px
image yields well over 8000 candidates; edgeThreshold stays at its default 10. The budget is then
the strongest ``num_features`` by response (DoG contrast).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.features._opencv import OPENCV_VERSION, OpenCVExtractor, cv_factory
from pipeline.features.registry import EXTRACTORS

#: OpenCV's SIFT_DESCR_SCL_FCTR: a descriptor bin spans 3 x the keypoint's sigma (Lowe's and
#: VLFeat's magnification factor, "mrSize"); the 4x4-bin support is therefore 12 sigma wide.
SIFT_DEFAULT_MR_SIZE = 3.0
#: contrastThreshold with ``low_threshold`` and without (OpenCV's default).
SIFT_LOW_CONTRAST, SIFT_DEFAULT_CONTRAST = 1e-5, 0.04

SIFT_OPTIONS: dict[str, Any] = {
    "contrast_threshold": None,   # None: 1e-5 with low_threshold, else 0.04
    "edge_threshold": 10.0,       # ratio of principal curvatures (larger keeps more edge-like points)
    "n_octave_layers": 3,
    "sigma": 1.6,                 # Gaussian sigma at octave 0 (px)
}
#: OpenCV's SIFT detects from octave -1, the image doubled by a pixel-centre resize (x -> 2 x + 0.5), and halves
#: the positions found there (2 x + 0.5 -> x + 0.25) without undoing the half pixel: its keypoints lie 0.25 px
#: right of and below the point they stand for, at every octave (measured: +0.250 px in x and y under a
#: 180-degree rotation). Subtracted from what we report (the descriptor is OpenCV's, at its own position).
#: OpenCV's own ``enable_precise_upscale=True`` avoids the offset but builds another pyramid, hence other keypoints
#: and descriptors than the default OpenCV SIFT the IMC benchmark used; the default is kept, its positions corrected.
SIFT_DOUBLING_OFFSET = 0.25


def sift_pixel_centre(xy: np.ndarray) -> np.ndarray:
    """OpenCV SIFT keypoint positions (N, 2) -> the pixel-centre convention (centre of the top-left pixel (0, 0))."""
    return (np.asarray(xy, np.float32) - np.float32(SIFT_DOUBLING_OFFSET)).astype(np.float32)


SIFT_BOUNDS = {"contrast_threshold": ">=0", "edge_threshold": ">0", "n_octave_layers": ">=1", "sigma": ">0"}


def make_sift_detector(opts: dict[str, Any], low_threshold: bool):
    """An OpenCV SIFT object with every detection kept (nfeatures=0: the budget is applied after)."""
    ct = opts["contrast_threshold"]
    if ct is None:
        ct = SIFT_LOW_CONTRAST if low_threshold else SIFT_DEFAULT_CONTRAST
    return cv_factory("SIFT_create")(0, int(opts["n_octave_layers"]), float(ct),
                                     float(opts["edge_threshold"]), float(opts["sigma"]))


@EXTRACTORS.register("sift", "SIFT (Lowe 2004), OpenCV; 128-D float32")
class SIFT(OpenCVExtractor):
    """SIFT (Lowe 2004), OpenCV; 128-D float32.

    ``mr_size``: descriptor support as a multiple of the keypoint sigma (library default 3.0). It
    is applied by scaling each keypoint's size by ``mr_size / 3`` before description; the reported
    scales are the detector's.
    """
    # 2: keypoints moved by -0.25 px in x and y to the pixel-centre convention (sift_pixel_centre)
    version = f"2+opencv-{OPENCV_VERSION}"
    factories = ("SIFT_create",)
    option_defaults = SIFT_OPTIONS
    option_bounds = SIFT_BOUNDS
    supports_mr_size = True
    binary = False

    def _make_detector(self):
        return make_sift_detector(self.opts, self.conf.low_threshold)

    def _output_positions(self, xy: np.ndarray, octave: np.ndarray, shape) -> np.ndarray:
        return sift_pixel_centre(xy)

    def _description_sizes(self, size: np.ndarray) -> np.ndarray:
        if self.conf.mr_size is None:
            return size
        return size * np.float32(self.conf.mr_size / SIFT_DEFAULT_MR_SIZE)


def root_sift(desc: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """RootSIFT (Arandjelovic & Zisserman, CVPR 2012): L1-normalise, then element-wise sqrt. The
    result is L2-unit, so Euclidean distance on it is the Hellinger kernel on the SIFT histograms.
    Hand-written: OpenCV has no RootSIFT."""
    d = np.abs(desc.astype(np.float32, copy=False))
    d = d / np.maximum(d.sum(axis=1, keepdims=True), np.float32(eps))
    return np.sqrt(d, dtype=np.float32)


@EXTRACTORS.register("rootsift", "RootSIFT: SIFT, L1-normalised and square-rooted; 128-D float32")
class RootSIFT(SIFT):
    """RootSIFT: SIFT, L1-normalised and square-rooted; 128-D float32 (L2-unit)."""

    def _postprocess(self, desc: np.ndarray) -> np.ndarray:
        return root_sift(desc)
