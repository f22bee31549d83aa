"""tuner.select on synthetic studies whose answer is known by construction: the selection rules (best, one-se,
smooth), the flat region of the optimum, frozen files made with a rule, the reference configuration, and the
test-run interval / reference comparison helpers. Real Optuna studies (in-memory storage), no mocks."""
import math

import optuna
import pytest

from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError
from tuner import select as sel
from tuner.freeze import frozen_from_study

optuna.logging.set_verbosity(optuna.logging.ERROR)

SPACE = {"params": {"threshold": {"type": "float", "low": 0.1, "high": 2.0, "log": True},
                    "ratio": {"type": "float", "low": 0.6, "high": 1.0, "log": False},
                    "max_iters": {"type": "int", "low": 1000, "high": 100000, "log": True}},
         "fixed": {}}
DISTS = {"threshold": optuna.distributions.FloatDistribution(0.1, 2.0, log=True),
         "ratio": optuna.distributions.FloatDistribution(0.6, 1.0),
         "max_iters": optuna.distributions.IntDistribution(1000, 100000, log=True)}


def at(a: float, b: float, c: float) -> dict:
    """Parameters at normalised coordinates (a, b, c) of (log eta, r, log Gamma)."""
    lg = math.log
    return {"threshold": math.exp(lg(0.1) + a * (lg(2.0) - lg(0.1))), "ratio": 0.6 + 0.4 * b,
            "max_iters": int(round(math.exp(lg(1000) + c * (lg(100000) - lg(1000)))))}


def make_study(trials) -> optuna.Study:
    """trials: [(coords, value, ci or None, feasible)]"""
    st = optuna.create_study(direction="maximize")
    st.set_user_attr("imtune", 1)
    st.set_user_attr("task", "stereo")
    st.set_user_attr("search_space_resolved", SPACE)
    st.set_user_attr("search_space", SPACE)
    st.set_user_attr("pipeline", PipelineConfig().to_dict())
    st.set_user_attr("budget", {"seconds_per_pair": 0.5, "gamma_max": 100000})
    st.set_user_attr("seed", 0)
    for coords, value, ci, feasible in trials:
        ua = {"feasible": feasible, "mAA10": value, "ransac_seconds_median": 0.1}
        if ci is not None:
            ua["mAA10_ci"] = list(ci)
        st.add_trial(optuna.trial.create_trial(params=at(*coords), distributions=DISTS, value=value, user_attrs=ua))
    return st


# the best (0.80 [0.70, 0.90]: SE = half-width 0.1 / 1.96 = 0.051) at an edge of a plateau centred on (0.5, 0.5, 0.5)
PLATEAU = [((0.9, 0.5, 0.5), 0.80, (0.70, 0.90), True),   # 0: best
           ((0.1, 0.5, 0.5), 0.76, (0.66, 0.86), True),   # 1
           ((0.5, 0.5, 0.5), 0.75, (0.65, 0.85), True),   # 2: the plateau's centre
           ((0.5, 0.9, 0.5), 0.77, (0.67, 0.87), True),   # 3
           ((0.5, 0.1, 0.5), 0.755, (0.65, 0.85), True),  # 4
           ((0.49, 0.5, 0.5), 0.745, (0.64, 0.84), True),  # 5: 0.055 below the best: more than one SE
           ((0.52, 0.5, 0.52), 0.60, (0.5, 0.7), True),   # 6: near the centre but far below
           ((0.5, 0.5, 0.5), 0.95, (0.9, 1.0), False)]    # 7: over budget: never frozen


def test_best_is_the_highest_feasible():
    st = make_study(PLATEAU)
    t, info = sel.select_trial(st, "best")
    assert t.number == 0 and info["rule"] == "best" and info["best_trial"] == 0


def test_one_se_picks_the_centre_of_the_trials_within_one_se():
    st = make_study(PLATEAU)
    t, info = sel.select_trial(st, "one-se")
    assert info["se"] == pytest.approx(0.1 / 1.959963984540054)  # half-width 0.1
    assert info["within_one_se"] == [0, 1, 2, 3, 4]  # 5 is 0.055 > 1 SE below; 7 is infeasible
    assert t.number == 2


