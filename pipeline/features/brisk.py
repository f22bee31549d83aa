"""BRISK (Leutenegger et al. 2011) and FREAK (Alahi et al. 2012) on BRISK keypoints. OpenCV 5 moved
BRISK to contrib (``cv2.xfeatures2d``); FREAK has always been there.

``low_threshold`` sets the AGAST threshold to 10 grey levels (OpenCV default 30), then the strongest
``num_features`` by response are kept.
"""
from __future__ import annotations

from typing import Any

from pipeline.features._opencv import OpenCVExtractor, cv_factory
from pipeline.features.registry import EXTRACTORS

BRISK_LOW_THRESH, BRISK_DEFAULT_THRESH = 10, 30

_DETECTOR_OPTIONS: dict[str, Any] = {
    "thresh": None,            # AGAST threshold (grey levels); None: 10 with low_threshold, else 30
    "octaves": 3,              # detection octaves (0: single scale)
}
_DETECTOR_BOUNDS = {"thresh": "0..255", "octaves": "0..8"}


def make_brisk(opts: dict[str, Any], low_threshold: bool, pattern_scale: float = 1.0):
    t = opts["thresh"]
    t = t if t is not None else (BRISK_LOW_THRESH if low_threshold else BRISK_DEFAULT_THRESH)
    return cv_factory("BRISK_create")(thresh=int(t), octaves=int(opts["octaves"]), patternScale=float(pattern_scale))


@EXTRACTORS.register("brisk", "BRISK, OpenCV; 512-bit binary")
class BRISK(OpenCVExtractor):
    """BRISK, OpenCV; 512-bit binary (64 bytes). No upright mode (see ``upright_note``)."""
    factories = ("BRISK_create",)
    option_defaults = {**_DETECTOR_OPTIONS, "pattern_scale": 1.0}
    option_bounds = {**_DETECTOR_BOUNDS, "pattern_scale": ">0"}
    binary = True
    supports_upright = False
    upright_note = ("OpenCV's BRISK always estimates its own orientation at description time; "
                    "use freak (upright FREAK on BRISK keypoints) instead")

    def _make_detector(self):
        return make_brisk(self.opts, self.conf.low_threshold, self.opts["pattern_scale"])


@EXTRACTORS.register("freak", "FREAK descriptors on BRISK keypoints, OpenCV; 512-bit binary")
class FREAK(OpenCVExtractor):
    """FREAK descriptors on BRISK keypoints, OpenCV; 512-bit binary (64 bytes). FREAK estimates its
    own orientation unless ``upright`` (orientationNormalized off); it drops keypoints whose pattern
    leaves the image, so fewer than the budget may come back."""
    factories = ("BRISK_create", "FREAK_create")
    option_defaults = {**_DETECTOR_OPTIONS,
                       "pattern_scale": 22.0,       # FREAK pattern scale
                       "scale_normalized": True,
                       "freak_octaves": 4}          # octaves covered by the keypoints
    option_bounds = {**_DETECTOR_BOUNDS, "pattern_scale": ">0", "freak_octaves": ">=1"}
    binary = True

    def _make_detector(self):
        return make_brisk(self.opts, self.conf.low_threshold)

    def _make_descriptor(self):
        o = self.opts
        return cv_factory("FREAK_create")(orientationNormalized=not self.upright,
                                          scaleNormalized=bool(o["scale_normalized"]),
                                          patternScale=float(o["pattern_scale"]), nOctaves=int(o["freak_octaves"]))
