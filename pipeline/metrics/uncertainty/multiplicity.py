"""Several comparisons held at one level together: Holm-adjusted p-values, Bonferroni levels."""
from __future__ import annotations

import math
from collections.abc import Sequence

from pipeline.metrics.uncertainty.scores import DEFAULT_RESAMPLES

# ------------------------------------------------------------------------------------------ ranking

def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (Holm 1979), in the given order: sorted ascending, the i-th of m (from 0)
    is ``max over j <= i of min(1, (m - j) p_(j))``; reject where the adjusted p < alpha, which holds the family-wise
    error rate at alpha for any dependence between the tests. Hand-written: scipy has no Holm
    (``scipy.stats.false_discovery_control`` is Benjamini-Hochberg's FDR) and statsmodels is not a dependency."""
    p = [float(x) for x in p_values]
    m = len(p)
    out = [1.0] * m
    running = 0.0
    for rank, i in enumerate(sorted(range(m), key=lambda j: p[j])):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out



def bonferroni(level: float, m: int, n_resamples: int = DEFAULT_RESAMPLES) -> tuple[float, float, int]:
    """(level_each, alpha_each, resamples_each) of m comparisons made together at family level ``level``: each at
    alpha / m (Bonferroni), with at least 20 / alpha_each bootstrap and sign-flip resamples (at most 100,000) so
    that a p-value can reach alpha_each and the interval's tails rest on enough resamples. m <= 1: unchanged."""
    m = max(1, int(m))
    alpha = (1.0 - level) / m
    return 1.0 - alpha, alpha, int(min(100_000, max(int(n_resamples), math.ceil(20.0 / alpha))))
