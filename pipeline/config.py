"""Plain, hashable stage configurations. Every cache key is derived from these (see ``pipeline.cache``)."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from dataclasses import dataclass, field

from pipeline.errors import ImtuneError

STRATEGIES = ("both", "either", "uni")

#: the largest random seed: the seeded estimators take 31 bits (pydegensac, OpenCV's RNG and COLMAP's
#: ``random_seed`` are masked to 0x7FFFFFFF or are a C int), so every seed in [0, SEED_MAX] reaches them
#: unchanged and two different seeds are two different runs; a larger one would alias a smaller one
SEED_MAX = 2**31 - 1
#: the largest iteration cap Gamma: the estimators take a C int (``GeometryEstimator.estimate`` clamps to it)
MAX_ITERS = 2**31 - 1


def check_seed(what: str, v) -> int:
    """A random seed: an integer in [0, SEED_MAX] (one-line ImtuneError naming ``what`` and the range)."""
    f = _number(what, v, integer=True)
    if not 0 <= f <= SEED_MAX or int(v) > SEED_MAX:
        raise ImtuneError(f"{what} must be an integer from 0 to {SEED_MAX} (the estimators take 31-bit seeds: a "
                          f"larger one would repeat a smaller one's run), got {v!r}")
    return int(v)


def run_seed(seed: int, k: int) -> int:
    """The seed of the ``k``-th repeated run (k = 0, 1, ...): ``seed + k``, wrapping past SEED_MAX to 0 (which the
    31-bit estimators did anyway), so every run's seed stays in range."""
    return (int(seed) + int(k)) % (SEED_MAX + 1)


_EXPONENT_RE = re.compile(r"^\s*(?P<m>[-+]?(?:\d+\.?\d*|\.\d+))[eE](?P<e>[-+]?\d+)\s*$")


def yaml_number_hint(v) -> str:
    """For a string that YAML read from a number in exponent notation (YAML 1.1, PyYAML's, reads ``1e5`` and
    ``1.0e5`` as strings: a float needs a dot and a signed exponent), `` (YAML reads 1e5 as a string: write 1.0e+5
    or 100000)``; "" for anything else. Appended to the "must be a number" messages of YAML values."""
    m = _EXPONENT_RE.match(v) if isinstance(v, str) else None
    if m is None:
        return ""
    mant, exp = m.group("m"), m.group("e")
    if "." not in mant:
        mant += ".0"
    elif mant.endswith("."):
        mant += "0"
    sci = f"{mant}e{exp if exp[0] in '+-' else '+' + exp}"
    if sci.lower() == v.strip().lower():  # already a YAML float: not why it failed
        return ""
    f = float(v)
    plain = str(int(f)) if f.is_integer() and abs(f) < 1e15 else ("" if "e" in repr(f) else repr(f))
    return f" (YAML reads {v.strip()} as a string: write {sci}" + (f" or {plain}" if plain else "") + ")"


def _number(what: str, v, integer: bool = False) -> float:
    """``v`` as a finite float (ImtuneError naming ``what`` for nan, inf, bools, non-numbers, non-integers)."""
    try:
        if isinstance(v, (bool, str, bytes)):
            raise TypeError
        f = float(v)
    except (TypeError, ValueError):
        raise ImtuneError(f"{what} must be a number, got {v!r}{yaml_number_hint(v)}") from None
    if not math.isfinite(f):
        raise ImtuneError(f"{what} must be a finite number, got {v!r}")
    if integer and f != int(f):
        raise ImtuneError(f"{what} must be an integer, got {v!r}")
    return f


def _set_types(obj) -> None:
    """Normalise a stage dataclass in place (its ``__post_init__``): an integral number in an int field becomes an
    int (YAML's ``num_features: 2048.0`` reached OpenCV as a float and crashed); a bool field takes true / false (or
    0 / 1) only (a quoted ``"false"`` was truthy: the option silently on); an optional path field a string."""
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if v is None:
            continue
        if f.type == "bool":
            if isinstance(v, bool) or getattr(getattr(v, "dtype", None), "kind", "") == "b" \
                    or (isinstance(v, int) and v in (0, 1)):
                object.__setattr__(obj, f.name, bool(v))
            else:
                raise ImtuneError(f"{f.name} must be true or false, got {v!r}")
        elif f.type == "int" and isinstance(v, float) and v.is_integer():  # anything else: the field's own check
            object.__setattr__(obj, f.name, int(v))
        elif f.type == "str | None" and not isinstance(v, str):
            raise ImtuneError(f"{f.name} must be a string (a folder), got {v!r}")


