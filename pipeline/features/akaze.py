"""AKAZE and KAZE (Alcantarilla et al. 2012, 2013). OpenCV 5 moved both to contrib
(``cv2.xfeatures2d``); ``cv_factory`` finds them in either place.

``low_threshold`` sets the detector response threshold to 1e-5 (OpenCV default 1e-3, Hessian
response of the nonlinear scale space on [0, 1] intensities), then the strongest ``num_features``
by response are kept.
"""
from __future__ import annotations

from typing import Any

from pipeline.features._opencv import OpenCVExtractor, cv_const, cv_factory
from pipeline.features.registry import EXTRACTORS

KAZE_LOW_THRESHOLD, KAZE_DEFAULT_THRESHOLD = 1e-5, 1e-3

_SCALE_SPACE_OPTIONS: dict[str, Any] = {
    "threshold": None,         # detector response threshold; None: 1e-5 with low_threshold, else 1e-3
    "n_octaves": 4,
    "n_octave_layers": 4,
    "diffusivity": 1,          # 0 PM_G1, 1 PM_G2, 2 WEICKERT, 3 CHARBONNIER
}
_SCALE_SPACE_BOUNDS = {"threshold": ">=0", "n_octaves": ">=1", "n_octave_layers": ">=1", "diffusivity": "0..3"}


def _threshold(opts: dict[str, Any], low: bool) -> float:
    t = opts["threshold"]
    return float(t if t is not None else (KAZE_LOW_THRESHOLD if low else KAZE_DEFAULT_THRESHOLD))


@EXTRACTORS.register("akaze", "AKAZE, OpenCV; 486-bit binary M-LDB")
class AKAZE(OpenCVExtractor):
    """AKAZE, OpenCV; 486-bit binary M-LDB (61 bytes). ``upright`` uses OpenCV's MLDB_UPRIGHT."""
    factories = ("AKAZE_create",)
    option_defaults = _SCALE_SPACE_OPTIONS
    option_bounds = _SCALE_SPACE_BOUNDS
    binary = True
    uses_class_id = True   # AKAZE keeps the keypoint's scale-space level in KeyPoint.class_id

    def _make_detector(self):
        dtype = (cv_const("AKAZE_DESCRIPTOR_MLDB_UPRIGHT", 4) if self.upright
                 else cv_const("AKAZE_DESCRIPTOR_MLDB", 5))
        o = self.opts
        return cv_factory("AKAZE_create")(descriptor_type=dtype, threshold=_threshold(o, self.conf.low_threshold),
                                          nOctaves=int(o["n_octaves"]), nOctaveLayers=int(o["n_octave_layers"]),
                                          diffusivity=int(o["diffusivity"]))


@EXTRACTORS.register("kaze", "KAZE, OpenCV; 64-D float32 (128-D with extended)")
class KAZE(OpenCVExtractor):
    """KAZE, OpenCV; 64-D float32 (128-D with option extended=True). KAZE assigns orientations at
    description time; ``upright`` uses OpenCV's upright KAZE descriptor."""
    factories = ("KAZE_create",)
    option_defaults = {**_SCALE_SPACE_OPTIONS, "extended": False}
    option_bounds = _SCALE_SPACE_BOUNDS
    binary = False
    uses_class_id = True   # KAZE keeps the keypoint's scale-space level in KeyPoint.class_id

    def _make_detector(self):
        o = self.opts
        return cv_factory("KAZE_create")(extended=bool(o["extended"]), upright=self.upright,
                                         threshold=_threshold(o, self.conf.low_threshold),
                                         nOctaves=int(o["n_octaves"]), nOctaveLayers=int(o["n_octave_layers"]),
                                         diffusivity=int(o["diffusivity"]))
