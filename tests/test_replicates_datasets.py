"""Replicated studies of a task measured on datasets (reconstruction): `tuner.replicates.dataset_replicated_summary`.

Known truth: the replicates' figures and their references are drawn from normal distributions of known means, so the
interval's coverage, the test's false-positive rate and the power at the printed "could detect" figure are measured
against the truth (2,000 simulated studies each; Monte-Carlo sd about 0.005 on a coverage of 0.95, 0.009 on a power
of 0.8). One case is recomputed by hand from the formulas."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.errors import ImtuneError
from tuner.replicates import dataset_replicated_summary, replicated_text


def _test(study: str, runs: list[float], ref_runs: list[float] | None, ds: str = "d1") -> dict:
    def block(xs):
        return {"runs": [{"scenes": {ds: {"score": x}}} for x in xs], "mean": {"score": float(np.mean(xs))}}
    t = {"study": study, "trial": 0, "params": {"ratio": 0.85}, "objective": {"name": "score"},
         "data": {"scenes": [ds]}, **block(runs)}
    if ref_runs is not None:
        t["reference"] = {"label": "COLMAP", "objective": "score", **block(ref_runs)}
    return t


def test_by_hand():
    tests = [_test("s", [0.50, 0.60], [0.40, 0.40]), _test("s-r2", [0.70, 0.70], [0.45, 0.35]),
             _test("s-r3", [0.40, 0.50], [0.30, 0.40])]
    out = dataset_replicated_summary(tests, [0, 1, 2])
    y = np.array([0.55, 0.70, 0.45])
    d = y - np.array([0.40, 0.40, 0.35])  # 0.15, 0.30, 0.10
    t975 = 4.302652729749464  # Student t, 2 df, 0.975 (tables)
    assert out["score"] == pytest.approx(y.mean())
    half = t975 * y.std(ddof=1) / math.sqrt(3)
    assert out["score_ci"] == pytest.approx([y.mean() - half, y.mean() + half])
    ref = out["reference"]
    assert ref["difference"] == pytest.approx(d.mean())
    se = d.std(ddof=1) / math.sqrt(3)
    assert ref["ci"] == pytest.approx([d.mean() - t975 * se, d.mean() + t975 * se])
    tstat = d.mean() / se  # 0.18333 / 0.060093 = 3.0509: p between 0.05 and 0.1 on 2 df
    assert 0.05 < ref["p_value"] < 0.1 and ref["df"] == 2 and tstat == pytest.approx(3.0509, abs=1e-3)
    assert ref["verdict"].startswith("inconclusive: could detect")
    assert ref["datasets"] == {"d1": pytest.approx(d.mean())}
    text = replicated_text(out)
    assert "replicated test score over 3 replicates" in text and "frozen - reference (COLMAP" in text
    assert all(len(line) <= 100 for line in text.splitlines())


def test_two_replicates_give_no_verdict_and_one_says_unmeasured():
    two = dataset_replicated_summary([_test("s", [0.5], [0.1]), _test("s-r2", [0.6], [0.1])], [0, 1])
    assert two["reference"]["verdict"].startswith("K = 2: no verdict")
    one = dataset_replicated_summary([_test("s", [0.5, 0.6], [0.1, 0.2])], [0])
    assert one["score_ci"] is None and not one["tuning_variance_measured"]
    assert "rerun with --replicates 3" in replicated_text(one)


def test_replicates_on_different_datasets_are_refused():
    with pytest.raises(ImtuneError, match="different datasets"):
        dataset_replicated_summary([_test("s", [0.5], [0.1], "a"), _test("s-r2", [0.6], [0.1], "b")], [0, 1])


def _simulate(rng, k: int, delta: float, sd_y: float = 0.08, sd_r: float = 0.03, mu_r: float = 0.36):
    """K replicates: each a tuned figure ~ N(mu_r + delta, sd_y) (tuning and run noise) and its reference
    ~ N(mu_r, sd_r) (run noise)."""
    y = rng.normal(mu_r + delta, sd_y, k)
    r = rng.normal(mu_r, sd_r, k)
    tests = [_test(f"s{i}", [float(a)], [float(b)]) for i, (a, b) in enumerate(zip(y, r))]
    return dataset_replicated_summary(tests, list(range(k)))


@pytest.mark.parametrize("k", [3, 5])
def test_coverage_and_false_positives_under_known_truth(k):
    rng = np.random.default_rng(44 + k)
    n, cover_y, cover_d, fp = 2000, 0, 0, 0
    for _ in range(n):
        out = _simulate(rng, k, 0.0)
        lo, hi = out["score_ci"]
        cover_y += lo <= 0.36 <= hi
        ref = out["reference"]
        cover_d += ref["ci"][0] <= 0.0 <= ref["ci"][1]
        fp += ref["verdict"].startswith("significant")
    assert 0.93 <= cover_y / n <= 0.97
    assert 0.93 <= cover_d / n <= 0.97
    assert 0.03 <= fp / n <= 0.07


def test_power_at_the_median_detectable_difference_is_about_80_percent():
    """The "could detect" figure of null studies (median over them), then the rejection rate when the truth is it."""
    rng = np.random.default_rng(7)
    mdes = [_simulate(rng, 3, 0.0)["reference"]["detectable"] for _ in range(400)]
    m = float(np.median(mdes))
    hits = sum(_simulate(rng, 3, m)["reference"]["verdict"].startswith("significant") for _ in range(2000))
    assert 0.75 <= hits / 2000 <= 0.85
