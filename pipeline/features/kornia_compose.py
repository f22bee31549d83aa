"""Composed features: detector [+ affine shape] [+ orientation] + patch descriptor, by name.

    from pipeline.features import extract
    feats = extract(FeatureConfig(name="keynet+affnet+mkd", num_features=2048), gray_uint8_image)

Name grammar: ``<detector>[+<affine>][+<orientation>]+<descriptor>`` with

- detectors (``kornia_detectors``): dog, hessian, hessian-laplace, harris-laplace, keynet;
- affine (``kornia_shape``): affnet, baumberg (alias affine);
- orientation (``kornia_shape``): gradori (alias ori), orinet, upright; default: the detector's own for
  DoG without an affine step (OpenCV SIFT orientations), OriNet for Key.Net (as kornia's KeyNet presets),
  the dominant gradient (gradori) otherwise;
- descriptors (``kornia_descriptors``): sift, rootsift, tfeat, mkd, hardnet, hardnet8, sosnet, hynet.

The paper's rows are registered by name (``ROWS``), e.g. ``dog-affnet-hardnet`` = ``dog+affnet+hardnet``,
``dog-affine-sift`` = ``dog+baumberg+sift`` (VLFeat's DoG-Affine), ``hessian-affnet-sift``. Any other
combination resolves from the command line (``--feature keynet+affnet+mkd``) through
``pipeline.features.resolve_feature`` (the feature registry consults it for unregistered names).

FeatureConfig fields: ``num_features`` (the budget: the strongest detections), ``low_threshold``
(the detectors' lowered thresholds), ``upright`` / ``upright_plus`` (no orientation; duplicates of
DoG's multi-orientation keypoints removed, after / before the budget cut), ``clahe``, ``mr_size`` (see
``kornia_descriptors``). ``options``: see :func:`option_defaults` (``tune list`` / error messages list them).

Outputs: keypoints (x, y) px at the working resolution; scales = 2 sigma (OpenCV ``KeyPoint.size``
convention); orientations in OpenCV's convention (degrees); scores = detector response; descriptors
(N, 128) float32.
"""
from __future__ import annotations

import functools
from typing import Any, ClassVar

import cv2
import numpy as np

from pipeline.errors import ImtuneError
from pipeline.features.base import Extractor, Features
from pipeline.features.kornia_base import COMMON_BOUNDS, COMMON_OPTIONS, package_version, require_weights
from pipeline.features.kornia_descriptors import DESCRIPTORS, PatchDescriptor, descriptor_class
from pipeline.features.kornia_detectors import DETECTORS, Detector, detector_class
from pipeline.features.kornia_shape import AFFINE, ORIENTATION, ShapeStep, canonical, step_class
from pipeline.features.registry import EXTRACTORS

# 2: the dog detector reports OpenCV SIFT positions moved by -0.25 px to the pixel-centre convention
VERSION = f"2+kornia-{package_version('kornia')}+torch-{package_version('torch')}+opencv-{cv2.__version__}"