def test_lower_bound_picks_the_highest_lower_end():
    # the best (0.80 [0.55, 0.95]) is lucky: few pairs carry it, a wide interval; trial 1 is lower (0.78) but good on
    # most pairs (0.78 [0.72, 0.84]): its lower end 0.72 is the highest of the feasible trials; 3 (0.99 [0.98, 1.0])
    # is over budget and never frozen
    st = make_study([((0.9, 0.5, 0.5), 0.80, (0.55, 0.95), True),   # 0: best value
                     ((0.1, 0.5, 0.5), 0.78, (0.72, 0.84), True),   # 1: highest lower end
                     ((0.5, 0.5, 0.5), 0.76, (0.70, 0.82), True),   # 2
                     ((0.5, 0.9, 0.5), 0.99, (0.98, 1.00), False)])  # 3: over budget
    t, info = sel.select_trial(st, "lower-bound")
    assert t.number == 1 and info["best_trial"] == 0 and info["lower_bound"] == pytest.approx(0.72)
    assert "lower end" in info["note"]
    # a tie of lower ends: the higher value wins
    st = make_study([((0.9, 0.5, 0.5), 0.70, (0.60, 0.80), True), ((0.1, 0.5, 0.5), 0.75, (0.60, 0.90), True)])
    assert sel.select_trial(st, "lower-bound")[0].number == 1
    # no interval stored (an older imtune's trials): the value stands for the lower end, i.e. the best trial
    st = make_study([(c, v, None, f) for c, v, _, f in PLATEAU])
    assert sel.select_trial(st, "lower-bound")[0].number == 0


def test_one_se_without_an_interval_falls_back_to_the_best():
    st = make_study([(c, v, None, f) for c, v, _, f in PLATEAU])
    t, info = sel.select_trial(st, "one-se")
    assert t.number == 0 and "no interval" in info["note"]


def test_smooth_prefers_a_good_neighbourhood_to_a_lucky_spike():
    spike = [((0.9, 0.9, 0.9), 0.90, (0.8, 1.0), True)]
    around_spike = [((0.9 + d1, 0.9 + d2, 0.9), 0.10, (0.0, 0.2), True)
                    for d1, d2 in ((0.02, 0), (-0.02, 0), (0, 0.02), (0, -0.02), (0.02, 0.02))]
    cluster = [((0.2 + d, 0.2, 0.2 + d), v, (v - 0.1, v + 0.1), True)
               for d, v in ((0.0, 0.70), (0.02, 0.72), (-0.02, 0.70), (0.04, 0.69), (-0.04, 0.70), (0.01, 0.71))]
    st = make_study(spike + around_spike + cluster)
    assert sel.select_trial(st, "best")[0].number == 0
    t, info = sel.select_trial(st, "smooth")
    assert t.number == 1 + 5 + 1  # the 0.72 member of the cluster
    assert info["k"] == 5
    # its smoothed value: itself and its 5 nearest (the rest of the cluster)
    assert info["smoothed_value"] == pytest.approx((0.70 + 0.72 + 0.70 + 0.69 + 0.70 + 0.71) / 6)


def test_unknown_rule_is_a_one_line_error():
    with pytest.raises(ImtuneError, match="unknown selection rule 'median'"):
        sel.check_rule("median")


def test_flat_region_spans_the_trials_within_the_optimum_interval():
    st = make_study(PLATEAU)
    best = sel.select_trial(st, "best")[0]
    flat = sel.flat_region(st, best)
    # CI of the best [0.70, 0.90]: trials 0-5 (0.745 >= 0.70), not 6 (0.60) nor the infeasible 7
    assert flat["trials"] == 6 and flat["of"] == 7
    eta = flat["params"]["threshold"]
    assert eta["min"] == pytest.approx(at(0.1, 0, 0)["threshold"]) and eta["max"] == pytest.approx(at(0.9, 0, 0)["threshold"])
    assert eta["share_of_range"] == pytest.approx(0.8, abs=1e-3)
    assert flat["params"]["ratio"]["share_of_range"] == pytest.approx(0.8, abs=1e-3)
    assert "6 of 7" in sel.flat_text(flat)


def test_frozen_from_study_uses_the_rule_and_records_it():
    st = make_study(PLATEAU)
    f = frozen_from_study(st, "one-se")
    assert f["trial"] == 2 and f["selection"]["rule"] == "one-se"
    assert f["config"]["geometry"]["threshold"] == pytest.approx(at(0.5, 0.5, 0.5)["threshold"])
    assert f["validation"]["mAA10_ci"] == [0.65, 0.85]
    assert f["robustness"]["trials"] == 6  # flatness is about the optimum (the best), whatever the rule
    assert frozen_from_study(st, "best")["trial"] == 0
    st.set_user_attr("select", "one-se")  # a rule recorded in the study is the default of later freezes
    assert frozen_from_study(st)["trial"] == 2


