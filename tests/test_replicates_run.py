"""`tune run --replicates K` and `tune compare` of replicated studies on tiny real data (issue 32, parts 2-3).

The statistics are tested in test_replicates_stats.py; here the wiring: K studies with their own seeds and frozen
settings, test.json's ``replicates`` / ``replicated``, a rerun that reuses them, and compare's P(A > B). Expected
figures are recomputed here from each replicate's own test.json (its pair errors), not taken from the code under
test.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
STRECHA = Path(os.environ.get("IMTUNE_SHARED", ROOT.parent / "shared")) / "data" / "strecha"
pytestmark = pytest.mark.skipif(not (STRECHA / "fountain-P11").is_dir(), reason=f"real data not found at {STRECHA}")
NAME = "sift-1024-degensac-stereo"


def tune(*args, cache):
    env = dict(os.environ, IMTUNE_CACHE=str(cache))
    r = subprocess.run([sys.executable, "-m", "tuner", *args], capture_output=True, text=True, cwd=ROOT, env=env,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def run_args(studies, seed, *extra):
    return ["run", "--data", str(STRECHA), "--feature", "sift", "--num-features", "1024", "--ransac", "degensac",
            "--scenes", "fountain-P11", "--test-scenes", "Herz-Jesus-P8,entry-P10", "--max-pairs", "4",
            "--chunk-pairs", "4", "--budget", "0.05", "--calibration-pairs", "3", "--n-trials", "2",
            "--test-runs", "1", "--reference", "none", "--seed", str(seed), "--studies-dir", str(studies),
            "--replicates", "3", *extra]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("replicates")
    cache = d / "cache"
    studies = d / "studies"
    a = json.loads(tune(*run_args(studies, 1, "--json"), cache=cache).stdout)
    b = json.loads(tune(*run_args(studies, 2, "--study", "other", "--json"), cache=cache).stdout)
    return {"studies": studies, "cache": cache, "a": a, "b": b}


def _test(studies, name):
    return json.loads((studies / name / "test.json").read_text())


def _maa10_by_hand(test: dict) -> tuple[float, dict]:
    """The scene-averaged mAA(10) of a test.json and its per-pair scores, from the runs' pair errors."""
    per = {}
    for run in test["runs"]:
        for scene, pair, err in run["pair_errors"]:
            e = np.inf if err in (None, "inf") else float(err)
            per.setdefault((scene, json.dumps(pair)), []).append(np.mean([e <= k for k in range(1, 11)]))
    scores = {k: float(np.mean(v)) for k, v in per.items()}
    scenes = sorted({k[0] for k in scores})
    return float(np.mean([np.mean([v for k, v in scores.items() if k[0] == s]) for s in scenes])), scores


def test_three_studies_with_their_own_seeds_and_frozen_settings(runs):
    import optuna

    from tuner.storage import open_storage
    storage = open_storage(f"sqlite:///{runs['studies']}/optuna.db", heartbeat=None)
    names = [NAME, f"{NAME}-r2", f"{NAME}-r3"]
    studies = [optuna.load_study(study_name=n, storage=storage) for n in names]
    seeds = [s.user_attrs["seed"] for s in studies]
    assert seeds[0] == 1  # replicate 1 is today's study: --seed as given
    assert len(set(seeds)) == 3
    sampler_seeds = {t.user_attrs.get("sampler_seed") for s in studies for t in s.trials}
    assert len(sampler_seeds) == 3  # each study's sampler seeded on its own
    for n, seed in zip(names, seeds):  # the estimator seed of the frozen settings and the test runs: the replicate's
        assert yaml.safe_load((runs["studies"] / n / "frozen.yaml").read_text())["config"]["geometry"]["seed"] == seed
        assert _test(runs["studies"], n)["runs"][0]["seed"] == seed
    first_params = [json.dumps(s.trials[0].params, sort_keys=True) for s in studies]
    assert len(set(first_params)) == 3  # not the same draws three times
    reps = _test(runs["studies"], NAME)["replicates"]
    assert [r["study"] for r in reps] == names
    attr = studies[0].user_attrs["replicated"]  # what optuna-dashboard shows beside the first study
    assert attr["K"] == 3 and [r["study"] for r in attr["replicates"]] == names
    assert [r["seed"] for r in reps] == seeds
    for r, n in zip(reps, names):
        frozen = _test(runs["studies"], n)
        assert r["params"] == frozen["params"] and r["trial"] == frozen["trial"]