class ComposedExtractor(Extractor):
    """Detector -> (affine) -> (orientation) -> patch descriptor. Subclasses are made by
    :func:`composed_class`; they set the four component classes."""
    version: ClassVar[str] = VERSION
    binary: ClassVar[bool] = False
    learned: ClassVar[bool] = True  # search-space family "learned" (tuner.space.feature_families)
    canonical_name: ClassVar[str] = ""
    detector_cls: ClassVar[type[Detector]]
    affine_cls: ClassVar[type[ShapeStep] | None] = None
    orientation_cls: ClassVar[type[ShapeStep] | None] = None  # None: the detector's own orientations
    descriptor_cls: ClassVar[type[PatchDescriptor]]

    @classmethod
    def components(cls) -> list:
        return [c for c in (cls.detector_cls, cls.affine_cls, cls.orientation_cls, cls.descriptor_cls) if c]

    @classmethod
    def check_available(cls) -> None:
        require_weights(cls.canonical_name, [w for c in cls.components() for w in c.weights])

    @classmethod
    def option_defaults(cls) -> dict[str, Any]:
        out = dict(COMMON_OPTIONS)
        for c in cls.components():
            out.update(c.option_defaults)
        return out

    def __init__(self, conf):
        from pipeline.features._opencv import check_bounds, parse_options
        super().__init__(conf)
        name = conf.name
        self.opts = parse_options(name, conf.options, self.option_defaults())
        bounds = dict(COMMON_BOUNDS)
        for c in self.components():
            bounds.update(c.option_bounds)
        check_bounds(name, self.opts, bounds)
        if conf.mr_size is not None and not conf.mr_size > 0:
            raise ImtuneError(f"feature {name!r}: mr_size must be > 0, got {conf.mr_size}")
        self.upright = bool(conf.upright or conf.upright_plus) or self.orientation_cls is ORIENTATION["upright"]
        self.detector = self.detector_cls(self.opts, conf.low_threshold, name)
        self.affine = self.affine_cls(self.opts) if self.affine_cls else None
        self.orienter = None if (self.upright or self.orientation_cls is None) else self.orientation_cls(self.opts)
        self.descriptor = self.descriptor_cls(self.opts)
        # the detector's own orientations survive only without any re-estimation
        self.keep_angles = (not self.upright and self.orienter is None and self.affine is None
                            and self.detector_cls.gives_orientation)

    def _empty(self) -> Features:
        z = np.zeros(0, np.float32)
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, self.descriptor_cls.dim), np.float32),
                        z, z.copy(), z.copy())

    def extract(self, image: np.ndarray) -> Features:
        """Detect, shape, orient and describe. ``image``: (H, W) uint8 at the working resolution."""
        from pipeline.features._opencv import as_gray_u8
        from pipeline.features.kornia_base import clahe_images, runtime_failure, torch_setup
        conf = self.conf
        img = as_gray_u8(image, conf.name)
        det_img, desc_img = clahe_images(img, conf.clahe, self.opts)
        torch = torch_setup(int(self.opts["threads"]))
        try:
            return self._extract(det_img, desc_img, torch)
        except (RuntimeError, ValueError) as e:
            if runtime_failure(conf.name, img, e):
                return self._empty()
            raise

    def _extract(self, det_img: np.ndarray, desc_img: np.ndarray, torch) -> Features:
        from pipeline.features.kornia_base import (
            check_finite,
            describe_patches,
            kornia_to_cv_angle,
            make_lafs,
            to_tensor,
        )
        conf = self.conf
        reestimated = self.orienter is not None or self.affine is not None
        det = self.detector.detect(det_img, conf.num_features, dedupe=self.upright or reestimated,
                                   refill=bool(conf.upright_plus) or (reestimated and not self.upright))
        if len(det) == 0:
            return self._empty()
        from kornia.feature import get_laf_orientation, scale_laf
        batch = int(self.opts["batch_size"])
        fm = self.detector_cls.frame_mult
        with torch.inference_mode():
            t = to_tensor(desc_img)
            ang = -det.angle if (self.keep_angles and det.angle is not None) else np.zeros(len(det), np.float32)
            lafs = make_lafs(det.xy, det.sigma * np.float32(fm), ang)
            if self.affine is not None:
                lafs = self.affine(lafs, t, batch)
            if self.orienter is not None:
                lafs = self.orienter(lafs, t, batch)
            mr = float(conf.mr_size) if conf.mr_size is not None else self.descriptor_cls.default_mr_size
            dlafs = scale_laf(lafs, 2.0 * mr / fm)
            desc = describe_patches(self.descriptor.module(), t, dlafs, self.descriptor_cls.patch_size, batch)
            ori = (np.zeros(len(det), np.float32) if self.upright
                   else kornia_to_cv_angle(get_laf_orientation(lafs).reshape(-1).numpy()))
        desc = check_finite(conf.name, np.ascontiguousarray(desc, np.float32))
        return Features(keypoints=np.ascontiguousarray(det.xy, np.float32), descriptors=desc,
                        scales=(2.0 * det.sigma).astype(np.float32), orientations=ori,
                        scores=det.response.astype(np.float32))