def test_frozen_optimum_on_a_bound_warns_with_a_wider_range():
    st = make_study([((0.0, 0.5, 0.5), 0.8, (0.7, 0.9), True), ((0.5, 0.5, 0.5), 0.6, (0.5, 0.7), True)])
    f = frozen_from_study(st, "best")
    assert any("lower bound" in w and "0.05" in w for w in f["warnings"]), f["warnings"]


def test_every_trial_zero_warns():
    st = make_study([((0.5, 0.5, 0.5), 0.0, (0.0, 0.0), True), ((0.2, 0.5, 0.5), 0.0, (0.0, 0.0), True)])
    f = frozen_from_study(st, "best")
    assert any("0" in w and "every" in w for w in f["warnings"]), f["warnings"]


def test_reference_is_the_paper_defaults_with_the_study_feature_and_estimator():
    frozen = {"task": "stereo", "config": {"feature": {"name": "orb", "num_features": 2000},
                                           "matching": {"ratio": 0.7, "strategy": "either"},
                                           "geometry": {"ransac": "magsac", "threshold": 3.0, "max_iters": 777}}}
    conf, label = sel.reference_config(frozen, None)
    assert (conf.feature.name, conf.feature.num_features, conf.geometry.ransac) == ("orb", 2000, "magsac")
    assert (conf.matching.ratio, conf.matching.strategy) == (0.85, "both")
    assert (conf.geometry.threshold, conf.geometry.max_iters) == (0.5, 50000)
    assert "paper defaults" in label
    assert sel.reference_config(frozen, "none") is None
    # multiview: COLMAP's RANSAC is not ours, only r and the strategy are the paper's
    mv, _ = sel.reference_config({**frozen, "task": "multiview"}, "paper")
    assert mv.matching.ratio == 0.85 and mv.geometry.threshold == 3.0 and mv.geometry.max_iters == 777
    with pytest.raises(ImtuneError, match="resolve"):
        sel.reference_config(frozen, "some-file.yaml")


def test_test_interval_and_self_comparison():
    import numpy as np
    rng = np.random.default_rng(3)
    runs = [[["A", f"p{i}", float(e)] for i, e in enumerate(rng.exponential(4.0, 20))] +
            [["B", f"q{i}", float(e) if e < 9 else "inf"] for i, e in enumerate(rng.exponential(6.0, 12))]
            for _ in range(3)]
    from pipeline.metrics.uncertainty import maa_from_errors
    per_run = []
    for r in runs:
        a = maa_from_errors([e for s, _, e in r if s == "A"])
        b = maa_from_errors([e for s, _, e in r if s == "B"])
        per_run.append((a + b) / 2)
    mean = {"mAA10": float(np.mean(per_run)), "mAA5": 0.0, "scenes": {"A": {}, "B": {}}}
    info = sel.test_interval(mean, runs, 500)
    assert info["consistent_with_mean"] and info["runs"] == 3
    lo, hi = mean["mAA10_ci"]
    assert lo <= mean["mAA10"] <= hi and "mAA10_ci" in mean["scenes"]["A"]
    assert sel.test_interval(mean, runs, 0) is None
    assert sel.test_interval({"mAA10": 0.5}, [None], 500) is None  # no pair errors (multiview): none
    same = sel.compare_reference(runs, runs, 500)
    assert same["difference"] == 0.0 and same["p_value"] == 1.0 and not same["significant"]
    assert "no significant difference" in sel.comparison_text({"label": "x", "mAA10": 0.5, "comparison": same})
    assert sel.pair_errors([{"scene": "A", "bag": 1, "errors": [1.0]}]) is None


def test_a_flat_optimum_frozen_by_best_points_to_one_se():
    """A 'best' pick among many tied trials is a pick by noise (the README main job once froze eta 0.75 px this way,
    22 of 26 trials tied: test 0.606 against the defaults' 0.679, where `--select one-se` gave 0.692). The frozen
    table now says so when more than half the trials tie, and names the command."""
    from tuner.commands.study import _frozen_notes
    flat = {"trials": 22, "of": 26, "interval": [0.804, 0.956], "params": {}}
    f = {"study": "s1", "selection": {"rule": "best", "best_trial": 33, "best_value": 0.887, "note": ""},
         "robustness": flat}
    lines = _frozen_notes(f).strip().splitlines()
    assert lines[-1].startswith("the optimum is flat (22 of 26 trials tie") and \
        "`tune test --study s1 --select one-se`" in lines[-1], lines
    for other in ({**f, "robustness": {**flat, "trials": 13}},  # half: not flat enough to say
                  {**f, "selection": {**f["selection"], "rule": "one-se"}}):  # already the centre
        assert "the optimum is flat" not in _frozen_notes(other)


