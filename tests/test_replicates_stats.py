"""The tuned figure and the tuned comparison (pipeline.metrics.replicates) on synthetic replicates x pairs data with
known variance components: coverage, false positives at .05 and .01, p-values that are the t test's at every level,
no verdict where a side has K = 1, the detectable difference against the power actually reached, P(A > B) with an
interval. The normal model here is the one the method assumes; benchmarks/verdict_calibration.py measures the same
functions on mAA scores from pose errors."""
import math

import numpy as np
import pytest
from scipy import stats

from pipeline.metrics.replicates import (
    components,
    detectable,
    p_a_beats_b,
    power,
    replicated_difference,
    replicated_interval,
    replicated_maa_interval,
)

STRATA = np.repeat([0, 1, 2], 10)


def _side(rng, pairs, k, tuning_sd, seed_sd, shift=0.0):
    """K x N scores: pair effects ``pairs`` (shared), a tuning effect per replicate, seed noise per cell."""
    return pairs[None, :] + shift + rng.normal(0, tuning_sd, (k, 1)) + rng.normal(0, seed_sd, (k, pairs.size))


def _null_p(k_a, k_b, n_scenes, per_scene, tuning_sd, seed_sd, sims, seed=0):
    rng = np.random.default_rng(seed)
    strata = np.repeat(np.arange(n_scenes), per_scene)
    ps, sig = [], []
    for _ in range(sims):
        pairs = rng.normal(0.5, 0.25, strata.size)
        a = _side(rng, pairs, k_a, tuning_sd, seed_sd)
        b = _side(rng, pairs, k_b, tuning_sd, seed_sd)
        d = replicated_difference(a, b, strata)
        ps.append(d.p_value)
        sig.append(d.significant)
    return np.array(ps), np.array(sig)


@pytest.mark.parametrize("tuning_sd", [0.0, 0.01, 0.04])
def test_false_positives_are_the_stated_rate_at_3_vs_3(tuning_sd):
    """Same method on both sides (the null), 30 pairs: p < .05 in 5% and p < .01 in 1% of data sets (binomial sd at
    1500 data sets: 0.0056 and 0.0026), or a little below where the replicate parts dominate (Welch's df over two
    parts of 2 df each, conservative when they are equal: 3.4-3.9% measured at a tuning sd of 0.04). The replaced
    method: 2-3% at .05, 3.1% at .01 with K = 2."""
    p, sig = _null_p(3, 3, 3, 10, tuning_sd, 0.08, 1500, seed=int(tuning_sd * 1000))
    assert 0.028 <= np.mean(p < 0.05) <= 0.065, np.mean(p < 0.05)
    assert np.mean(p < 0.01) <= 0.018, np.mean(p < 0.01)
    assert np.array_equal(sig, p < 0.05)


def test_few_test_pairs_do_not_inflate_false_positives():
    """8 pairs (4 in each of 2 scenes): the pair part rests on 6 df, not a million (the replaced method: 10.1%)."""
    p, _ = _null_p(3, 3, 2, 4, 0.01, 0.1, 1500, seed=3)
    assert 0.03 <= np.mean(p < 0.05) <= 0.07, np.mean(p < 0.05)


def test_null_p_values_are_uniform():
    """Not only at alpha: the KS distance of null p-values from uniform is Monte-Carlo small (a normal tail rescaled
    to match at alpha, as before, piles small p-values up)."""
    p, _ = _null_p(2, 3, 3, 10, 0.03, 0.08, 1200, seed=5)
    assert stats.kstest(p, "uniform").statistic < 0.06


def test_p_value_is_the_t_tests_at_its_df():
    rng = np.random.default_rng(2)
    pairs = rng.normal(0.5, 0.2, 30)
    a = _side(rng, pairs, 3, 0.05, 0.05, shift=0.1)
    b = _side(rng, pairs, 3, 0.05, 0.05)
    d = replicated_difference(a, b, STRATA)
    assert d.p_value == pytest.approx(2 * stats.t.sf(abs(d.diff) / d.se, d.df), rel=1e-9)
    half = stats.t.ppf(0.975, d.df) * d.se
    assert (d.low, d.high) == pytest.approx((d.diff - half, d.diff + half), rel=1e-9)
    assert (d.p_value < 0.05) == (d.low > 0 or d.high < 0)