@functools.cache
def composed_class(detector: str, affine: str | None, orientation: str | None, descriptor: str
                   ) -> type[ComposedExtractor]:
    """The extractor class of one combination (one class per combination; canonical component names;
    ``orientation`` None = the default for the detector, see the module docstring)."""
    det = detector_class(detector)
    aff = AFFINE[canonical(affine)] if affine else None
    if orientation is None and det.name == "keynet":
        orientation = "orinet"
    if orientation is None and not (det.gives_orientation and aff is None):
        orientation = "gradori"
    ori = ORIENTATION[canonical(orientation)] if orientation else None
    desc = descriptor_class(descriptor)
    name = "+".join(p for p in (det.name, aff.name if aff else None, ori.name if ori else None, desc.name) if p)
    doc = " + ".join(c.description for c in (det, aff, ori, desc) if c)
    return type(f"Composed[{name}]", (ComposedExtractor,), {
        "__doc__": f"{doc}; 128-D float32 (kornia)", "__module__": __name__, "canonical_name": name,
        "detector_cls": det, "affine_cls": aff, "orientation_cls": ori, "descriptor_cls": desc})


def parse_composed(name: str) -> type[ComposedExtractor]:
    """The class of a ``det[+aff][+ori]+desc`` name; one-line ImtuneError naming the bad part."""
    parts = [p.strip().lower() for p in name.split("+")]
    if len(parts) < 2 or not all(parts):
        raise ImtuneError(f"bad composed feature name {name!r}: expected <detector>[+<affine>][+<orientation>]"
                          f"+<descriptor>, e.g. keynet+affnet+mkd")
    det, *steps, desc = parts
    from pipeline.features.kornia_detectors import ALIASES
    if ALIASES.get(det, det) not in DETECTORS:
        raise ImtuneError(f"feature {name!r}: unknown detector {det!r} (detectors: {', '.join(DETECTORS)})")
    if desc not in DESCRIPTORS:
        raise ImtuneError(f"feature {name!r}: unknown descriptor {desc!r} (descriptors: {', '.join(DESCRIPTORS)})")
    aff = ori = None
    for s in steps:
        try:
            cls = step_class(s)
        except ImtuneError:
            raise ImtuneError(f"feature {name!r}: unknown step {s!r} (affine: {', '.join(AFFINE)}; "
                              f"orientation: {', '.join(ORIENTATION)})") from None
        if cls.name in AFFINE:
            if aff:
                raise ImtuneError(f"feature {name!r}: two affine steps ({aff}, {s})")
            aff = cls.name
        else:
            if ori:
                raise ImtuneError(f"feature {name!r}: two orientation steps ({ori}, {s})")
            ori = cls.name
    return composed_class(ALIASES.get(det, det), aff, ori, desc)


#: The paper's named rows (and kornia's presets) -> (detector, affine, orientation, descriptor).
ROWS: dict[str, tuple[str, str | None, str | None, str]] = {
    "dog-tfeat": ("dog", None, None, "tfeat"),
    "dog-mkd": ("dog", None, None, "mkd"),
    "dog-hardnet": ("dog", None, None, "hardnet"),
    "dog-hardnet8": ("dog", None, None, "hardnet8"),
    "dog-sosnet": ("dog", None, None, "sosnet"),
    "dog-hynet": ("dog", None, None, "hynet"),
    "dog-affnet-hardnet": ("dog", "affnet", None, "hardnet"),
    "keynet-hardnet": ("keynet", None, None, "hardnet"),
    "keynet-sosnet": ("keynet", None, None, "sosnet"),
    "keynet-affnet-hardnet": ("keynet", "affnet", None, "hardnet"),
    "dog-affine-sift": ("dog", "baumberg", None, "sift"),
    "hessian-affnet-sift": ("hessian", "affnet", None, "sift"),
}

for _row, _parts in ROWS.items():
    _cls = composed_class(*_parts)
    EXTRACTORS.register(_row, f"{_cls.__doc__} (= {_cls.canonical_name})")(_cls)
