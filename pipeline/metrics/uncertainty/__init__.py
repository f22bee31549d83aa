"""How sure an mAA is, and whether a difference between two configurations is real.

Everything here rests on one fact: mAA(tau) is *linear* in per-pair scores. With
``score_p = mean over k = 1..tau of [err_p <= k]`` (0 for a failure, err = inf), a scene's mAA is the
mean of its pairs' scores, and the benchmark's overall mAA (the mean over scenes of the per-scene mAA)
is ``sum_p w_p score_p`` with ``w_p = 1 / (n_scenes * n_pairs_in_scene)``. So

- a confidence interval is a bootstrap of that weighted mean, resampling pairs *within* each scene
  (stratified by scene: every resample keeps each scene's pair count and the scenes' equal weights);
- a paired comparison of A and B on the same pairs is the same statistic of ``score_b - score_a``;
- averaging repeated runs pair by pair gives exactly the mean of the runs' mAAs.

Conventions (all functions):

- ``n_resamples`` bootstrap resamples (default 2000), ``seed`` (default 0: the same inputs always give
  the same interval), ``level`` (default 0.95). Intervals are percentile intervals from
  ``scipy.stats.bootstrap`` (``method="BCa"`` is accepted; it falls back to the percentile interval
  where BCa is undefined, e.g. when every resample gives the same value): for an mAA with the pseudo-scores
  below, for a paired difference at the expanded level of :func:`stratified_interval`; rankings compare at
  a Bonferroni level (:func:`rank_with_ties`).
- Intervals are ``[lo, hi]`` lists of floats; keys are ``mAA5_ci``, ``mAA10_ci`` (one per tau).
- Small and easy scenes (:data:`SCORE_RANGE`): the mAA intervals (stereo, multiview, repeated runs) take the
  spread of resamples of each scene's (bag group's) scores together with two pseudo-scores at the ends of a
  score's range, one failed (0) and one perfect (1) -- the "add two" of Agresti & Coull (1998) for a
  proportion, here for a mean of scores bounded in [0, 1] -- and centre it at the plain estimate (the pseudo-
  scores widen the interval, they do not move it). Why: a pair score is bounded, and an easy scene's is
  skewed against 1 with rare failures. The plain percentile bootstrap of 12 pairs of a scene with true
  mAA(10) 0.978 (2% failures) covered the truth 38% of the time (most samples hold no failure: every resample
  is 1.0 and the "95%" interval [1, 1]), 66% at 55 pairs; 10 pairs of a scene at 0.877 70%; three such scenes'
  overall mAA 88%. With the pseudo-scores: 93-100% per scene and 95-99% overall from 8 to 73 pairs per
  scene (conservative at 8-12 pairs), within 10% of the plain width at 33-73 pairs of middling scenes
  (``benchmarks/interval_coverage.py intervals`` measures it). A scene with one pair is resampled the same
  way (one pair says little); a scene without pairs is the constant 0 the task reports. :func:`stratified_interval` adds nothing unless asked (``pseudo``).
- Errors are in degrees; ``inf`` (or the string ``"inf"`` of a JSON file) and NaN count as failures,
  exactly as :func:`pipeline.metrics.pose.mean_average_accuracy` treats them.

numpy + scipy only; nothing above ``pipeline.metrics`` is imported.

One module per idea: :mod:`~pipeline.metrics.uncertainty.scores` (pair scores, their range, the defaults),
:mod:`~pipeline.metrics.uncertainty.intervals` (bootstrap intervals of an mAA),
:mod:`~pipeline.metrics.uncertainty.paired` (paired comparisons and the verdict rule),
:mod:`~pipeline.metrics.uncertainty.bags` (multiview bag records), :mod:`~pipeline.metrics.uncertainty.multiplicity`
(Holm, Bonferroni), :mod:`~pipeline.metrics.uncertainty.ranking` (ranks with ties),
:mod:`~pipeline.metrics.uncertainty.runs` (repeated runs combined). Every name is importable from
``pipeline.metrics.uncertainty`` as before.
"""
from __future__ import annotations

from pipeline.metrics.uncertainty.bags import bags_differ, is_bag_records
from pipeline.metrics.uncertainty.intervals import bag_intervals, maa_intervals, stratified_interval
from pipeline.metrics.uncertainty.multiplicity import bonferroni, holm
from pipeline.metrics.uncertainty.paired import (
                                                 DIRECTION_RULE,
                                                 format_p,
                                                 paired_bags,
                                                 paired_bootstrap,
                                                 paired_direction,
                                                 paired_relative,
)
from pipeline.metrics.uncertainty.ranking import rank_by_intervals, rank_with_ties
from pipeline.metrics.uncertainty.runs import combine_bag_runs_interval, combine_runs_interval
from pipeline.metrics.uncertainty.scores import (
                                                 DEFAULT_LEVEL,
                                                 DEFAULT_RESAMPLES,
                                                 SCORE_RANGE,
                                                 STD_DDOF,
                                                 maa_from_errors,
                                                 pair_scores,
)

__all__ = ["pair_scores", "maa_from_errors", "maa_intervals", "bag_intervals", "paired_bootstrap", "paired_direction",
           "DIRECTION_RULE", "rank_with_ties", "rank_by_intervals", "combine_runs_interval",
           "combine_bag_runs_interval", "paired_bags", "bags_differ", "is_bag_records", "stratified_interval", "holm",
           "bonferroni", "DEFAULT_RESAMPLES", "DEFAULT_LEVEL", "SCORE_RANGE", "STD_DDOF", "format_p", "paired_relative"]
