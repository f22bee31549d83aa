"""benchmarks/verdict_calibration.py keeps running, and its target check flags what it should (the figures
themselves are the benchmark's, documented on the statistics page; a few data sets here only exercise the code)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "verdict_calibration.py"


def _bench():
    spec = importlib.util.spec_from_file_location("verdict_calibration", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_a_cell_runs_both_methods_on_the_same_data_sets():
    m = _bench()
    cal = {"tau": 0.05, "pairs": {8: {"mu_a": 0.5, "mu_a_high": 0.9, "shifts": {0.0: 0.0, 0.05: 0.1, 0.1: 0.2},
                                      "sigma1_a": 0.004, "sigma1_b": {0.0: 0.004, 0.05: 0.005, 0.1: 0.006}}},
           "mu_332": {"benchmark": 0.5, "high": 0.9}}
    rows = m.run_cell((3, 1, 8, "small", cal, 15, 0, 200))
    assert [r["method"] for r in rows] == ["new", "old"]
    new = rows[0]
    assert new["claim"] == "assumption" and new["verdicts05"] == 0.0  # a side with K = 1: never a verdict
    for r in rows:
        for k in ("coverage_mean", "coverage_diff", "fp05", "fp01", "ks", "power05", "power10"):
            assert 0.0 <= r[k] <= 1.0, (k, r)
        assert r["fp01"] <= r["fp05"]
    verdict = m.run_cell((3, 3, 8, "small", cal, 15, 1, 200))[0]
    assert verdict["claim"] == "verdict"
    for k in ("power_at_mde", "coverage_pab", "coverage_mean_332", "coverage_mean_high", "coverage_mean_332_high",
              "predicted_power05"):
        assert 0.0 <= verdict[k] <= 1.0, (k, verdict[k])
    assert verdict["mde_median"] > 0


def test_scores_are_the_benchmarks_per_pair_maa():
    import numpy as np
    m = _bench()
    log_err = np.log10(np.array([0.5, 1.0, 1.5, 9.99, 10.0, 10.5, 200.0]))
    # thresholds 1..10 deg within reach: 10, 10, 9, 1, 1, 0, 0
    assert m.scores_of(log_err).tolist() == [1.0, 1.0, 0.9, 0.1, 0.1, 0.0, 0.0]


def test_the_target_check_flags_a_cell_outside_and_passes_one_inside():
    m = _bench()
    base = {"k_a": 3, "k_b": 3, "pairs": 30, "tuning_sd": "small", "claim": "verdict", "coverage_mean": 0.95,
            "coverage_diff": 0.95, "fp05": 0.05, "fp01": 0.01, "power05": 0.3, "power10": 0.8}
    good = [{**base, "method": "new"}, {**base, "method": "old", "fp05": 0.02}]
    assert m.check(good, 2000) == ([], [])
    bad = [{**base, "method": "new", "fp05": 0.12, "coverage_diff": 0.85}, {**base, "method": "old"}]
    flagged, _ = m.check(bad, 2000)
    assert len(flagged) == 1 and "fp05 0.120" in flagged[0] and "coverage_diff 0.850" in flagged[0]
    weaker = [{**base, "method": "new", "power05": 0.1}, {**base, "method": "old", "fp05": 0.05}]
    assert "power05 0.100 < old 0.300" in m.check(weaker, 2000)[0][0]
    # the promises of a verdict cell: power at the median mde, P(A > B) coverage, the 3 + 3 + 2 figure
    kept = {**base, "method": "new", "power_at_mde": 0.81, "coverage_pab": 0.95, "coverage_mean_332": 0.94}
    assert m.check([kept, {**base, "method": "old", "fp05": 0.02}], 400) == ([], [])
    broken = {**kept, "power_at_mde": 0.70, "coverage_pab": 0.89, "coverage_mean_332": 0.88}
    line = m.check([broken, {**base, "method": "old", "fp05": 0.02}], 400)[0][0]
    assert "power_at_mde 0.700" in line and "coverage_pab 0.890" in line and "coverage_mean_332 0.880" in line


def test_the_truth_is_the_expected_score_of_the_simulated_world():
    """The benchmark's truth (exact, a sum of normal cdfs) against a brute-force average of the very draws the cells
    make: a truth off by 0.01 would move every coverage and power column of the benchmark."""
    import numpy as np
    m = _bench()
    rng = np.random.default_rng(3)
    tau, shift, reps, n = 0.1, 0.08, 6000, 50
    for with_v in (False, True):
        # each simulated side: one tuning draw, fresh pairs in every scene; its figure the mean over scenes
        figs = [np.mean([m.draw_side(rng, rng.normal(ms, m.PAIR_SD, n), 1, tau, shift,
                                     rng.normal(0, m.METHOD_PAIR_SD, n) if with_v else None).mean()
                         for ms in m.scene_means(3)]) for _ in range(reps)]
        mc, se = float(np.mean(figs)), float(np.std(figs, ddof=1) / np.sqrt(reps))
        assert abs(mc - m.expected(tau, shift, 3, with_v)) < 4 * se, (with_v, mc, se, m.expected(tau, shift, 3, with_v))
    # the tuning sd of the figure: quadrature against 4000 simulated tunings on many pairs
    t = rng.normal(0, tau, 4000)
    sd_in = float(np.sqrt(m.PAIR_SD**2 + (tau / 2) ** 2 + m.SEED_SD**2))
    figures = np.mean([m.expected_score(ms + t, sd_in) for ms in m.scene_means(3)], axis=0)
    assert abs(figures.std(ddof=1) - m.tuning_sd_of(tau)) < 0.05 * m.tuning_sd_of(tau)


def test_the_ideal_bootstrap_of_the_replaced_difference_is_its_limit():
    """``n_boot`` 0 gives the replaced method's pair SD without resampling: 20000 resamples agree within 2%."""
    import numpy as np
    m = _bench()
    rng = np.random.default_rng(11)
    strata = np.repeat([0, 1, 2], [3, 5, 8])
    a, b = rng.normal(0.5, 0.2, (3, 16)), rng.normal(0.45, 0.2, (3, 16))
    exact = m.legacy_difference(a, b, strata, rng, n_boot=0)
    drawn = m.legacy_difference(a, b, strata, rng, n_boot=20000)
    assert exact[0] == drawn[0]
    assert abs(exact[1] / drawn[1] - 1) < 0.02, (exact, drawn)


