"""The learned-matcher family's base: the registry, the raw output a matcher returns and caches, and the matcher
base class (its options typed by their defaults). ``pipeline.matching.learned`` is the family's entry point; a
matcher module (``lightglue.py``) subclasses :class:`LearnedMatcher` from here."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.errors import ImtuneError
from pipeline.registry import Registry

LEARNED_MATCHERS = Registry("learned matcher")


@dataclass
class LearnedMatches:
    """A learned matcher's raw output for a pair: ``matches`` (M, 2) int32 [i in image 1, j in image 2], sorted by
    i; ``confidence`` (M,) float32 in [0, 1]; ``n1``, ``n2`` keypoints. Holds every match the network proposes at
    confidence > 0 (LightGlue: the mutual best assignments), so that any threshold is a selection of it."""
    matches: np.ndarray
    confidence: np.ndarray
    n1: int
    n2: int

    def select(self, min_confidence: float) -> tuple[np.ndarray, np.ndarray]:
        """(matches (K, 2) int32, confidences (K,) float32) with confidence > ``min_confidence`` (strictly, as
        LightGlue's own ``filter_threshold``)."""
        keep = np.asarray(self.confidence, np.float64) > float(min_confidence)
        return np.asarray(self.matches, np.int32).reshape(-1, 2)[keep], np.asarray(self.confidence, np.float32)[keep]


class LearnedMatcher:
    """Base class. Subclasses register with ``LEARNED_MATCHERS.register(name)`` and declare ``option_defaults``
    (options of ``MatchConfig.matcher_options``, typed by their default) and ``version`` (part of the cache key:
    bump it when the output of :meth:`match` changes)."""
    name: ClassVar[str] = ""
    version: ClassVar[str] = "1"
    option_defaults: ClassVar[dict[str, Any]] = {}

    def __init__(self, options=()):
        self.opts = parse_matcher_options(self.name, options, self.option_defaults)
        self.check_options()

    def check_options(self) -> None:
        """One-line ImtuneError for an invalid option value."""

    @classmethod
    def check_available(cls) -> None:
        """UnavailableError (one line) when the matcher cannot run here (missing package or weights)."""

    @classmethod
    def check_feature(cls, feature) -> None:
        """One-line ImtuneError unless the matcher has weights for ``feature`` (a FeatureConfig)."""

    def cache_parts(self, feature_name: str) -> list:
        """What the cached output depends on besides the two feature sets (options, weights, code versions)."""
        return [self.name, self.version, sorted(self.opts.items())]

    def warmup(self, feature_name: str) -> None:
        """Load the network (once per process), so that the seconds :meth:`match` is timed for are matching only."""

    def match(self, fi, fj, feature_name: str) -> LearnedMatches:
        """The raw output for a pair of ``pipeline.tasks.prepare.ImageFeatures``."""
        raise NotImplementedError


def parse_matcher_options(name: str, options, defaults: dict[str, Any]) -> dict[str, Any]:
    """``MatchConfig.matcher_options`` ((key, value) pairs or a dict) over ``defaults``, each value a number (the
    options are thresholds); one-line ImtuneError naming the matcher and the key otherwise."""
    try:
        given = dict(options or ())
    except (TypeError, ValueError):
        raise ImtuneError(f"matcher {name!r}: options must be KEY=VALUE pairs, got {options!r}") from None
    out = dict(defaults)
    for k, v in given.items():
        if k not in defaults:
            raise ImtuneError(f"matcher {name!r}: unknown option {k!r} (known: {', '.join(sorted(defaults))})")
        try:
            if isinstance(v, (bool, str, bytes)):
                raise TypeError
            f = float(v)
        except (TypeError, ValueError):
            raise ImtuneError(f"matcher {name!r}: option {k} must be a number, got {v!r}") from None
        if not np.isfinite(f):
            raise ImtuneError(f"matcher {name!r}: option {k} must be finite, got {v!r}")
        out[k] = f
    return out
