"""Nearest-neighbour matching: exact both-direction k-NN tables (cached per pair) and the per-trial filter.

    from pipeline.matching import knn_tables, filter_matches, match_descriptors
    tab = knn_tables(desc1, desc2, binary=False, k=2)           # the expensive, cacheable part
    matches, dist = filter_matches(tab, MatchConfig(ratio=0.8))   # microseconds, every trial
    matches, dist = match_descriptors(desc1, desc2, conf)         # both steps

See ``knn.py`` for how the search is done and ``filter.py`` for the matching conventions.
"""
from __future__ import annotations

from pipeline.config import MatchConfig
from pipeline.matching.filter import filter_matches
from pipeline.matching.knn import KnnTables, knn_tables, warmup

__all__ = ["KnnTables", "knn_tables", "filter_matches", "match_descriptors", "neighbours_needed", "warmup"]


def neighbours_needed(conf: MatchConfig) -> int:
    """k of the tables a config needs: 2 for the ratio test, 10 for FGINN's spatial search."""
    return 10 if conf.fginn else 2


def match_descriptors(desc1, desc2, conf: MatchConfig, binary: bool = False, kpts1=None, kpts2=None):
    """k-NN tables (``conf.method``) then ``filter_matches``: (matches (M, 2) int32, distances (M,) float32)."""
    tab = knn_tables(desc1, desc2, binary=binary, k=neighbours_needed(conf), method=conf.method)
    return filter_matches(tab, conf, kpts1, kpts2)