def test_tune_studies_names_the_frozen_trial_beside_the_best(tmp_path):
    """`tune studies` listed "best mAA10 0.8873 | best trial 33" for the README job's study, frozen with --select
    one-se at trial 16: nothing said which trial the study freezes (its report, test.json and tables use 16). Now a
    'frozen trial' column (with the rule) beside the best. PLATEAU frozen by one-se is trial 2 (see above)."""
    import json

    from tests.test_bad_input_files import tune
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    mem = make_study(PLATEAU)
    st = optuna.create_study(study_name="plateau", storage=storage, direction="maximize")
    for k, v in {**mem.user_attrs, "select": "one-se"}.items():
        st.set_user_attr(k, v)
    for t in mem.trials:
        st.add_trial(t)
    r = tune("studies", "--storage", storage, "--studies-dir", tmp_path / "studies", "--json")
    assert r.returncode == 0, r.stderr[-2000:]
    (row,) = json.loads(r.stdout)
    assert row["best trial"] == 0 and row["frozen trial"] == 2 and row["frozen by"] == "one-se", row


def test_the_flat_region_line_says_its_interval_is_one_of_validation_mAA():
    """The flat-region line (`tune` output, report.html, frozen.yaml) read "22 of 26 trials within the optimum's
    interval [0.804, 0.956]: Gamma 1,232-174,531, r 0.772-0.985, eta 0.166-1.24 px": beside parameter ranges, an
    interval of what (an r? an eta?) was left unsaid. It is the 95% interval of the optimum's validation mAA(10°)."""
    st = make_study(PLATEAU)
    flat = sel.flat_region(st, sel.select_trial(st, "best")[0])
    text = sel.flat_text(flat)
    assert "6 of 7 trials with validation mAA(10°) within the optimum's 95% interval [0.700, 0.900]" in text, text
    assert "validation mAA(10) within the optimum's 95% interval" in flat["note"], flat["note"]


def test_a_reused_test_result_gets_the_intervals_of_the_current_method():
    """`tune test` returns an existing test.json for the same trial, configuration and data as is; one written by an
    earlier imtune kept that version's intervals: for 12 pairs all solved within 1 deg in each of 3 runs the plain
    bootstrap's [1, 1] (a true mAA(10) of 0.9 gives 12 of 12 such pairs 28% of the time), while `tune results` and
    `tune findings` recompute from the same pair errors. A reused result whose interval method is not the current
    one is recomputed from its pair errors (the mean's, per scene, and the reference comparison)."""
    runs = [[["A", f"p{i}", 0.2] for i in range(12)] for _ in range(3)]
    ref_runs = [[["A", f"p{i}", "inf"] for i in range(12)] for _ in range(3)]
    stale = {"lo_hi": [1.0, 1.0]}
    result = {"runs": [{"pair_errors": r} for r in runs],
              "mean": {"mAA10": 1.0, "mAA5": 1.0, "mAA10_ci": stale["lo_hi"], "mAA5_ci": stale["lo_hi"],
                       "scenes": {"A": {"mAA10": 1.0, "mAA10_ci": [1.0, 1.0]}}},
              "interval": {"method": "percentile bootstrap over pairs (an earlier imtune)", "level": 0.95},
              "reference": {"label": "paper defaults", "mAA10": 0.0, "mean": {"mAA10": 0.0, "mAA5": 0.0},
                            "runs": [{"pair_errors": r} for r in ref_runs],
                            "comparison": {"difference": 1.0, "ci": [1.0, 1.0], "p_value": 0.5, "pairs": 12}}}
    assert sel.refresh_intervals(result, 500)
    lo, hi = result["mean"]["mAA10_ci"]
    assert hi == 1.0 and lo < 0.9, (lo, hi)
    assert result["mean"]["scenes"]["A"]["mAA10_ci"][0] < 0.9
    assert result["interval"]["method"] == sel.TEST_INTERVAL_NOTE
    c = result["reference"]["comparison"]  # 12 of 12 pairs one way: exact sign-flip p = 2 / 2^12
    assert c["difference"] == 1.0 and c["p_value"] < 0.01 and c["significant"]
    assert not sel.refresh_intervals(result, 500)  # current: left as is


