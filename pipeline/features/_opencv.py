"""Machinery shared by the OpenCV extractors.

Every OpenCV extractor runs the same four steps:

1. detect on the detection image (CLAHE-equalised when ``clahe`` is "detector" or "both"), with the
   lowered threshold when ``low_threshold`` (so that the budget can be reached);
2. select: strongest ``num_features`` by detector response (top-k); with ``upright`` orientations
   are set to 0 and duplicate (x, y, scale) keypoints removed — after the top-k cut for ``upright``,
   before it for ``upright_plus`` (which therefore refills to the budget);
3. describe the selected keypoints on the description image (CLAHE when "descriptor" or "both");
4. return a :class:`Features` record, keypoints in the order strongest first.
"""
from __future__ import annotations

import functools
from typing import Any, ClassVar

import cv2
import numpy as np

from pipeline.errors import ImtuneError, UnavailableError
from pipeline.features.base import Extractor, Features

OPENCV_VERSION: str = cv2.__version__

# Where a factory may live. Hand-written lookup because OpenCV moves these between major versions:
# OpenCV 5 moved KAZE, AKAZE, BRISK and AGAST from the main module to contrib's xfeatures2d
# (opencv/opencv#25292), SIFT moved from xfeatures2d to the main module in 4.4, and BEBLID, TEBLID,
# FREAK and SURF have always been in xfeatures2d. Code that hard-codes one location breaks on the
# other major version.
_NAMESPACES = ("", "xfeatures2d", "features", "features2d")

#: Images with a side shorter than this (px) on which OpenCV fails (ORB/BRISK pyramids reach an
#: empty level) give empty Features instead of an error.
TINY_SIDE = 64

#: Options every OpenCV extractor accepts: CLAHE clip limit (contrast limit per tile, OpenCV units)
#: and tiles per image side (cv2.createCLAHE tileGridSize).
COMMON_OPTIONS: dict[str, Any] = {"clahe_clip": 2.0, "clahe_tiles": 8}


def _cv_modules():
    for ns in _NAMESPACES:
        mod = getattr(cv2, ns, None) if ns else cv2
        if mod is not None:
            yield ("cv2." + ns) if ns else "cv2", mod


@functools.cache
def cv_factory(name: str):
    """The OpenCV factory ``name`` (e.g. ``"AKAZE_create"``) from whichever cv2 namespace has it
    (cv2, then cv2.xfeatures2d, ...). Raises :class:`UnavailableError` if this cv2 build has none."""
    for _, mod in _cv_modules():
        f = getattr(mod, name, None)
        if callable(f):
            return f
    where = ", ".join(m for m, _ in _cv_modules())
    raise UnavailableError(f"OpenCV {OPENCV_VERSION} has no {name} (looked in {where}); "
                           "install opencv-contrib-python-headless")


def cv_const(name: str, fallback: int) -> int:
    """An OpenCV enum value (e.g. ``"AKAZE_DESCRIPTOR_MLDB"``) wherever it lives; ``fallback`` (the
    value in OpenCV's headers) if this build exposes it nowhere."""
    for _, mod in _cv_modules():
        v = getattr(mod, name, None)
        if isinstance(v, int):
            return v
    return fallback


def _coerce(name: str, key: str, value: Any, default: Any) -> Any:
    import math
    if not isinstance(default, bool) and isinstance(value, (int, float, str)) and not isinstance(value, bool):
        try:
            finite = math.isfinite(float(value))
        except (TypeError, ValueError):
            finite = True  # not a number at all: the type check below says so
        if not finite:  # gms threshold=inf filtered every match (every pair failed, unsaid); an int option crashed
            raise ImtuneError(f"feature {name!r}: option {key}={value!r} must be a finite number")
    try:
        if default is None or isinstance(default, float):
            return float(value)
        if isinstance(default, bool):
            if isinstance(value, str):
                if value.lower() in ("true", "1", "yes"):
                    return True
                if value.lower() in ("false", "0", "no"):
                    return False
                raise ValueError(value)
            return bool(value)
        if isinstance(default, int):
            if float(value) != int(float(value)):
                raise ValueError(value)
            return int(float(value))
        return type(default)(value)
    except (TypeError, ValueError):
        kind = "number" if default is None else type(default).__name__
        raise ImtuneError(f"feature {name!r}: option {key}={value!r} is not a {kind}") from None