def test_the_docs_sections_hold_each_verdict_cells_power_and_the_figure_ranges():
    m = _bench()
    cells = []
    for ka, kb, n, pw in ((3, 3, 8, 0.812), (3, 5, 8, 0.774), (5, 5, 30, 0.801), (1, 3, 8, None)):
        claim = "verdict" if min(ka, kb) >= 3 else "assumption"
        cells.append({"k_a": ka, "k_b": kb, "pairs": n, "tuning_sd": "small", "method": "new", "claim": claim,
                      "power_at_mde": pw, "mde_median": 0.2, "coverage_mean": 0.95 if ka == 3 else 0.9,
                      "coverage_mean_332": 0.96, "coverage_mean_high": 0.93, "coverage_mean_332_high": 0.92})
        cells.append({**cells[-1], "method": "old"})
    text = m.sections({"sims": 400, "cells": cells})
    assert "| 8 | small | 0.81 (0.200) | 0.77 (0.200) | - |" in text
    assert "| 30 | small | - | - | 0.80 (0.200) |" in text
    assert "Over the 3 verdict cells: 0.774-0.812." in text
    assert "| 3 | 0.950 | 0.960 | 0.930 | 0.920 | - | - |" in text
    assert text.count("[start:") == text.count("[end:") == 4
    assert "| false positives at .05 | - | 0.035-0.065 |" in text  # no fp05 in these cells: no range invented
    assert "| power at the median \"could detect\" figure | 0.774-0.812 | 0.78-0.85 |" in text
