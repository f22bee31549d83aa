"""The three promises of a tuned verdict (issue 47), on synthetic data with a known truth:

- "could detect |A - B| >= mde": with the truth at the median mde, the test rejects about 80% of the time, and the
  power a comparison predicts for itself matches the power reached;
- the tuned figure (``replicated_maa_interval``) from 8 test pairs near the ceiling covers its truth;
- P(A > B) is unbiased and its interval covers, under a real difference.

The normal world of test_replicates_stats (pairs shared by both sides, a tuning shift per replicate, seed noise
per cell) for the comparisons; per-pair mAA(10) scores from normal log10 pose errors for the figure, whose expected
value is a sum of normal cdfs. Few data sets each, bands that the replaced functions fall outside of."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import special

from pipeline.metrics.replicates import (
    FEW_PAIRS_NOTE,
    replicated_difference,
    replicated_maa_interval,
)

STRATA = np.repeat([0, 1, 2], 10)
TUNING_SD, SEED_SD, METHOD_PAIR_SD = 0.04, 0.08, 0.03


def _side(rng, pairs, k, shift=0.0):
    return (pairs[None, :] + shift + rng.normal(0, TUNING_SD, (k, 1))
            + rng.normal(0, SEED_SD, (k, pairs.size)))


def _comparison(rng, shift):
    """3 vs 3 replicates on 30 pairs; B another method (its own per-pair term), worse by ``shift`` in truth."""
    pairs = rng.normal(0.5, 0.25, STRATA.size)
    b = _side(rng, pairs + rng.normal(0, METHOD_PAIR_SD, STRATA.size), 3)
    return replicated_difference(_side(rng, pairs, 3, shift), b, STRATA)


def test_power_at_the_median_detectable_difference_is_80_percent():
    """The tuning shift dominates (each side's replicate variance on 2 df): the replaced mde, computed at the
    estimated standard error, reached about 0.70 here; now 0.85 (each variance part median-unbiased errs on the
    side of power where two replicate parts on 2 df each dominate), and the power a comparison predicts for
    itself at the true difference is within 0.08 of the power reached."""
    rng = np.random.default_rng(47)
    target = float(np.median([_comparison(rng, 0.0).mde for _ in range(300)]))
    rejected, predicted = [], []
    for _ in range(700):
        d = _comparison(rng, target)
        rejected.append(d.p_value < 0.05 and d.diff > 0)
        predicted.append(d.power_at(target))
    reached = float(np.mean(rejected))
    assert 0.75 <= reached <= 0.90, (target, reached)
    assert abs(float(np.median(predicted)) - reached) <= 0.08, (np.median(predicted), reached)


def test_power_at_is_what_the_detectable_difference_solves():
    d = _comparison(np.random.default_rng(3), 0.0)
    assert d.power_at(d.mde) == pytest.approx(0.80, abs=2e-3)
    assert d.power_se >= d.se
    assert d.power_at(0.0) == pytest.approx(0.05, abs=1e-6)


def _scores(log_err):
    """Per-pair mAA(10) of log10 pose errors in degrees: the share of thresholds 1..10 the error is within."""
    return np.clip(11.0 - np.ceil(10.0 ** log_err), 0.0, 10.0) / 10.0


def _expected(mu, sd):
    return float(special.ndtr((np.log10(np.arange(1, 11)) - mu) / sd).mean())


@pytest.mark.parametrize("layout", [(4, 4), (3, 3, 2)])
def test_tuned_figure_from_8_pairs_near_the_ceiling_covers(layout):
    """K = 3 replicates, 8 test pairs, mAA(10) near 0.89: the symmetric interval (the replaced one) covered
    0.83-0.85 here, missing low; on the logit scale 0.93-0.94 (binomial sd 0.011 at 400 data sets)."""
    rng = np.random.default_rng(len(layout))
    scene_mu = np.linspace(-0.4, 0.1, len(layout))
    strata = np.repeat(np.arange(len(layout)), layout)
    mu = np.repeat(scene_mu, layout)
    tau, pair_sd, seed_sd = 0.02, 0.45, 0.25
    sd = math.sqrt(pair_sd**2 + tau**2 + (tau / 2) ** 2 + seed_sd**2)
    truth = float(np.mean([_expected(m, sd) for m in scene_mu]))
    hits, notes = 0, set()
    for _ in range(400):
        lat = (rng.normal(mu, pair_sd)[None, :] + rng.normal(0, tau, (3, 1)) + rng.normal(0, tau / 2, (3, mu.size))
               + rng.normal(0, seed_sd, (3, mu.size)))
        iv = replicated_maa_interval(_scores(lat), strata)
        hits += iv.low <= truth <= iv.high
        notes.add(iv.note)
    assert 0.90 <= hits / 400 <= 0.98, hits / 400
    assert FEW_PAIRS_NOTE in notes  # `tune` says that few pairs near the ceiling are where it was measured short


def test_the_few_pairs_note_is_not_given_at_10_pairs_a_scene():
    rng = np.random.default_rng(0)
    scores = np.clip(rng.normal(0.9, 0.05, (3, 30)), 0, 1)
    assert replicated_maa_interval(scores, STRATA).note == ""
    assert replicated_maa_interval(scores[:, :8], np.repeat([0, 1], 4)).note == FEW_PAIRS_NOTE


@pytest.mark.parametrize("delta", [0.07, 0.09])
def test_p_a_beats_b_is_unbiased_and_its_interval_covers(delta):
    """Truth: Phi(delta / sigma_1), sigma_1^2 = 2 (tuning sd^2 + seed sd^2 / N), the variance of the difference of
    two single tunings on the same pairs. The replaced estimate ran low here and its interval covered too little
    (see the test's run on the replaced code in the closing note of issue 47); now the mean error is within 0.02
    (Monte-Carlo sd about 0.007) and the coverage 0.93-0.99."""
    rng = np.random.default_rng(int(delta * 100))
    truth = float(special.ndtr(delta / math.sqrt(2 * (TUNING_SD**2 + SEED_SD**2 / STRATA.size))))
    err, hits = [], 0
    sims = 500
    for i in range(sims):
        d = replicated_difference(*_pair_data(rng, delta), STRATA, seed=i)
        err.append(d.p_a_beats_b - truth)
        lo, hi = d.p_a_beats_b_ci
        hits += lo <= truth <= hi
    assert abs(float(np.mean(err))) <= 0.02, (truth, np.mean(err))
    assert 0.93 <= hits / sims <= 0.99, hits / sims


def _pair_data(rng, shift):
    pairs = rng.normal(0.5, 0.25, STRATA.size)
    return _side(rng, pairs, 3, shift), _side(rng, pairs, 3)


def test_tune_prints_the_few_pairs_note_in_lines_of_at_most_100_columns():
    """The note of the tuned figure reaches the text `tune` prints, wrapped."""
    from tuner.replicates import replicated_text
    rng = np.random.default_rng(1)
    iv = replicated_maa_interval(np.clip(rng.normal(0.9, 0.05, (3, 8)), 0, 1), np.repeat([0, 1], 4))
    text = replicated_text({"replicates": [], "K": 3, "pairs": 8, "mAA10": iv.mean, "mAA10_ci": [iv.low, iv.high],
                            "se_pairs": iv.se_pairs, "se_between": iv.se_between, "tuning_variance_measured": True,
                            "figure_note": iv.note})
    flat = " ".join(text.split())
    assert "fewer than 10 test pairs in a scene" in flat and "test on more pairs" in flat
    note = text[text.index("note: fewer"):]
    assert max(len(line) for line in note.splitlines()) <= 100
