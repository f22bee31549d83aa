"""BEBLID (Suarez et al. 2020) and TEBLID (Suarez et al. 2021): boosted binary descriptors from
contrib (``cv2.xfeatures2d``), on ORB keypoints by default as OpenCV's documentation recommends.

OpenCV's ``scale_factor`` adapts the sampling window to the detector's keypoint size convention; its
documented values: 1.00 for ORB keypoints, 6.75 for SIFT keypoints (option ``detector="sift"``),
6.25 for KAZE/SURF, 5.00 for AKAZE/BRISK/FAST. Option ``descriptor_scale`` overrides it.
Detector options are those of the chosen detector (``orb``: fast_threshold, ...; ``sift``:
contrast_threshold, ...), with the same ``low_threshold`` behaviour.
"""
from __future__ import annotations

from pipeline.errors import ImtuneError
from pipeline.features._opencv import OPENCV_VERSION, OpenCVExtractor, cv_const, cv_factory
from pipeline.features.orb import ORB_BOUNDS, ORB_OPTIONS, make_orb_detector, orb_pixel_centre
from pipeline.features.registry import EXTRACTORS
from pipeline.features.sift import SIFT_BOUNDS, SIFT_OPTIONS, make_sift_detector, sift_pixel_centre

#: OpenCV's documented BEBLID/TEBLID scale_factor per keypoint detector.
DESCRIPTOR_SCALE = {"orb": 1.00, "sift": 6.75}
_DETECTORS = {"orb": (ORB_OPTIONS, ORB_BOUNDS), "sift": (SIFT_OPTIONS, SIFT_BOUNDS)}  # name -> its options


class _Boosted(OpenCVExtractor):
    # 2: with detector=sift, keypoints moved by -0.25 px to the pixel-centre convention (sift_pixel_centre)
    # 3: with detector=orb, keypoints at the pixel-centre position of their pyramid-level pixel (orb_pixel_centre)
    version = f"3+opencv-{OPENCV_VERSION}"
    factory = ""
    default_bits = 512
    binary = True
    _bits_const: dict[int, tuple[str, int]] = {}

    def __init__(self, conf):
        det = dict(conf.options or ()).get("detector", "orb")
        if det not in _DETECTORS:
            raise ImtuneError(f"feature {conf.name!r}: detector must be one of {', '.join(_DETECTORS)}, got {det!r}")
        # Options depend on the detector: set them per instance before the base class parses them.
        self.option_defaults = {"detector": "orb", "descriptor_scale": None, "n_bits": self.default_bits,
                                **_DETECTORS[det][0]}
        self.option_bounds = {"descriptor_scale": ">0", **_DETECTORS[det][1]}
        super().__init__(conf)

    def _output_positions(self, xy, octave, shape):
        if self.opts["detector"] == "sift":
            return sift_pixel_centre(xy)
        return orb_pixel_centre(xy, octave, shape, float(self.opts["scale_factor"]))

    def _make_detector(self):
        if self.opts["detector"] == "sift":
            return make_sift_detector(self.opts, self.conf.low_threshold)
        return make_orb_detector(self.opts, self.conf.low_threshold, self.conf.num_features)

    def _make_descriptor(self):
        scale = self.opts["descriptor_scale"]
        if scale is None:
            scale = DESCRIPTOR_SCALE[self.opts["detector"]]
        bits = int(self.opts["n_bits"])
        if bits not in self._bits_const:
            raise ImtuneError(f"feature {self.conf.name!r}: n_bits must be 256 or 512, got {bits}")
        return cv_factory(self.factory)(float(scale), cv_const(*self._bits_const[bits]))


@EXTRACTORS.register("beblid", "BEBLID on ORB keypoints, OpenCV contrib; 512-bit binary")
class BEBLID(_Boosted):
    """BEBLID on ORB keypoints, OpenCV contrib; 512-bit binary (64 bytes; n_bits=256 for 32)."""
    factories = ("ORB_create", "SIFT_create", "BEBLID_create")
    factory = "BEBLID_create"
    default_bits = 512
    _bits_const = {512: ("BEBLID_SIZE_512_BITS", 100), 256: ("BEBLID_SIZE_256_BITS", 101)}


@EXTRACTORS.register("teblid", "TEBLID on ORB keypoints, OpenCV contrib; 256-bit binary")
class TEBLID(_Boosted):
    """TEBLID on ORB keypoints, OpenCV contrib; 256-bit binary (32 bytes; n_bits=512 for 64)."""
    factories = ("ORB_create", "SIFT_create", "TEBLID_create")
    factory = "TEBLID_create"
    default_bits = 256
    _bits_const = {256: ("TEBLID_SIZE_256_BITS", 102), 512: ("TEBLID_SIZE_512_BITS", 103)}
