"""COLMAP's own SIFT through pycolmap (``pycolmap.FeatureExtractor``, CPU): the features an SfM entrant gets out of
the box, inside imtune's pipeline (its matcher, estimators, tasks).

What differs from OpenCV's SIFT (``sift``) at the same budget, each of which COLMAP chose for SfM:

- the budget: ``num_features`` is COLMAP's ``max_num_features``, a cap on detected *locations*; when there are more,
  COLMAP drops the finest scales first (OpenCV's ``sift`` keeps the strongest responses, many of them fine-scale
  blobs that do not repeat across wide baselines);
- up to two orientations per location (``max_num_orientations`` 2): a location with two dominant gradients gives two
  descriptors, so an image has more descriptors than ``num_features`` (about 1.4 x on the IMC datasets);
- descriptors are RootSIFT (``normalization`` L1_ROOT); here returned as float32, L2-unit, so that Euclidean
  distances are those of ``rootsift``;
- detection from octave -1 (the image doubled), peak threshold 0.02 / 3, edge threshold 10: COLMAP's defaults,
  read from pycolmap's own option object (never copied here).

Keypoints: COLMAP's pixel-corner convention ((0.5, 0.5) is the centre of the top-left pixel) moved to imtune's
pixel-centre convention (-0.5 px). Scales are COLMAP's (the affine shape's scale, px), orientations in degrees.
Options (``--feature-option KEY=VALUE``): ``max_num_orientations``, ``first_octave``, ``peak_threshold``,
``edge_threshold``; None keeps pycolmap's default.
"""
from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from pipeline.features._opencv import as_gray_u8, parse_options
from pipeline.features.base import Extractor, Features
from pipeline.features.registry import EXTRACTORS

COLMAP_SIFT_OPTIONS: dict[str, Any] = {"max_num_orientations": None, "first_octave": None, "peak_threshold": None,
                                       "edge_threshold": None}
PIXEL_OFFSET = 0.5  # COLMAP's pixel-corner convention -> imtune's pixel-centre one


def _pycolmap_version() -> str:
    """The installed pycolmap's version, read without importing it (its import is slow and takes SIGTERM over)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("pycolmap")
    except PackageNotFoundError:
        return "missing"


@functools.lru_cache(maxsize=8)
def _extractor(num_features: int, options: tuple):
    """A pycolmap CPU SIFT extractor (one thread: imtune parallelises over images and pairs), kept per process."""
    from pipeline.colmap_db import import_pycolmap, quiet
    pycolmap = import_pycolmap()
    quiet(2)
    o = pycolmap.FeatureExtractionOptions()
    o.num_threads = 1
    o.use_gpu = False
    o.sift.max_num_features = int(num_features)
    for k, v in options:
        if v is not None:
            setattr(o.sift, k, type(getattr(o.sift, k))(v))
    return pycolmap.FeatureExtractor.create(o, pycolmap.Device.cpu)


@EXTRACTORS.register("colmap-sift", "COLMAP's SIFT (pycolmap, CPU): its defaults, finest scales dropped first, "
                     "RootSIFT; 128-D float32")
class ColmapSIFT(Extractor):
    """COLMAP's SIFT (module docstring)."""
    version = f"1+pycolmap-{_pycolmap_version()}"
    binary = False

    @classmethod
    def check_available(cls) -> None:
        from pipeline.geometry.base import require
        require("pycolmap", "pycolmap")

    def __init__(self, conf):
        super().__init__(conf)
        self.opts = parse_options(conf.name, conf.options, COLMAP_SIFT_OPTIONS)
        from pipeline.errors import ImtuneError
        for k in ("max_num_orientations",):
            v = self.opts[k]
            if v is not None and (v != int(v) or v < 1):
                raise ImtuneError(f"feature {conf.name!r}: option {k}={v!r} must be an integer >= 1")
        for k in ("peak_threshold", "edge_threshold"):
            v = self.opts[k]
            if v is not None and not v > 0:
                raise ImtuneError(f"feature {conf.name!r}: option {k}={v!r} must be > 0")
        if conf.upright or conf.clahe != "none" or conf.mr_size is not None:
            raise ImtuneError(f"feature {conf.name!r} takes none of upright, clahe, mr_size (COLMAP's SIFT as it is)")

    def extract(self, image: np.ndarray) -> Features:
        image = as_gray_u8(image, self.conf.name)
        opts = tuple(sorted(self.opts.items()))
        kps, desc = _extractor(int(self.conf.num_features), opts).extract_from_uint8_array(image)
        n = len(kps)
        if n == 0:
            return Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), np.zeros(0, np.float32),
                            np.zeros(0, np.float32), None, False)
        xy = np.array([(k.x, k.y) for k in kps], np.float64) - PIXEL_OFFSET
        scale = np.array([k.compute_scale() for k in kps], np.float32)
        ori = np.array([math.degrees(k.compute_orientation()) for k in kps], np.float32) % np.float32(360.0)
        d = np.array(desc.to_float().data, np.float32).reshape(n, -1)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), np.float32(1e-12))
        return Features(xy.astype(np.float32), d, scale, ori, None, False)