def parse_options(name: str, options: Any, defaults: dict[str, Any]) -> dict[str, Any]:
    """Merge ``FeatureConfig.options`` ((key, value) pairs or a dict) over ``defaults``; unknown keys
    and values of the wrong type raise :class:`ImtuneError` naming the extractor."""
    try:
        given = dict(options or ())
    except (TypeError, ValueError):
        raise ImtuneError(f"feature {name!r}: options must be (key, value) pairs, got {options!r}") from None
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise ImtuneError(f"feature {name!r}: unknown option(s) {', '.join(map(str, unknown))} "
                          f"(known: {', '.join(sorted(defaults))})")
    out = dict(defaults)
    for k, v in given.items():
        out[k] = _coerce(name, k, v, defaults[k])
    return out


def check_bounds(name: str, opts: dict[str, Any], bounds: dict[str, str]) -> None:
    """Range-check option values before OpenCV sees them (some out-of-range values crash OpenCV,
    e.g. ORB with nlevels=0). ``bounds``: key -> ">0", ">=1", ">1" or "lo..hi" (inclusive)."""
    for key, spec in bounds.items():
        v = opts.get(key)
        if v is None:
            continue
        if ".." in spec:
            lo, hi = (float(x) for x in spec.split(".."))
            ok = lo <= v <= hi
        elif spec.startswith(">="):
            ok = v >= float(spec[2:])
        elif spec.startswith(">"):
            ok = v > float(spec[1:])
        else:
            raise ValueError(spec)
        if not ok:
            raise ImtuneError(f"feature {name!r}: option {key}={v!r} out of range (must be {spec})")


def as_gray_u8(image: Any, name: str) -> np.ndarray:
    """Check the extractor input: (H, W) (or (H, W, 1)) uint8. Returns a C-contiguous (H, W) view."""
    if not isinstance(image, np.ndarray):
        raise ImtuneError(f"feature {name!r}: expected a numpy image, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ImtuneError(f"feature {name!r}: expected a (H, W) uint8 grayscale image, "
                          f"got shape {image.shape} dtype {image.dtype}")
    if image.size == 0:
        raise ImtuneError(f"feature {name!r}: empty image of shape {image.shape}")
    return np.ascontiguousarray(image)