def test_replicated_figure_is_the_mean_of_the_replicates_and_its_interval_is_wider(runs):
    top = _test(runs["studies"], NAME)
    rep = top["replicated"]
    names = [r["study"] for r in top["replicates"]]
    own = [_test(runs["studies"], n) for n in names]
    by_hand = [_maa10_by_hand(t)[0] for t in own]
    for t, h, r in zip(own, by_hand, top["replicates"]):
        assert t["mean"]["mAA10"] == pytest.approx(h, abs=1e-12)  # the scores read back are the test's
        assert r["mAA10"] == pytest.approx(h, abs=1e-12)
    assert rep["mAA10"] == pytest.approx(np.mean(by_hand), abs=1e-12)
    assert runs["a"]["replicated"]["mAA10"] == pytest.approx(np.mean(by_hand), abs=1e-12)
    lo, hi = rep["mAA10_ci"]
    assert lo < rep["mAA10"] < hi
    assert rep["K"] == 3 and rep["tuning_variance_measured"] is True
    assert set(rep["spread"]) == {"ratio", "threshold", "max_iters"}
    for p in ("ratio", "threshold", "max_iters"):
        vals = [r["params"][p] for r in top["replicates"]]
        assert rep["spread"][p] == {"min": min(vals), "max": max(vals)}
    # the same pairs with the tuning part dropped (every replicate's scores the mean's): narrower exactly when the
    # tuning variance, estimated here by hand (s^2 of the replicate figures minus the interaction mean square / N,
    # scene-weighted scores), is positive
    from pipeline.metrics.replicates import replicated_maa_interval, scene_weights
    from tuner.replicates import score_matrix
    scores, strata = score_matrix(own, scaled=False)
    assert scores.mean(axis=1) == pytest.approx(by_hand, abs=1e-12)
    one = replicated_maa_interval(scores.mean(axis=0, keepdims=True).repeat(3, 0), strata)
    assert one.se_between == 0 and one.mean == pytest.approx(rep["mAA10"], abs=1e-12)
    w = scores * scene_weights(strata)[None, :]
    resid = w - w.mean(axis=1, keepdims=True) - w.mean(axis=0, keepdims=True) + w.mean()
    tuning = np.var(w.mean(axis=1), ddof=1) - np.sum(resid**2) / (2 * (w.shape[1] - 1)) / w.shape[1]
    iv = replicated_maa_interval(scores, strata)
    assert (iv.low, iv.high) == pytest.approx((lo, hi), abs=1e-12)
    if 0 < lo and hi < 1 and 0 < one.low and one.high < 1:  # the variances add (intervals on the logit scale)
        from scipy import special, stats
        m = rep["mAA10"]

        def var_of(low, high, df):  # se = logit half-width / t * m (1 - m) (the delta method)
            return ((special.logit(high) - special.logit(low)) / 2 / stats.t.ppf(0.975, df) * m * (1 - m)) ** 2
        assert var_of(lo, hi, iv.df) - var_of(one.low, one.high, one.df) == pytest.approx(tuning / 3, rel=1e-6,
                                                                                          abs=1e-12)
    if rep["se_between"] >= rep["se_pairs"]:  # the tuning spread dominates: wider than every replicate's own
        for t in own:
            slo, shi = t["mean"]["mAA10_ci"]
            assert hi - lo > shi - slo


def test_interval_wider_than_each_replicate_when_replicates_differ():
    """Synthetic: three replicates of 24 pairs in 2 scenes whose means differ by 0.2 (tuning spread larger than the
    pair spread): the replicated interval is wider than each replicate's own (K = 1) interval and contains the
    mean; replicates that agree exactly give the K = 1 interval of their common scores."""
    from pipeline.metrics.replicates import replicated_maa_interval
    rng = np.random.default_rng(0)
    base = rng.uniform(0.3, 0.9, 24)
    scores = np.clip(np.stack([base - 0.2, base, base + 0.2]), 0, 1)
    strata = np.array(["a"] * 12 + ["b"] * 12)
    iv = replicated_maa_interval(scores, strata)
    assert iv.low < scores.mean() < iv.high
    for row in scores:
        single = replicated_maa_interval(row[None, :], strata)
        assert single.tuning_variance_measured is False
        assert iv.high - iv.low > single.high - single.low
    same = replicated_maa_interval(np.stack([base] * 3), strata)
    alone = replicated_maa_interval(base[None, :], strata)
    assert (same.low, same.high) == pytest.approx((alone.low, alone.high))


def test_rerun_reuses_every_replicate(runs):
    before = {n: len(_test(runs["studies"], n)["runs"]) for n in (NAME, f"{NAME}-r2", f"{NAME}-r3")}
    created = {n: _test(runs["studies"], n)["created"] for n in before}
    out = json.loads(tune(*run_args(runs["studies"], 1, "--json"), cache=runs["cache"]).stdout)
    assert [len(o["worker"]["trials_run"]) for o in out["replicates"]] == [0, 0, 0]
    assert [o["counts"]["complete"] + o["counts"]["pruned"] for o in out["replicates"]] == [2, 2, 2]
    assert {n: _test(runs["studies"], n)["created"] for n in before} == created  # tests reused, not rerun
    assert out["replicated"]["mAA10"] == pytest.approx(runs["a"]["replicated"]["mAA10"], abs=1e-12)