def test_every_reader_of_an_earlier_test_json_gets_the_current_intervals(tmp_path):
    """A study's report (`tune plot`) and tables read test.json through one reader; a file written by an earlier
    imtune showed its old interval ([1, 1] for 12 pairs all within 1 deg) until `tune test` ran again, beside
    numbers (ranks, findings) recomputed the current way. The reader now recomputes it from the pair errors."""
    import json

    from tuner.freeze import load_test_file
    runs = [[["A", f"p{i}", 0.2] for i in range(12)] for _ in range(3)]
    old = {"study": "s", "runs": [{"pair_errors": r, "mAA10": 1.0} for r in runs],
           "mean": {"mAA10": 1.0, "mAA5": 1.0, "mAA10_ci": [1.0, 1.0], "mAA5_ci": [1.0, 1.0]},
           "interval": {"method": "percentile bootstrap over pairs (an earlier imtune)", "level": 0.95,
                        "resamples": 500}}
    p = tmp_path / "test.json"
    p.write_text(json.dumps(old))
    d, why = load_test_file(p, "s")
    assert why is None and d["mean"]["mAA10_ci"][0] < 0.9 and d["interval"]["method"] == sel.TEST_INTERVAL_NOTE
    raw, _ = load_test_file(p, "s", refresh=False)
    assert raw["mean"]["mAA10_ci"] == [1.0, 1.0]  # the file itself is left to `tune test`


def test_an_earlier_test_json_of_the_same_scenes_and_pairs_is_not_called_another_test_set():
    """`tune test` after `tune data build-gt` (co-visibility now known: the data fingerprint changes, the 16 pairs of
    Herz-Jesus-P8 and entry-P10 do not) warned 'the study's earlier test.json measured another test set
    (Herz-Jesus-P8, entry-P10; 16 pairs)', naming the very set it had just measured. Now the line says the scenes and
    pairs are the same and the data differs (both fingerprints); another set of scenes keeps the old line."""
    from tuner.freeze import earlier_test_line
    now = {"scenes": ["Herz-Jesus-P8", "entry-P10"], "pairs": 16, "fingerprint": "073f4b57346be4c9"}
    same = {"path": "/s/earlier-1/test.json", "scenes": ["Herz-Jesus-P8", "entry-P10"], "pairs": 16,
            "fingerprint": "281672c91a8ad960"}
    line = earlier_test_line({"data": now, "earlier_test": same})
    assert "another test set" not in line and "the same scenes (Herz-Jesus-P8, entry-P10; 16 pairs)" in line
    assert "281672c91a8ad960, now 073f4b57346be4c9" in line and "/s/earlier-1/test.json" in line
    other = earlier_test_line({"data": {**now, "scenes": ["entry-P10"], "pairs": 3}, "earlier_test": same})
    assert other.startswith("the study's earlier test.json measured another test set (Herz-Jesus-P8, entry-P10; 16")
    assert earlier_test_line({"data": now}) is None


def test_a_reused_multiview_test_result_gets_the_current_intervals_and_one_without_bag_images_is_rerun(tmp_path):
    """A multiview test.json whose interval an earlier imtune made another way kept it: the refresh read only
    stereo ``pair_errors``, so the bag errors beside it were never used. And `tune test --reuse` (and every reuse of a
    test.json) handed back a multiview test whose bags carry no images, so `tune results` could never pair its bags
    with another study's. Now the interval is recomputed from the bag errors (bags resampled within each scene and
    size: 12 bags of 10 pairs all within 1 deg in each run, a stale [1, 1] -> an interval below 1), and such a
    file is not reused: the test runs again and records its bags' images."""
    import json

    from tuner.freeze import _previous_result
    bags = [["A", 5, k, [0.2] * 10, [f"{k}-{j}" for j in range(5)]] for k in range(12)]
    result = {"study": "s", "runs": [{"bag_errors": bags, "mAA10": 1.0} for _ in range(3)],
              "mean": {"mAA10": 1.0, "mAA5": 1.0, "mAA10_ci": [1.0, 1.0], "mAA5_ci": [1.0, 1.0]},
              "interval": {"method": "bootstrap over bags (an earlier imtune)", "level": 0.95}, "identity": {"x": 1}}
    assert sel.refresh_intervals(json.loads(json.dumps(result)), 500)
    r = json.loads(json.dumps(result))
    sel.refresh_intervals(r, 500)
    assert r["mean"]["mAA10_ci"][0] < 0.95 and r["interval"]["method"] == sel.BAG_TEST_INTERVAL_NOTE
    p = tmp_path / "test.json"
    p.write_text(json.dumps(result))
    assert _previous_result(p, {"x": 1}, "s") is not None  # images recorded: reused
    for run in result["runs"]:
        run["bag_errors"] = [b[:4] for b in run["bag_errors"]]
    p.write_text(json.dumps(result))
    assert _previous_result(p, {"x": 1}, "s") is None  # no images: rerun