def rank_keypoints(xy: np.ndarray, size: np.ndarray, angle: np.ndarray, response: np.ndarray,
                   k: int, upright: bool = False, refill: bool = False) -> np.ndarray:
    """Indices of the candidate keypoints, strongest (largest ``response``) first. The caller keeps
    the first ``k`` that the descriptor accepts (descriptors drop keypoints near the border).

    Hand-written rather than OpenCV's ``nfeatures`` / ``KeyPointsFilter::retainBest`` because those
    keep every keypoint tied with the k-th (so more than k can come back), do not de-duplicate the
    several orientations SIFT assigns at one location, and order ties by thread scheduling; here
    ties are broken by (x, y, size, angle), so the selection is deterministic (it is a cache key).

    upright: keep only the strongest of keypoints sharing (x, y, size) exactly (their orientation
    is dropped) — applied after the top-k cut, so at most k, and possibly fewer, candidates remain;
    refill (``upright_plus``): de-duplicate all detections first, so the budget is refilled from
    weaker ones.
    """
    if len(response) == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort((angle, size, xy[:, 1], xy[:, 0], -response))
    if not upright:
        return order
    if not refill:
        order = order[:k]
    key = np.stack([xy[order, 0], xy[order, 1], size[order]], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    return order[np.sort(first)]


def _kp_arrays(kps) -> tuple[np.ndarray, ...]:
    if len(kps) == 0:
        z = np.zeros(0, np.float32)
        return np.zeros((0, 2), np.float32), z, z, z, np.zeros(0, np.int32), np.zeros(0, np.int32)
    a = np.array([(k.pt[0], k.pt[1], k.size, k.angle, k.response) for k in kps], np.float32)
    oc = np.array([(k.octave, k.class_id) for k in kps], np.int32)
    return a[:, :2].copy(), a[:, 2].copy(), a[:, 3].copy(), a[:, 4].copy(), oc[:, 0].copy(), oc[:, 1].copy()


def _subsequence(xy_in: np.ndarray, xy_out: np.ndarray) -> np.ndarray:
    """Indices into ``xy_in`` of ``xy_out``, an order-preserving subsequence of it (OpenCV's border
    filters erase keypoints in place and keep the order)."""
    idx = np.empty(len(xy_out), np.int64)
    j, n = 0, len(xy_in)
    for i, p in enumerate(xy_out):
        while j < n and not (xy_in[j, 0] == p[0] and xy_in[j, 1] == p[1]):
            j += 1
        if j == n:
            raise ImtuneError("internal: an OpenCV descriptor reordered or moved keypoints")
        idx[i] = j
        j += 1
    return idx


class OpenCVExtractor(Extractor):
    """Detect -> select (budget, upright) -> describe with OpenCV ``Feature2D`` objects.

    Subclasses set ``factories`` (OpenCV factory names they need), ``option_defaults`` and
    ``binary``, and implement ``_make_detector`` / ``_make_descriptor``. An instance holds OpenCV
    objects: use one per thread.
    """
    version: ClassVar[str] = f"1+opencv-{OPENCV_VERSION}"
    #: OpenCV factory names this extractor needs (checked by ``check_available``).
    factories: ClassVar[tuple[str, ...]] = ()
    #: extractor-specific options and their defaults (None: depends on ``low_threshold``).
    option_defaults: ClassVar[dict[str, Any]] = {}
    supports_upright: ClassVar[bool] = True
    supports_mr_size: ClassVar[bool] = False
    #: the OpenCV method stores its own data in KeyPoint.class_id (AKAZE/KAZE: scale level).
    uses_class_id: ClassVar[bool] = False
    #: option ranges, see ``check_bounds``.
    option_bounds: ClassVar[dict[str, str]] = {}
    #: why upright is unsupported (when ``supports_upright`` is False).
    upright_note: ClassVar[str] = ""

    def __init__(self, conf):
        super().__init__(conf)
        name = conf.name
        self.opts = parse_options(name, conf.options, {**COMMON_OPTIONS, **self.option_defaults})
        check_bounds(name, self.opts, {"clahe_clip": ">0", "clahe_tiles": ">=1", **self.option_bounds})
        self.upright = bool(conf.upright or conf.upright_plus)
        if self.upright and not self.supports_upright:
            raise ImtuneError(f"feature {name!r}: upright is not supported{': ' + self.upright_note if self.upright_note else ''}")
        if conf.mr_size is not None:
            if not self.supports_mr_size:
                raise ImtuneError(f"feature {name!r}: mr_size applies to SIFT descriptors only (sift, rootsift)")
            if not conf.mr_size > 0:
                raise ImtuneError(f"feature {name!r}: mr_size must be > 0, got {conf.mr_size}")
        self._clahe = None
        if conf.clahe != "none":
            tiles = int(self.opts["clahe_tiles"])
            self._clahe = cv2.createCLAHE(clipLimit=float(self.opts["clahe_clip"]), tileGridSize=(tiles, tiles))
        try:
            self.detector = self._make_detector()
            self.descriptor = self._make_descriptor()
        except cv2.error as e:  # OpenCV rejected an option value
            msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
            raise ImtuneError(f"feature {name!r}: OpenCV rejected the options {dict(conf.options or ())}: {msg}") from e

    @classmethod
    def check_available(cls) -> None:
        for f in cls.factories:
            cv_factory(f)

    # -- hooks -------------------------------------------------------------------------------
    def _make_detector(self):
        raise NotImplementedError

    def _make_descriptor(self):
        return self.detector

    def _description_sizes(self, size: np.ndarray) -> np.ndarray:
        """Keypoint sizes handed to the descriptor (SIFT rescales them for ``mr_size``)."""
        return size

    def _postprocess(self, desc: np.ndarray) -> np.ndarray:
        return desc

    def _output_positions(self, xy: np.ndarray, octave: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Keypoint positions as reported, from OpenCV's (``xy`` (N, 2), ``octave`` (N,) KeyPoint.octave, ``shape``
        (H, W) of the image): the hook where a detector's own coordinate frame is brought to the pixel-centre
        convention (SIFT, ORB). Applied after description, so that OpenCV describes the keypoints it detected."""
        return xy

    def _descriptor_dim(self) -> int:
        return int(self.descriptor.descriptorSize())

    # -- the pipeline --------------------------------------------------------------------------
    def _empty(self) -> Features:
        z = np.zeros(0, np.float32)
        dtype = np.uint8 if self.binary else np.float32
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, self._descriptor_dim()), dtype),
                        z, z.copy(), z.copy(), binary=self.binary)

    def _describe(self, img: np.ndarray, xy, size, angle, resp, octave, cid):
        """Describe one batch of keypoints. Returns (rows of the batch kept by the descriptor,
        descriptors, orientations in degrees [0, 360))."""
        dsize = self._description_sizes(size)
        dangle = np.zeros_like(angle) if self.upright else angle
        # class_id carries the row index through compute() (which silently drops keypoints whose
        # support leaves the image) unless the method keeps its own data there.
        ids = cid if self.uses_class_id else np.arange(len(xy), dtype=np.int32)
        kin = [cv2.KeyPoint(float(p[0]), float(p[1]), float(s), float(a), float(r), int(o), int(c))
               for p, s, a, r, o, c in zip(xy, dsize, dangle, resp, octave, ids)]
        kout, desc = self.descriptor.compute(img, kin)
        if len(kout) == 0 or desc is None:
            return np.zeros(0, np.int64), None, None
        if not self.uses_class_id:  # always: ORB returns every keypoint given, but grouped by pyramid level
            idx = np.array([k.class_id for k in kout], np.int64)
        elif len(kout) == len(kin):
            idx = np.arange(len(kin))
        else:
            idx = _subsequence(xy, np.array([k.pt for k in kout], np.float32))
        if self.upright:
            ori = np.zeros(len(idx), np.float32)
        else:  # the angle the descriptor used (KAZE, BRISK and FREAK assign their own)
            ori = np.mod(np.array([k.angle for k in kout], np.float32), np.float32(360.0)).astype(np.float32)
        order = np.argsort(idx, kind="stable")  # back to the order given (strongest first)
        return idx[order], np.asarray(desc)[order], ori[order]

    def extract(self, image: np.ndarray) -> Features:
        """Detect and describe. ``image``: (H, W) uint8 grayscale at the working resolution (px).

        Returns at most ``num_features`` keypoints, strongest first; fewer only when the detector
        finds fewer (or ``upright`` removed duplicates)."""
        conf, k = self.conf, self.conf.num_features
        img = as_gray_u8(image, conf.name)
        eq = self._clahe.apply(img) if self._clahe is not None else img
        det_img = eq if conf.clahe in ("detector", "both") else img
        desc_img = eq if conf.clahe in ("descriptor", "both") else img
        try:
            arrs = _kp_arrays(self.detector.detect(det_img, None))
            cand = rank_keypoints(arrs[0], arrs[1], arrs[2], arrs[3], k, self.upright, conf.upright_plus)
            rows, descs, oris = [], [], []
            got, start, end = 0, 0, min(k, len(cand))
            while start < end:
                batch = cand[start:end]
                idx, desc, ori = self._describe(desc_img, *(a[batch] for a in arrs))
                if len(idx):
                    rows.append(batch[idx])
                    descs.append(desc)
                    oris.append(ori)
                    got += len(idx)
                # Refill keypoints the descriptor dropped from the next-strongest candidates.
                start, end = end, min(len(cand), end + 2 * (k - got) + 16) if got < k else end
        except cv2.error as e:
            if min(img.shape) < TINY_SIDE:  # pyramids of a tiny image hit empty levels: no features
                return self._empty()
            msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
            raise ImtuneError(f"feature {conf.name!r} failed on a {img.shape[1]}x{img.shape[0]} image: {msg}") from e
        if got == 0:
            return self._empty()
        sel = np.concatenate(rows)[:k]
        desc = self._postprocess(np.concatenate(descs)[:k])
        desc = desc.astype(np.uint8 if self.binary else np.float32, copy=False)
        xy, size, _, resp = arrs[0], arrs[1], arrs[2], arrs[3]
        return Features(keypoints=np.ascontiguousarray(self._output_positions(xy[sel], arrs[4][sel], img.shape), np.float32),
                        descriptors=np.ascontiguousarray(desc),
                        scales=size[sel].astype(np.float32),
                        orientations=np.concatenate(oris)[:k],
                        scores=resp[sel].astype(np.float32), binary=self.binary)