def test_compare_of_two_replicated_runs_prints_p_a_beats_b(runs):
    r = tune("compare", NAME, "other", "--studies-dir", str(runs["studies"]), "--json", cache=runs["cache"])
    d = json.loads(r.stdout)
    a = [_maa10_by_hand(_test(runs["studies"], n))[0] for n in (NAME, f"{NAME}-r2", f"{NAME}-r3")]
    b = [_maa10_by_hand(_test(runs["studies"], n))[0] for n in ("other", "other-r2", "other-r3")]
    assert d["difference_a_minus_b"] == pytest.approx(np.mean(a) - np.mean(b), abs=1e-12)
    # P(one new tuning of A > one of B) = Phi(difference / sqrt(s_A^2 + s_B^2)), s^2 the variance of one replicate's
    # figure, by hand from the three replicate figures of each side
    from scipy import stats
    s2 = np.var(a, ddof=1) + np.var(b, ddof=1)
    if s2 > 0:  # Phi(d / sqrt(s^2 - se^2)), unbiased (c^2 floored at s^2 / 4), held inside its interval
        lo, hi = d["p_a_beats_b_ci"]
        est = stats.norm.cdf((np.mean(a) - np.mean(b)) / np.sqrt(max(s2 - d["se"] ** 2, s2 / 4)))
        assert d["p_a_beats_b"] == pytest.approx(min(max(est, lo), hi), abs=1e-9)
        assert lo <= d["p_a_beats_b"] <= hi
    assert d["ci"][0] <= d["difference_a_minus_b"] <= d["ci"][1]
    assert d["verdict_allowed"] is True and d["significant"] == (d["p_value"] < 0.05)
    text = tune("compare", NAME, "other", "--studies-dir", str(runs["studies"]), cache=runs["cache"]).stdout
    assert "P(A > B) = " in text and "not measured" not in text
    if not d["significant"]:  # an inconclusive verdict says what it could have detected
        assert "inconclusive: could detect |A - B| >= " in text


def test_k1_verdict_says_tuning_variance_not_measured(runs):
    """A replicated study against one single tuning (the -r2 study alone): the verdict names what is missing."""
    r = tune("compare", NAME, "other-r2", "--studies-dir", str(runs["studies"]), cache=runs["cache"])
    assert "the tuning variance was not measured" in r.stdout
    assert "P(A > B)" not in r.stdout
    assert "significant" not in r.stdout and "no tuned verdict: B was tuned once" in r.stdout
    d = json.loads(tune("compare", NAME, "other-r2", "--studies-dir", str(runs["studies"]), "--json",
                        cache=runs["cache"]).stdout)
    assert d["significant"] is False and d["verdict_allowed"] is False and d["assumption"]


def test_results_show_the_replicated_figure_once(runs):
    """`tune results`: one row per replicated configuration (its -r2 / -r3 studies are not rows), the replicated
    mean and interval with (K=3); the caption says what K means."""
    r = tune("results", "--studies-dir", str(runs["studies"]), "--format", "json", cache=runs["cache"])
    text = tune("results", "--studies-dir", str(runs["studies"]), cache=runs["cache"]).stdout
    assert "(K=3)" in text and "tuning replicates" in text
    # both runs are sift 1024 + degensac: one row, the better of the two replicated figures
    tops = [_test(runs["studies"], n)["replicated"] for n in (NAME, "other")]
    shown = [f"{t['mAA10']:.3f} [{t['mAA10_ci'][0]:.3f}, {t['mAA10_ci'][1]:.3f}] (K=3)" for t in tops]
    assert any(x in text for x in shown), (shown, text)
    assert f"{NAME}-r2" not in r.stdout and "other-r3" not in r.stdout


def test_k1_run_says_tuning_variance_not_measured(runs):
    """`--replicates 1` (the default) is today's study: the finished first replicate resumed (no trial), and the
    printed outcome says the tuning variance was not measured."""
    r = tune(*run_args(runs["studies"], 1, "--replicates", "1", "--quiet"), cache=runs["cache"])
    assert "this worker ran 0" in r.stdout
    assert "tuning: 1 replicate: the tuning variance was not measured" in r.stdout
    assert "replicated test mAA10" not in r.stdout


