"""SURF (Bay et al. 2006). Patented, so OpenCV builds it only with OPENCV_ENABLE_NONFREE, which no
pip wheel sets: ``cv2.xfeatures2d.SURF_create`` exists in opencv-contrib-python-headless but raises.
``check_available`` probes it once; on a non-free build SURF works like the other extractors.
"""
from __future__ import annotations

import functools
from typing import Any, ClassVar

import cv2

from pipeline.errors import UnavailableError
from pipeline.features._opencv import OpenCVExtractor, cv_factory
from pipeline.features.registry import EXTRACTORS

SURF_UNAVAILABLE = ("surf is non-free and not in any pip OpenCV build (opencv-contrib-python-headless); "
                    "build OpenCV with OPENCV_ENABLE_NONFREE to use it")
SURF_LOW_HESSIAN, SURF_DEFAULT_HESSIAN = 1.0, 100.0


@functools.cache
def _surf_works() -> bool:
    try:
        cv_factory("SURF_create")()
    except (UnavailableError, cv2.error):
        return False
    return True


@EXTRACTORS.register("surf", "SURF, OpenCV non-free; 64-D float32 (128-D with extended)")
class SURF(OpenCVExtractor):
    """SURF, OpenCV non-free; 64-D float32 (128-D with option extended=True)."""
    factories = ("SURF_create",)
    option_defaults: ClassVar[dict[str, Any]] = {
        "hessian_threshold": None,   # None: 1.0 with low_threshold, else 100
        "n_octaves": 4, "n_octave_layers": 3, "extended": False}
    option_bounds = {"hessian_threshold": ">=0", "n_octaves": ">=1", "n_octave_layers": ">=1"}
    binary = False

    @classmethod
    def check_available(cls) -> None:
        if not _surf_works():
            raise UnavailableError(SURF_UNAVAILABLE)

    def _make_detector(self):
        o = self.opts
        h = o["hessian_threshold"]
        h = h if h is not None else (SURF_LOW_HESSIAN if self.conf.low_threshold else SURF_DEFAULT_HESSIAN)
        return cv_factory("SURF_create")(hessianThreshold=float(h), nOctaves=int(o["n_octaves"]),
                                         nOctaveLayers=int(o["n_octave_layers"]), extended=bool(o["extended"]),
                                         upright=self.upright)
