"""Learned matchers: a network matches two images' features at once (LightGlue), beside the k-NN strategies.

    from pipeline.matching.learned import LEARNED_MATCHERS, LearnedMatches
    LEARNED_MATCHERS.names()                 # ['lightglue']
    matcher = get_learned_matcher(conf)      # conf: MatchConfig with method "lightglue"
    raw = matcher.match(fi, fj)              # LearnedMatches: every candidate match and its confidence
    m, conf = raw.select(0.2)                # what a trial keeps: confidence > 0.2

How they fit the protocol: a learned matcher's raw output (each candidate match with its confidence in [0, 1]) is
what is cached per feature set and pair (``pipeline.tasks.prepare.pair_knn``), as the k-NN tables are; a trial
only thresholds it at ``MatchConfig.min_confidence``, the parameter that takes the ratio test's place in the search
space. The ratio test, strategy, distance threshold and FGINN do not apply. The network's time is matching time
(``match_seconds`` of a stereo record), reported and outside the estimator's budget.

A matcher is trained for one feature: :meth:`LearnedMatcher.check_feature` refuses, in one line, a feature it has
no weights for.
"""
from __future__ import annotations

from pipeline.errors import ImtuneError
from pipeline.matching.learned_base import (  # noqa: F401  (the family's names, re-exported)
    LEARNED_MATCHERS,
    LearnedMatcher,
    LearnedMatches,
    parse_matcher_options,
)


def is_learned(method: str) -> bool:
    """``method`` (``MatchConfig.method``) names a learned matcher."""
    _register()
    return method in LEARNED_MATCHERS


def get_learned_matcher(method: str, options=()) -> LearnedMatcher:
    _register()
    cls = LEARNED_MATCHERS.get(method)
    cls.check_available()
    return cls(options)


def check_pair(method: str, feature, options=()) -> None:
    """One-line ImtuneError when the learned matcher ``method`` cannot match ``feature`` (no weights for it) or its
    options are invalid; nothing for the k-NN methods."""
    if not is_learned(method):
        if options:
            raise ImtuneError(f"matcher options {dict(options)} apply to a learned matcher (--matcher "
                              f"{' | '.join(LEARNED_MATCHERS.names())}), not to {method!r}: drop them")
        return
    cls = LEARNED_MATCHERS.get(method)
    cls.check_feature(feature)
    cls(options)


def _register() -> None:
    import pipeline.matching.lightglue  # noqa: F401  (registers "lightglue"; it subclasses learned_base's class)
