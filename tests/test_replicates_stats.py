"""Two-level interval on synthetic replicate x pair data with known variance components."""
import numpy as np

from pipeline.metrics.replicates import NOT_MEASURED, p_a_beats_b, replicated_difference, replicated_interval


def _coverage(s_r: float, k: int, n_sims: int = 150) -> tuple[float, float]:
    rng = np.random.default_rng(1)
    hits, widths = 0, []
    strata = np.repeat([0, 1, 2], 10)
    for _ in range(n_sims):
        scores = 0.5 + rng.normal(0, s_r, (k, 1)) + rng.normal(0, 0.1, (1, 30)) + rng.normal(0, 0.02, (k, 30))
        iv = replicated_interval(scores, strata, n_boot=200, seed=int(rng.integers(1 << 30)))
        hits += iv.low <= 0.5 <= iv.high
        widths.append(iv.high - iv.low)
    return hits / n_sims, float(np.mean(widths))


def test_coverage_near_nominal_and_widens_with_tuning_variance():
    cov_small, w_small = _coverage(0.005, 3)
    cov_big, w_big = _coverage(0.05, 3)
    assert 0.86 <= cov_small <= 0.995
    assert 0.86 <= cov_big <= 0.995
    assert w_big > 1.5 * w_small


def test_p_a_beats_b_known_case():
    assert p_a_beats_b([1, 2, 3], [0, 0, 0]) == 1.0
    assert p_a_beats_b([1, 2, 3], [2, 2, 2]) == (0 + 1.5 + 3) / 9


def test_single_replicate_says_tuning_variance_not_measured():
    rng = np.random.default_rng(0)
    a = rng.normal(0.5, 0.1, (1, 20))
    d = replicated_difference(a, a - 0.01, n_boot=100)
    assert not d.tuning_variance_measured and d.p_a_beats_b is None
    assert NOT_MEASURED in d.verdict()
    assert not replicated_interval(a, n_boot=100).tuning_variance_measured