def test_seed_noise_is_counted_once():
    """No tuning effect, only per-pair seed noise: the estimated variance of the difference matches the variance of
    the difference over data sets (the replaced method counted the seed noise in the pair bootstrap AND in the
    replicate spread: about twice this)."""
    rng = np.random.default_rng(4)
    diffs, var = [], []
    for _ in range(1500):
        pairs = rng.normal(0.5, 0.25, 30)
        d = replicated_difference(_side(rng, pairs, 3, 0.0, 0.1), _side(rng, pairs, 3, 0.0, 0.1), STRATA)
        diffs.append(d.diff)
        var.append(d.se**2)
    assert np.mean(var) == pytest.approx(np.var(diffs), rel=0.12)


@pytest.mark.parametrize("k,tuning_sd,low", [(2, 0.1, 0.90), (3, 0.02, 0.93), (3, 0.1, 0.93), (5, 0.05, 0.93)])
def test_mean_interval_covers_the_expected_tuned_figure(k, tuning_sd, low):
    """Coverage of the grand mean's 95% interval over pairs AND tunings. K = 2 with a large tuning sd rests on one
    df and covers a little less (0.926-0.938 here, 0.89-0.91 in the calibration benchmark): why K = 2 gives no
    verdict (MIN_VERDICT_K)."""
    rng = np.random.default_rng(k)
    hits = 0
    sims = 1000
    for _ in range(sims):
        pairs = rng.normal(0.5, 0.2, 30)
        iv = replicated_interval(_side(rng, pairs, k, tuning_sd, 0.05), STRATA)
        hits += iv.low <= 0.5 <= iv.high
    assert low <= hits / sims <= 0.97, hits / sims


def test_one_replicate_gets_no_verdict():
    """K = 1 against K = 3 of the same method with a large tuning sd: the replaced method said 'significant' 30% of
    the time. Here never; the verdict names what is missing, and the p it prints rests on a stated assumption whose
    error rate is the stated one."""
    rng = np.random.default_rng(6)
    p, verdicts = [], []
    for _ in range(600):
        pairs = rng.normal(0.5, 0.25, 30)
        d = replicated_difference(_side(rng, pairs, 1, 0.1, 0.05), _side(rng, pairs, 3, 0.1, 0.05), STRATA)
        p.append(d.p_value)
        verdicts.append(d.significant)
        assert not d.verdict_allowed
    assert not any(verdicts)
    assert np.mean(np.array(p) < 0.05) <= 0.075
    text = d.verdict()
    assert "significant" not in text and "no tuned verdict" in text and "--replicates 3" in text
    assert "A was tuned once" in text and "assuming" in text
    both = replicated_difference(_side(rng, pairs, 1, 0.1, 0.05), _side(rng, pairs, 1, 0.1, 0.05), STRATA)
    assert not both.significant and both.p_a_beats_b is None and "A and B were tuned once" in both.verdict()
    assert "over test pairs only" in both.verdict()
    assert not replicated_maa_interval(np.clip(pairs, 0, 1)[None, :], STRATA).tuning_variance_measured


def test_inconclusive_says_what_it_could_detect_and_power_there_is_80_percent():
    """The detectable difference (80% power at .05) of a null comparison, then data sets at that true difference:
    about 80% of them reject."""
    rng = np.random.default_rng(7)
    pairs = rng.normal(0.5, 0.25, 30)
    d0 = replicated_difference(_side(rng, pairs, 3, 0.02, 0.08), _side(rng, pairs, 3, 0.02, 0.08), STRATA)
    if d0.significant:
        pytest.skip("this seed's null data set came out significant")
    text = d0.verdict()
    assert "inconclusive: could detect |A - B| >= " in text and "test pairs would detect 0.05" in text
    # the true se of this design, and the mde at the true se and typical df
    mdes, rejected = [], []
    for _ in range(800):
        pairs = rng.normal(0.5, 0.25, 30)
        d = replicated_difference(_side(rng, pairs, 3, 0.02, 0.08), _side(rng, pairs, 3, 0.02, 0.08), STRATA)
        mdes.append(d.mde)
    target = float(np.median(mdes))
    for _ in range(800):
        pairs = rng.normal(0.5, 0.25, 30)
        d = replicated_difference(_side(rng, pairs, 3, 0.02, 0.08, shift=target), _side(rng, pairs, 3, 0.02, 0.08),
                                  STRATA)
        rejected.append(d.significant and d.diff > 0)
    assert 0.68 <= np.mean(rejected) <= 0.92, (target, np.mean(rejected))


