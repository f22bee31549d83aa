"""Pose AUC@5/10/20 (pipeline.metrics.auc) against values computed by hand from the SuperGlue / glue-factory
definition: sorted errors, recall (1..n)/n, the point (0, 0) prepended, trapezoid up to the threshold, / threshold."""
import math

import numpy as np
import pytest

from pipeline.metrics.auc import auc_intervals, auc_summary, pose_auc
from pipeline.tasks.stereo import combine, summarize


def test_all_zero_errors_give_one():
    assert pose_auc([0.0, 0.0, 0.0]) == [1.0, 1.0, 1.0]


def test_all_failed_give_zero():
    assert pose_auc([math.inf] * 4) == [0.0, 0.0, 0.0]
    assert pose_auc([float("nan")] * 2) == [0.0, 0.0, 0.0]
    assert pose_auc([]) == [0.0, 0.0, 0.0]


def test_known_steps_by_hand():
    # errors 1 and 3 deg: curve (0,0) -> (1,.5) -> (3,1), flat to t.
    # t=5: 0.5*1*0.5 + 2*(0.5+1)/2 + 2*1 = 0.25 + 1.5 + 2 = 3.75 -> 0.75
    # t=10: 0.25 + 1.5 + 7 = 8.75 -> 0.875;  t=20: 0.25 + 1.5 + 17 = 18.75 -> 0.9375
    assert pose_auc([3.0, 1.0]) == pytest.approx([0.75, 0.875, 0.9375], abs=1e-12)


def test_failed_pairs_count_and_threshold_cuts_segment():
    # errors 2, 8, inf: curve (0,0) -> (2,1/3) -> (8,2/3) -> (inf,1).
    # t=5: segment to 8 does not end below 5, so flat at 1/3 from 2 to 5: 2*(1/3)/2 + 3*(1/3) = 1/3 + 1 = 4/3 -> 4/15
    # t=10: 1/3 + 6*(1/3+2/3)/2 + 2*(2/3) = 1/3 + 3 + 4/3 = 14/3 -> 14/30
    # t=20: 1/3 + 3 + 12*(2/3) = 1/3 + 3 + 8 = 34/3 -> 34/60
    assert pose_auc([8.0, math.inf, 2.0]) == pytest.approx([4 / 15, 14 / 30, 34 / 60], abs=1e-12)


def test_intervals_hold_the_estimate_and_are_seeded():
    recs = ([{"scene": "a", "err": e} for e in (1.0, 2.0, 3.0, math.inf, 7.0, 12.0)]
            + [{"scene": "b", "err": e} for e in (0.5, 4.0, 30.0)])
    ci = auc_intervals(recs, n_resamples=400)
    pa, pb = pose_auc([1.0, 2.0, 3.0, math.inf, 7.0, 12.0]), pose_auc([0.5, 4.0, 30.0])
    for i, t in enumerate((5, 10, 20)):
        lo, hi = ci[f"auc{t}_ci"]
        assert 0.0 <= lo < (pa[i] + pb[i]) / 2 < hi <= 1.0
        lo, hi = ci["scenes"]["a"][f"auc{t}_ci"]
        assert lo < pa[i] < hi
    assert auc_intervals(recs, n_resamples=400) == ci


def test_constant_perfect_scene_interval_is_not_degenerate():
    # the pseudo-pairs (one perfect, one failed) widen an all-perfect scene's interval below 1 (as for mAA)
    ci = auc_intervals([{"scene": "a", "err": 0.0} for _ in range(10)], n_resamples=400)
    lo, hi = ci["auc10_ci"]
    assert hi == 1.0 and lo < 1.0


def test_stereo_summary_carries_auc_mean_over_scenes():
    def rec(scene, e):
        return {"scene": scene, "err": e, "NM": 1, "NI": 1, "ransac_seconds": 0.0, "match_seconds": 0.0}
    a = [rec("a", 0.0), rec("a", 0.0)]
    b = [rec("b", 3.0), rec("b", 1.0)]
    per = {"a": summarize(a, 1.0), "b": summarize(b, 1.0)}
    assert per["b"]["auc5"] == pytest.approx(0.75)
    overall = combine(per, a + b)
    assert overall["auc5"] == pytest.approx((1.0 + 0.75) / 2)
    assert overall["auc20"] == pytest.approx((1.0 + 0.9375) / 2)
    assert auc_summary([0.0]) == {"auc5": 1.0, "auc10": 1.0, "auc20": 1.0}
    assert np.isfinite(overall["mAA10"])
