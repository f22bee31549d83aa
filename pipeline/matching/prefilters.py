"""Outlier pre-filters: applied to a pair's tentative matches between matching and the robust estimator
(stereo) or COLMAP (multiview) — the official benchmark's ``outlier_filter`` slot.

    from pipeline.matching.prefilters import PREFILTERS, PairContext, apply_prefilter
    keep = apply_prefilter("gms", matches, PairContext(kpts1, kpts2, size1=(w1, h1), size2=(w2, h2)))
    matches = matches[keep]

Registered (``tune list`` shows availability):

- ``none``: keep every match.
- ``gms``: GMS, grid-based motion statistics (Bian et al., CVPR 2017), OpenCV contrib
  ``cv2.xfeatures2d.matchGMS``. Options: ``rotation`` (false), ``scale`` (false), ``threshold`` (6.0,
  the threshold factor: higher keeps fewer). Made for many matches (its authors use ~10k); with a
  strict ratio test it can empty a pair.
- ``adalam``: AdaLAM (Cavalli et al., ECCV 2020), kornia ``AdalamFilter``: local affine verification
  around confident seeds, using keypoint scales and orientations when the feature has them. Options:
  AdaLAM's own (``area_ratio`` 100, ``search_expansion`` 4, ``ransac_iters`` 128, ``min_inliers`` 6,
  ``min_confidence`` 200, ``orientation_difference_threshold`` 30 deg, ``scale_rate_threshold`` 1.5,
  ``detected_scale_rate_threshold`` 5, ``refit`` true, ``force_seed_mnn`` true) and ``putative``:
  "tentative" (default: filter the matches the ratio test and strategy kept, so the tuned r still
  matters) or "nn" (AdaLAM's intended input: every nearest neighbour of image 1, scored by its ratio,
  whatever r and the strategy are). Seeds are matches whose squared distance ratio is below 0.64.
- ``cne``: Context Normalization networks (Yi et al., CVPR 2018; the official benchmark's filter) need
  trained weights that are not distributed with this project: listed, unavailable. A trained model plugs
  in by registering a :class:`Prefilter` subclass (see docs/extending.md).

A pre-filter returns a boolean mask over the input matches (order kept). Its config lives in
``MatchConfig.prefilter`` (name) and ``MatchConfig.prefilter_options`` ((key, value) pairs).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.errors import ImtuneError, UnavailableError
from pipeline.registry import Registry

PREFILTERS = Registry("prefilter")


@dataclass
class PairContext:
    """What a pre-filter may use about a pair (keypoints at the working resolution).

    kpts1 (N1, 2), kpts2 (N2, 2) px; size1, size2: (width, height) px; scales / orientations: (N,) or
    None (OpenCV ``KeyPoint.size`` / angle conventions); ratio (M,): per match d1 / d2 of its source row
    (lower is better; None if unknown); tables: the pair's k-NN tables (``KnnTables``) or None.
    """
    kpts1: np.ndarray
    kpts2: np.ndarray
    size1: tuple[int, int] | None = None
    size2: tuple[int, int] | None = None
    scales1: np.ndarray | None = None
    scales2: np.ndarray | None = None
    orientations1: np.ndarray | None = None
    orientations2: np.ndarray | None = None
    ratio: np.ndarray | None = None
    tables: Any = None


class Prefilter(ABC):
    """Base class. Subclasses register with ``PREFILTERS.register(name)``; ``option_defaults`` lists the
    accepted options (type from the default)."""
    option_defaults: ClassVar[dict[str, Any]] = {}

    def __init__(self, name: str, options=()):
        from pipeline.features._opencv import parse_options
        self.check_available()
        self.name = name
        try:
            self.opts = parse_options(name, options, self.option_defaults)
        except ImtuneError as e:  # same checks as feature options; say what it is about
            raise ImtuneError(str(e).replace(f"feature {name!r}", f"prefilter {name!r}", 1)) from None

    @classmethod
    def check_available(cls) -> None:
        """Raise UnavailableError with a one-line reason when it cannot run here."""

    @abstractmethod
    def filter(self, matches: np.ndarray, ctx: PairContext) -> np.ndarray:
        """Boolean mask (M,) over ``matches`` ((M, 2) int [i in image 1, j in image 2])."""


def _check_positive(name: str, opts: dict, keys: tuple) -> None:
    """Each of ``keys`` in ``opts`` is > 0 (one-line ImtuneError naming the pre-filter and the option)."""
    for k in keys:
        if not opts[k] > 0:
            raise ImtuneError(f"prefilter {name!r}: option {k} must be > 0, got {opts[k]}")


@PREFILTERS.register("none", "no pre-filter (default)")
class NoFilter(Prefilter):
    def filter(self, matches, ctx):
        return np.ones(len(matches), bool)


@PREFILTERS.register("gms", "GMS grid-based motion statistics (OpenCV contrib matchGMS)")
class GMS(Prefilter):
    """GMS (Bian et al., CVPR 2017) through ``cv2.xfeatures2d.matchGMS``."""
    option_defaults = {"rotation": False, "scale": False, "threshold": 6.0}

    def __init__(self, name, options=()):
        super().__init__(name, options)
        _check_positive(name, self.opts, ("threshold",))  # <= 0 kept every match, unsaid

    @classmethod
    def check_available(cls) -> None:
        from pipeline.features._opencv import cv_factory
        cv_factory("matchGMS")

    def filter(self, matches, ctx):
        import cv2

        from pipeline.features._opencv import cv_factory
        m = np.asarray(matches).reshape(-1, 2)
        if len(m) == 0:
            return np.zeros(0, bool)
        if ctx.size1 is None or ctx.size2 is None:
            raise ImtuneError("gms needs the image sizes of the pair")
        # Only the matched keypoints are passed (GMS reads their positions), re-indexed.
        u1, inv1 = np.unique(m[:, 0], return_inverse=True)
        u2, inv2 = np.unique(m[:, 1], return_inverse=True)
        k1 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in np.asarray(ctx.kpts1, np.float64)[u1, :2]]
        k2 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in np.asarray(ctx.kpts2, np.float64)[u2, :2]]
        # DMatch.imgIdx is unused by GMS (it returns copies of the kept input matches): it carries the row
        dm = [cv2.DMatch(int(a), int(b), r, 0.0) for r, (a, b) in enumerate(zip(inv1.ravel(), inv2.ravel()))]
        out = cv_factory("matchGMS")(tuple(int(v) for v in ctx.size1), tuple(int(v) for v in ctx.size2), k1, k2, dm,
                                     bool(self.opts["rotation"]), bool(self.opts["scale"]),
                                     float(self.opts["threshold"]))
        keep = np.zeros(len(m), bool)
        if out:
            rows = np.fromiter((d.imgIdx for d in out), np.int64, len(out))
            keep[rows] = True
        return keep


ADALAM_DEFAULTS: dict[str, Any] = {
    "area_ratio": 100, "search_expansion": 4, "ransac_iters": 128, "min_inliers": 6, "min_confidence": 200,
    "orientation_difference_threshold": 30.0, "scale_rate_threshold": 1.5, "detected_scale_rate_threshold": 5.0,
    "refit": True, "force_seed_mnn": True, "putative": "tentative", "threads": 0,
}


@PREFILTERS.register("adalam", "AdaLAM local affine verification (kornia)")
class AdaLAM(Prefilter):
    """AdaLAM (Cavalli et al., ECCV 2020) through kornia's ``AdalamFilter.filter_matches``."""
    option_defaults = ADALAM_DEFAULTS

    @classmethod
    def check_available(cls) -> None:
        from pipeline.features.kornia_base import require_torch_kornia
        require_torch_kornia()

    def __init__(self, name, options=()):
        super().__init__(name, options)
        if self.opts["putative"] not in ("tentative", "nn"):
            raise ImtuneError(f"adalam: option putative must be tentative or nn, got {self.opts['putative']!r}")
        # out of range they were an internal error inside kornia (ransac_iters=0, scale_rate_threshold=0, threads<0)
        # or a silent nonsense (area_ratio=0 emptied every pair, min_inliers=-5)
        _check_positive(name, self.opts, ("area_ratio", "search_expansion", "ransac_iters", "min_inliers",
                                          "min_confidence", "orientation_difference_threshold",
                                          "scale_rate_threshold", "detected_scale_rate_threshold"))
        if self.opts["threads"] < 0:
            raise ImtuneError(f"prefilter {name!r}: option threads must be >= 0 (0: torch's default), "
                              f"got {self.opts['threads']}")

    def _config(self, ctx: PairContext) -> dict:
        import torch
        cfg = {k: v for k, v in self.opts.items() if k not in ("putative", "threads")}
        for k in ("area_ratio", "search_expansion", "ransac_iters", "min_inliers", "min_confidence"):
            cfg[k] = int(cfg[k])
        if ctx.orientations1 is None or ctx.orientations2 is None:
            cfg["orientation_difference_threshold"] = None
        if ctx.scales1 is None or ctx.scales2 is None:
            cfg["scale_rate_threshold"] = None
        cfg["device"] = torch.device("cpu")
        return cfg

    def filter(self, matches, ctx):
        from pipeline.features.kornia_base import torch_setup
        m = np.asarray(matches, np.int64).reshape(-1, 2)
        if len(m) == 0:
            return np.zeros(0, bool)
        torch = torch_setup(int(self.opts["threads"]))
        from kornia.feature.adalam import AdalamFilter
        if self.opts["putative"] == "nn":
            src, dst, score, mnn = self._nn_input(ctx)
        else:
            src, dst = m[:, 0], m[:, 1]
            score = (np.asarray(ctx.ratio, np.float64) ** 2 if ctx.ratio is not None
                     else np.zeros(len(m)))  # no ratios (custom matches): every match may seed
            mnn = None
        k1 = np.asarray(ctx.kpts1, np.float32)[src, :2]
        k2 = np.asarray(ctx.kpts2, np.float32)
        t = lambda a, dt=torch.float32: torch.from_numpy(np.ascontiguousarray(a)).to(dt)  # noqa: E731
        o1 = t(ctx.orientations1[src]) if ctx.orientations1 is not None else None
        o2 = t(ctx.orientations2) if ctx.orientations2 is not None else None
        s1 = t(ctx.scales1[src]) if ctx.scales1 is not None else None
        s2 = t(ctx.scales2) if ctx.scales2 is not None else None
        cfg = self._config(ctx)
        if mnn is None:
            cfg["force_seed_mnn"] = False
        with torch.inference_mode():
            idx = AdalamFilter(cfg).filter_matches(
                t(k1), t(k2), t(dst, torch.long), t(score), t(mnn, torch.bool) if mnn is not None else None,
                tuple(ctx.size1) if ctx.size1 else None, tuple(ctx.size2) if ctx.size2 else None,
                o1, o2, s1, s2)
        idx = idx.numpy().reshape(-1, 2)
        pairs = np.stack([src[idx[:, 0]], idx[:, 1]], 1) if len(idx) else np.zeros((0, 2), np.int64)
        n2 = max(len(ctx.kpts2), 1)
        return np.isin(m[:, 0] * n2 + m[:, 1], pairs[:, 0] * n2 + pairs[:, 1])

    @staticmethod
    def _nn_input(ctx: PairContext):
        tab = ctx.tables
        if tab is None or np.asarray(tab.idx12).ndim != 2 or np.asarray(tab.idx12).shape[1] < 2:
            raise ImtuneError("adalam putative=nn needs the pair's k-NN tables (k >= 2)")
        idx12, d12 = np.asarray(tab.idx12), np.asarray(tab.dist12, np.float64)
        idx21 = np.asarray(tab.idx21)
        src = np.flatnonzero(idx12[:, 0] >= 0)
        dst = idx12[src, 0].astype(np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            score = np.where(np.isfinite(d12[src, 1]) & (d12[src, 1] > 0), (d12[src, 0] / d12[src, 1]) ** 2, 0.0)
        mnn = idx21[dst, 0] == src
        return src, dst, score, mnn


@PREFILTERS.register("cne", "CNe context normalization (needs trained weights: unavailable)")
class CNe(Prefilter):
    """Context Normalization networks (Yi et al., CVPR 2018): the interface is here; no trained model is."""

    @classmethod
    def check_available(cls) -> None:
        raise UnavailableError("cne needs trained weights that are not distributed with imtune; register a "
                               "trained model as a Prefilter (see Extending in the docs)")

    def filter(self, matches, ctx):  # pragma: no cover - never constructed
        raise NotImplementedError


def get_prefilter(name: str, options=()) -> Prefilter:
    """An instance of the pre-filter ``name`` (ImtuneError if unknown, UnavailableError if it cannot run)."""
    return PREFILTERS.get(name)(name, options)


def apply_prefilter(name: str, matches: np.ndarray, ctx: PairContext, options=()) -> np.ndarray:
    """Boolean mask over ``matches`` kept by the pre-filter ``name`` (all True for "none")."""
    if not name or name == "none":
        return np.ones(len(matches), bool)
    keep = np.asarray(get_prefilter(name, options).filter(np.asarray(matches), ctx), bool).reshape(-1)
    if keep.shape != (len(matches),):
        raise ImtuneError(f"prefilter {name!r} returned a mask of shape {keep.shape} for {len(matches)} matches")
    return keep


def parse_prefilter_spec(spec: str | None) -> tuple[str, tuple]:
    """``"adalam:min_inliers=8,putative=nn"`` -> ("adalam", (("min_inliers", "8"), ("putative", "nn")));
    the name is checked against the registry and for availability (one-line errors), the options by the
    pre-filter's own parser."""
    spec = (spec or "none").strip()
    name, _, rest = spec.partition(":")
    name = name.strip().lower()
    opts: list[tuple[str, str]] = []
    for item in filter(None, (x.strip() for x in rest.split(","))):
        k, eq, val = item.partition("=")
        if not eq or not k.strip():
            raise ImtuneError(f"--prefilter {spec!r}: options are key=value pairs separated by commas")
        if k.strip() in dict(opts):  # the last one was used, unsaid
            raise ImtuneError(f"--prefilter {spec!r}: option {k.strip()} is given twice: give it once")
        opts.append((k.strip(), val.strip()))
    opts_t = tuple(sorted(opts))
    if name != "none":
        get_prefilter(name, opts_t)  # unknown / unavailable / bad options -> one-line error now
    return name, opts_t