def test_replicates_of_a_bag_task_are_refused_before_tuning(tmp_path):
    """The replicated figure pairs stereo test pairs: a multiview run with --replicates 2 is one line, exit 2, before
    any study exists."""
    env = dict(os.environ, IMTUNE_CACHE=str(tmp_path / "cache"))
    r = subprocess.run([sys.executable, "-m", "tuner", "run", "--task", "multiview", "--data", str(STRECHA),
                        "--scenes", "fountain-P11", "--studies-dir", str(tmp_path / "s"), "--replicates", "2"],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "--replicates 2" in lines[0] and "bags" in lines[0], r.stderr
    assert not (tmp_path / "s" / "optuna.db").exists()


def test_two_single_studies_compare_as_before_and_say_tuning_not_measured(runs):
    """Two unreplicated studies (-r2 of each run) are evaluated on the pairs as before; the verdict names what a
    single tuning cannot measure."""
    common = ["compare", f"{NAME}-r2", "other-r2", "--studies-dir", str(runs["studies"]), "--data", str(STRECHA),
              "--scenes", "Herz-Jesus-P8"]
    d = json.loads(tune(*common, "--json", "--quiet", cache=runs["cache"]).stdout)
    assert "overall" in d and "difference" in d["overall"]  # the single-study comparison, unchanged
    assert d["tuning_variance_measured"] is False and "not measured" in d["tuning_note"]


def test_reference_comparison_of_replicates_from_pair_errors():
    """Synthetic test.json dicts (no tuning): tuned - reference over 3 replicates equals the mean difference of the
    scene-weighted mAAs computed here; P(tuned > reference) is the model's from the replicate figures; a reference with other settings
    than the others (not only its seed) gives no comparison."""
    from tuner.replicates import reference_comparison, replicated_summary
    rng = np.random.default_rng(3)
    pairs = [("a", [0, i]) for i in range(6)] + [("b", [1, i]) for i in range(10)]

    def run(shift):
        return {"pair_errors": [[sc, p, float(e)] for (sc, p), e in zip(pairs, rng.gamma(2.0, 2.0 + shift, len(pairs)))]}
    tests = []
    for k, shift in enumerate((0.0, 0.5, -0.5)):
        t = {"study": f"s{k}", "trial": k, "params": {"ratio": 0.8 + k / 100}, "runs": [run(shift)],
             "reference": {"label": "paper", "config": {"geometry": {"seed": k, "threshold": 0.5}}, "runs": [run(1.5)]}}
        t["mean"] = {"mAA10": _maa10_by_hand(t)[0]}
        tests.append(t)
    tuned = [_maa10_by_hand(t)[0] for t in tests]
    ref = [_maa10_by_hand(t["reference"])[0] for t in tests]
    out = reference_comparison(tests)
    assert out["difference"] == pytest.approx(np.mean(tuned) - np.mean(ref), abs=1e-12)
    assert out["mAA10"] == pytest.approx(np.mean(ref), abs=1e-12)
    # P(one new tuning beats the reference) = Phi(difference / sqrt(s_tuned^2 + s_reference^2)) of the replicate
    # figures (each side's sample variance), by hand
    from scipy import stats
    s2 = np.var(tuned, ddof=1) + np.var(ref, ddof=1)
    lo, hi = out["p_tuned_beats_reference_ci"]
    est = stats.norm.cdf((np.mean(tuned) - np.mean(ref)) / np.sqrt(max(s2 - out["se"] ** 2, s2 / 4)))
    assert out["p_tuned_beats_reference"] == pytest.approx(min(max(est, lo), hi), abs=1e-9)
    assert lo <= out["p_tuned_beats_reference"] <= hi
    assert out["verdict_allowed"] is True and out["verdict"].startswith("tuned - reference = ")
    assert out["ci"][0] < out["difference"] < out["ci"][1]
    summary = replicated_summary(tests, [1, 2, 3])
    assert summary["mAA10"] == pytest.approx(np.mean(tuned), abs=1e-12) and summary["reference"] == out
    tests[2]["reference"]["config"]["geometry"]["threshold"] = 1.0
    assert reference_comparison(tests) is None


def test_the_plot_report_of_a_replicated_study_gives_the_replicated_figure(runs):
    """`tune plot --study NAME` of the first replicate: beside its own test figure, the replicated mean and interval
    and each replicate's study and figure, as test.json records them (it showed the first replicate alone)."""
    import html as html_mod
    out = runs["studies"] / "plot.html"
    tune("plot", "--study", NAME, "--studies-dir", str(runs["studies"]), "--out", str(out), cache=runs["cache"])
    page = html_mod.unescape(out.read_text())
    rep = _test(runs["studies"], NAME)["replicated"]
    lo, hi = rep["mAA10_ci"]
    assert f"replicated test mAA10 over 3 replicates x {rep['pairs']} pairs: {rep['mAA10']:.4f} [{lo:.4f}, {hi:.4f}]" \
        in page, page[:3000]
    for r in _test(runs["studies"], NAME)["replicates"]:
        assert f"{r['study']} (seed {r['seed']}): trial #{r['trial']}" in page
        assert f"test mAA10 {r['mAA10']:.4f}" in page