def check_covisibility(v) -> float | None:
    """A minimum co-visibility: None (all listed pairs) or a finite fraction in [0, 1]."""
    if v is None:
        return None
    f = _number("co-visibility", v)
    if not 0.0 <= f <= 1.0:
        raise ImtuneError(f"co-visibility must be in [0, 1], got {v!r}")
    return f


def config_hash(obj, n: int = 16) -> str:
    """Stable hex digest of a dataclass / dict / scalar (sorted-key JSON)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):  # an instance, not the class itself
        obj = dataclasses.asdict(obj)
    blob = json.dumps(obj, sort_keys=True, default=str).encode()
    return hashlib.sha1(blob).hexdigest()[:n]


@dataclass(frozen=True)
class FeatureConfig:
    """Local feature extraction.

    name: registry name (``tune list``), e.g. ``sift``, ``rootsift``, ``orb``.
    num_features: keypoint budget per image (the paper's two categories: 2048 and 8000).
    low_threshold: use the lowered detection threshold of the paper, so the budget is reached.
    upright: orientation fixed to 0 and duplicate (x, y) keypoints removed; ``upright_plus``
        refills to the budget after removing duplicates (the paper's "upright++").
    clahe: "none" | "detector" | "descriptor" | "both" — CLAHE before detection and/or description.
    mr_size: descriptor support scale (SIFT mrSize multiplier; None = library default).
    max_side: IMC resizing convention — images resized so the long side is at most this (px).
    options: extractor-specific extra options as sorted (key, value) pairs.
    """
    name: str = "sift"
    num_features: int = 8000
    low_threshold: bool = True
    upright: bool = False
    upright_plus: bool = False
    clahe: str = "none"
    mr_size: float | None = None
    max_side: int = 1024
    options: tuple = ()

    def __post_init__(self):
        _set_types(self)
        if _number("num_features", self.num_features, integer=True) < 1:
            raise ImtuneError(f"num_features must be >= 1, got {self.num_features}")
        if self.mr_size is not None and not _number("mr_size", self.mr_size) > 0:
            raise ImtuneError(f"mr_size must be > 0, got {self.mr_size}")
        if _number("max_side", self.max_side, integer=True) < 0:
            raise ImtuneError(f"max_side must be >= 0 px (0 = keep the original size), got {self.max_side}")
        if self.clahe not in ("none", "detector", "descriptor", "both"):
            raise ImtuneError(f"clahe must be none|detector|descriptor|both, got {self.clahe!r}")


@dataclass(frozen=True)
class MatchConfig:
    """Tentative matching from the cached k-NN tables.

    ratio: Lowe's ratio test threshold r in (0, 1]; 1 = no test.
    strategy: "both" (mutual NN, intersection), "either" (union), "uni" (i -> j only).
    distance_threshold: drop matches whose descriptor distance exceeds this (None = off).
    fginn: first-geometric-inconsistent NN: the second neighbour must lie > fginn_px from the first.
    method: "exact" brute force (default) or "flann" (4 KD-trees, 128 checks / LSH for binary).
    prefilter: outlier pre-filter applied to the tentative matches before the estimator / COLMAP
        (``pipeline.matching.prefilters``: none, gms, adalam, cne); prefilter_options: its (key, value) pairs.
    custom_matches: folder of imported matches (IMC h5 layout, ``pipeline.matching.custom_matches``);
        when set the matcher is skipped (ratio, strategy, distance threshold and FGINN do not apply).

    method may also name a learned matcher (``lightglue``, ``pipeline.matching.learned``): the network's raw output
    is cached per pair and a trial keeps the matches of confidence > ``min_confidence`` (in [0, 1]; LightGlue's
    ``filter_threshold``, default 0.1), the parameter that takes r's place; ratio, strategy, distance threshold and
    FGINN do not apply. matcher_options: its (key, value) pairs (LightGlue: depth_confidence, width_confidence).
    """
    ratio: float = 1.0
    strategy: str = "both"
    distance_threshold: float | None = None
    fginn: bool = False
    fginn_px: float = 10.0
    method: str = "exact"
    prefilter: str = "none"
    prefilter_options: tuple = ()
    custom_matches: str | None = None
    min_confidence: float = 0.1
    matcher_options: tuple = ()

    @property
    def learned(self) -> bool:
        """``method`` names a learned matcher (LightGlue), not a k-NN search."""
        from pipeline.matching.learned import is_learned
        return is_learned(self.method)

    def __post_init__(self):
        _set_types(self)
        if not (0.0 < _number("ratio r", self.ratio) <= 1.0):
            raise ImtuneError(f"ratio r must be in (0, 1], got {self.ratio}")
        if self.strategy not in STRATEGIES:
            raise ImtuneError(f"unknown matching strategy {self.strategy!r} (choose from {', '.join(STRATEGIES)})")
        if self.method not in ("exact", "flann") and not self.learned:
            from pipeline.matching.learned import LEARNED_MATCHERS
            raise ImtuneError(f"unknown matcher {self.method!r} (choose exact, flann or "
                              f"{' or '.join(LEARNED_MATCHERS.names())})")
        if not (0.0 <= _number("min_confidence", self.min_confidence) <= 1.0):
            raise ImtuneError(f"min_confidence must be in [0, 1] (a learned matcher's match confidence), "
                              f"got {self.min_confidence}")
        if self.distance_threshold is not None and _number("distance threshold", self.distance_threshold) < 0:
            raise ImtuneError(f"distance threshold must be >= 0, got {self.distance_threshold}")
        if not _number("fginn_px", self.fginn_px) > 0:
            raise ImtuneError(f"fginn_px must be > 0 px, got {self.fginn_px}")
        if not isinstance(self.prefilter, str) or not self.prefilter:
            raise ImtuneError(f"prefilter must be a name (see `tune list`), got {self.prefilter!r}")


@dataclass(frozen=True)
class GeometryConfig:
    """Robust estimation of F.

    ransac: estimator registry name (``tune list``), e.g. ``degensac``, ``magsac++``, ``cv-usac``.
    threshold: inlier threshold eta in pixels (at the working resolution, long side <= 1024 px).
    confidence: RANSAC confidence (the protocol fixes 0.999999).
    max_iters: iteration cap Gamma.
    seed: random seed passed to estimators that accept one.
    """
    ransac: str = "degensac"
    threshold: float = 0.5
    confidence: float = 0.999999
    max_iters: int = 50000
    seed: int = 0

    def __post_init__(self):
        _set_types(self)
        if not _number("inlier threshold", self.threshold) > 0:
            raise ImtuneError(f"inlier threshold must be > 0 px, got {self.threshold}")
        if not (0.0 < _number("confidence", self.confidence) < 1.0):
            raise ImtuneError(f"confidence must be in (0, 1), got {self.confidence}")
        if _number("max-iters", self.max_iters, integer=True) < 1:
            raise ImtuneError(f"max-iters must be >= 1, got {self.max_iters}")
        if int(self.max_iters) > MAX_ITERS:
            raise ImtuneError(f"max-iters must be at most {MAX_ITERS} (what the estimators take), got {self.max_iters}")
        check_seed("seed", self.seed)


#: MapperConfig's defaults that are not pycolmap's (see its docstring)
MAPPER_DEVIATIONS = ("min_model_size", "max_num_models", "init_min_num_inliers", "abs_pose_min_num_inliers")


@dataclass(frozen=True)
class MapperConfig:
    """The mapper options that decide registration in the reconstruction task (``pipeline.tasks.reconstruction``;
    searched there, ignored by every other task). Their defaults are pycolmap's own (``tests`` assert it against
    ``pycolmap.IncrementalPipelineOptions`` / ``GlobalPipelineOptions``), except :data:`MAPPER_DEVIATIONS`:
    ``min_model_size`` 3 and ``max_num_models`` 25 (the IMC 2025 baseline's settings), and ``init_min_num_inliers``
    25 and ``abs_pose_min_num_inliers`` 12 (pycolmap: 100 and 30): verified pairs at 2048 features carry tens of
    inliers, and at pycolmap's values the mapper registered 39% of the 76-image IMC 2025 dataset's images against 63%
    (``benchmarks/reconstruction_causes.py``, docs/reconstruction.md).

    min_inliers: a verified pair enters the view graph with at least this many inliers of our estimator (COLMAP's
        ``min_num_matches``, default 15): it decides which images connect, hence which scenes split or merge.
    min_model_size: a reconstruction of fewer images is no cluster (its images are written as outliers; COLMAP's
        ``min_model_size``): it decides whether small fragments and look-alike outliers count as clusters.
    max_num_models: the incremental mapper starts at most this many models (COLMAP's ``max_num_models``).
    init_min_num_inliers: inliers the initial pair needs (``mapper.init_min_num_inliers``; COLMAP halves it when no
        pair qualifies).
    abs_pose_min_num_inliers: 2D-3D inliers an image needs to be registered (``mapper.abs_pose_min_num_inliers``).
    abs_pose_max_error: the absolute pose RANSAC's threshold, px (``mapper.abs_pose_max_error``).
    filter_max_reproj_error: observations reprojecting further are dropped, px (``mapper.filter_max_reproj_error``).
    global_max_rotation_error: the global mapper's rotation-averaging outlier threshold, degrees
        (``mapper.rotation_averaging.max_rotation_error_deg``).
    global_max_angular_error: the global mapper's track filter, degrees (``mapper.max_angular_reproj_error_deg``).
    """
    min_inliers: int = 15
    min_model_size: int = 3
    max_num_models: int = 25
    init_min_num_inliers: int = 25
    abs_pose_min_num_inliers: int = 12
    abs_pose_max_error: float = 12.0
    filter_max_reproj_error: float = 4.0
    global_max_rotation_error: float = 10.0
    global_max_angular_error: float = 1.0

    def __post_init__(self):
        _set_types(self)
        if _number("min_inliers", self.min_inliers, integer=True) < 5:
            raise ImtuneError(f"min_inliers must be an integer >= 5, got {self.min_inliers}")
        if _number("min_model_size", self.min_model_size, integer=True) < 2:
            raise ImtuneError(f"min_model_size must be an integer >= 2, got {self.min_model_size}")
        for name in ("max_num_models", "init_min_num_inliers", "abs_pose_min_num_inliers"):
            if _number(name, getattr(self, name), integer=True) < 1:
                raise ImtuneError(f"{name} must be an integer >= 1, got {getattr(self, name)}")
        for name in ("abs_pose_max_error", "filter_max_reproj_error", "global_max_rotation_error",
                     "global_max_angular_error"):
            if not _number(name, getattr(self, name)) > 0:
                raise ImtuneError(f"{name} must be > 0, got {getattr(self, name)}")
            object.__setattr__(self, name, float(getattr(self, name)))  # 12 and 12.0: one configuration, one hash


@dataclass(frozen=True)
class PipelineConfig:
    feature: FeatureConfig = field(default_factory=FeatureConfig)
    matching: MatchConfig = field(default_factory=MatchConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)

    def __post_init__(self):
        from pipeline.matching.learned import check_pair
        check_pair(self.matching.method, self.feature, self.matching.matcher_options)  # LightGlue + sift: one line

    def to_dict(self) -> dict:
        """The sections as plain dicts; ``mapper`` only where it differs from its defaults (it is read by the
        reconstruction task alone, and every other configuration, study and frozen file keeps its form); the
        learned matcher's fields (``min_confidence``, ``matcher_options``) only with a learned matcher (the same)."""
        d = dataclasses.asdict(self)
        if self.mapper == MapperConfig():
            d.pop("mapper")
        if not self.matching.learned:
            for k in ("min_confidence", "matcher_options"):
                d["matching"].pop(k)
        return d