def test_power_and_detectable_agree_with_scipy():
    assert power(detectable(1.0, 4.0, 0.05), 4.0, 0.05) == pytest.approx(0.8, abs=1e-3)
    assert power(0.0, 10.0, 0.05) == pytest.approx(0.05, abs=1e-9)
    nc = 3.0
    q = stats.t.ppf(0.975, 7)
    assert power(nc, 7, 0.05) == pytest.approx(stats.nct.sf(q, 7, nc) + stats.nct.cdf(-q, 7, nc), rel=1e-6)
    assert detectable(1.0, math.inf, 0.05) == pytest.approx(stats.norm.ppf(0.975) + stats.norm.ppf(0.8), rel=1e-3)


def test_p_a_beats_b_has_an_interval_that_covers_one_half_under_the_null():
    rng = np.random.default_rng(8)
    inside = 0
    for _ in range(300):
        pairs = rng.normal(0.5, 0.25, 30)
        d = replicated_difference(_side(rng, pairs, 3, 0.05, 0.05), _side(rng, pairs, 3, 0.05, 0.05), STRATA)
        lo, hi = d.p_a_beats_b_ci
        assert 0 <= lo <= d.p_a_beats_b <= hi <= 1
        inside += lo <= 0.5 <= hi
    assert inside / 300 >= 0.9
    far = replicated_difference(_side(rng, pairs, 3, 0.01, 0.02, shift=0.3), _side(rng, pairs, 3, 0.01, 0.02), STRATA)
    assert far.p_a_beats_b > 0.99 and far.p_a_beats_b_ci[0] > 0.9


def test_components_known_case():
    """Two replicates x three pairs by hand: row means 2 and 3 (s^2 = 0.5); residuals +-0.5, +-0.5, 0 ->
    MS_res = (4 x 0.25) / ((2 - 1)(3 - 1)) = 0.5."""
    c = components(np.array([[1.0, 2.0, 3.0], [3.0, 3.0, 3.0]]))
    assert c.row_var == pytest.approx(0.5)
    assert c.ms_res == pytest.approx(0.5)
    assert c.tuning_var == pytest.approx(0.5 - 0.5 / 3)


def test_empirical_p_a_beats_b_known_case():
    assert p_a_beats_b([1, 2, 3], [0, 0, 0]) == 1.0
    assert p_a_beats_b([1, 2, 3], [2, 2, 2]) == (0 + 1.5 + 3) / 9


def test_degrees_of_freedom_by_hand():
    """A 3 vs 3 comparison: the plug-in Welch-Satterthwaite df over the two replicate parts (s_A^2 / 3 and s_B^2 / 3
    on 2 df each) and the pair-effect part (the stratified variance of the per-pair differences minus the
    interaction mean squares / (K N), on its strata's df). A figure of one side: the same with its replicate part at
    the upper 60% limit of a chi-square with 2 df (its df are lower)."""
    rng = np.random.default_rng(21)
    pairs = rng.normal(0.5, 0.25, 30)
    a, b = _side(rng, pairs, 3, 0.03, 0.08), _side(rng, pairs, 3, 0.03, 0.08, shift=0.02)
    d = replicated_difference(a, b, STRATA)
    ca, cb = components(a), components(b)
    per = a.mean(axis=0) - b.mean(axis=0)
    groups = [per[STRATA == s] for s in range(3)]
    vp_terms = [10 * g.var(ddof=1) / 30**2 for g in groups]
    vp = sum(vp_terms)
    dfp = vp**2 / sum(t * t / 9 for t in vp_terms)
    pe = vp - (ca.ms_res + cb.ms_res) / (3 * 30)
    terms = [(ca.row_var / 3, 2), (cb.row_var / 3, 2), (max(pe, 0.0), dfp)]
    var = sum(v for v, _ in terms) if pe >= 0 else max(sum(v for v, _ in terms) + pe, 0.5 * sum(v for v, _ in terms))
    df = sum(v for v, _ in terms) ** 2 / sum(v * v / f for v, f in terms if v > 0)
    assert d.se == pytest.approx(math.sqrt(var), rel=1e-9)
    assert d.df == pytest.approx(df, rel=1e-9)
    # the figure of A: its replicate part enters the df at s^2 * 2 / chi2_2(0.40) (upper 60% limit)
    iv = replicated_interval(a, STRATA)
    vpa_terms = [10 * a.mean(axis=0)[STRATA == s].var(ddof=1) / 30**2 for s in range(3)]
    vpa = sum(vpa_terms)
    dfpa = vpa**2 / sum(t * t / 9 for t in vpa_terms)
    pea = max(vpa - ca.ms_res / (3 * 30), 0.0)
    up = ca.row_var / 3 * 2 / stats.chi2.ppf(0.40, 2)
    assert iv.df == pytest.approx((up + pea) ** 2 / (up**2 / 2 + pea**2 / dfpa), rel=1e-9)
