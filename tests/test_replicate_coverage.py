"""The simulation of benchmarks/replicate_coverage.py, small: the replicated interval of a tuned difference covers
the known expected-tuned-performance difference near its nominal 95%, the single-study (pairs-only) one clearly less
(issue 32). Loose bands: 60 comparisons, binomial sd 0.03."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "replicate_coverage.py"


def _bench():
    spec = importlib.util.spec_from_file_location("replicate_coverage", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_replicated_interval_covers_tuned_difference_single_does_not():
    m = _bench()
    r = m.coverage(m.Surface(), sims=60, k=3, sampler="random", seed=1, n_boot=400, truth_tunings=5000)
    assert r["tuning_sd_a"] > 0.01 and r["tuning_sd_b"] > 0.01  # tuning noise exists in this problem
    assert 0.85 <= r["coverage_replicated"] <= 1.0, r
    assert r["coverage_single"] <= 0.88, r  # pair sampling alone misses the tuning variance
    assert r["coverage_replicated"] - r["coverage_single"] >= 0.08, r
