"""`tune results` ranks with ties: features whose test mAA(10) difference to the one above is not significant
share its rank, and every mAA is shown with its 95% interval. Synthetic test runs with known per-pair errors
(test.json as the test run writes it, plus each run's pair errors)."""
import json
import math

import numpy as np

from tuner.freeze import study_dir
from tuner.reports import StudyInfo, results_rows


def pair_errors(rng, scale, n=40, scenes=("Herz-Jesus-P8", "entry-P10")):
    out = []
    for sc in scenes:
        e = rng.exponential(scale, n)
        e[rng.random(n) < 0.1] = math.inf
        out += [[sc, f"{i:04d}.jpg|{i + 1:04d}.jpg", "inf" if not math.isfinite(x) else float(x)] for i, x in enumerate(e)]
    return out


def maa10(errs):
    e = np.array([float(x[2]) for x in errs])
    return float(np.mean([np.mean([(e[[x[0] == sc for x in errs]] <= k).mean() for k in range(1, 11)])
                          for sc in sorted({x[0] for x in errs})]))


def make_study(tmp_path, name, feature, runs, with_pairs=True, ci=None):
    """A tested study: test.json with ``runs`` (lists of [scene, pair, err]) and the study's test summary."""
    values = [maa10(r) for r in runs]
    d = study_dir(tmp_path, name)
    d.mkdir(parents=True, exist_ok=True)
    test = {"runs": [{"seed": k, "mAA10": v, **({"pair_errors": r} if with_pairs else {})}
                     for k, (v, r) in enumerate(zip(values, runs))]}
    (d / "test.json").write_text(json.dumps(test))
    summary = {"mAA10": float(np.mean(values)), "NF": 2048.0, "NI": 100.0, "runs": len(runs)}
    if ci:
        summary["mAA10_ci"] = ci
    return StudyInfo(name=name, task="stereo", feature=feature, num_features=2048, ransac="degensac", attrs={},
                     best=None, n_complete=1, test=summary)


def test_paired_ties_from_the_test_runs_pair_errors(tmp_path):
    rng = np.random.default_rng(0)
    good = [pair_errors(np.random.default_rng(1), 1.5)] * 3
    base = pair_errors(rng, 6.0)
    # "twin": the same pairs, the errors perturbed by seed noise (5%) in each run: no real difference
    twin = [[[sc, p, (e if e == "inf" else e * float(np.exp(rng.normal(0, 0.05))))] for sc, p, e in base]
            for _ in range(3)]
    studies = [make_study(tmp_path, "a", "sift", [base] * 3), make_study(tmp_path, "b", "orb", twin),
               make_study(tmp_path, "c", "superpoint", good)]
    rows, cols = results_rows(studies, studies_dir=tmp_path)
    assert [r["rank"] for r in rows] == [1, 2, 2] and rows[0]["feature"] == "superpoint"
    assert {rows[1]["feature"], rows[2]["feature"]} == {"sift", "orb"}
    assert "ties" in cols and rows[2]["ties"].startswith(f"rank shared with {rows[1]['feature']} (2048)")
    assert "paired bootstrap" in rows[2]["ties"] and rows[1]["ties"] == "" and rows[0]["ties"] == ""
    v = rows[0]["mAA10 degensac"]  # "value [lo, hi]"
    val, rest = v.split(" [")
    lo, hi = (float(x) for x in rest.rstrip("]").split(", "))
    assert abs(float(val) - maa10(good[0])) <= 1e-3 and lo < float(val) < hi
    js, jcols = results_rows(studies, "json", studies_dir=tmp_path)
    assert abs(js[0]["mAA10 degensac"] - maa10(good[0])) <= 1e-4 and len(js[0]["mAA10_ci degensac"]) == 2
    assert js[2]["rank"] == 2 and "mAA10_ci degensac" in jcols


def test_without_pair_errors_ranks_by_overlapping_intervals_and_says_so(tmp_path):
    rng = np.random.default_rng(3)
    runs = [pair_errors(rng, 3.0)]
    studies = [make_study(tmp_path, "a", "sift", runs, with_pairs=False, ci=[0.50, 0.60]),
               make_study(tmp_path, "b", "orb", runs, with_pairs=False, ci=[0.58, 0.70]),
               make_study(tmp_path, "c", "akaze", runs, with_pairs=False, ci=[0.20, 0.30])]
    studies[1].test["mAA10"], studies[0].test["mAA10"], studies[2].test["mAA10"] = 0.64, 0.55, 0.25
    rows, _ = results_rows(studies, studies_dir=tmp_path)
    assert [(r["feature"], r["rank"]) for r in rows] == [("orb", 1), ("sift", 1), ("akaze", 3)]
    assert "intervals overlap" in rows[1]["ties"] and rows[2]["ties"] == ""
    assert rows[0]["mAA10 degensac"] == "0.640 [0.580, 0.700]"
    # no interval at all (old test.json, no studies dir): plain ranks, and the table says why
    for s in studies:
        s.test.pop("mAA10_ci")
    rows, _ = results_rows(studies)
    assert [r["rank"] for r in rows] == [1, 2, 3]
    assert all(r["ties"] == "no interval: ranked by value alone" for r in rows[1:])
    assert rows[0]["mAA10 degensac"] == "0.640"


def test_the_results_table_says_it_shows_test_numbers_and_what_they_are(tmp_path):
    """`tune results` printed a bare table ("mAA10 degensac 0.692 [0.620, 0.758]") saying neither that these are
    test-set numbers nor on which scenes, how many runs, or what the interval is, while `tune table` (validation)
    has a caption; the results table now has one too (markdown "Table:" line, LaTeX caption)."""
    from tuner.reports import render_table
    rng = np.random.default_rng(5)
    runs = [pair_errors(rng, 3.0) for _ in range(3)]
    studies = [make_study(tmp_path, "a", "sift", runs), make_study(tmp_path, "b", "orb", runs[:1] * 3)]
    for s in studies:
        s.test.update(scenes=["Herz-Jesus-P8", "entry-P10"], pairs=80)
    rows, cols = results_rows(studies, studies_dir=tmp_path)
    md = render_table(rows, cols, "markdown")
    cap = md.splitlines()[-1]
    assert cap.startswith("Table: Test results on the test scenes Herz-Jesus-P8, entry-P10 (80 pairs)"), cap
    for words in ("mean of 3 runs", "95% interval over pairs and runs", "NI: inliers per pair",
                  "NF: features per image"):
        assert words in cap, (words, cap)
    assert "\\caption{Test results on the test scenes" in render_table(rows, cols, "latex")


def bag_runs(difficulty, shrink, runs=2, images=None, rng=None):
    """test.json ``bag_errors`` of a multiview test: per run ``[scene, size, bag, [pair errors], [images]]`` on the
    given bags (their difficulty shared by every method: the common bag effect); ``shrink`` scales the errors,
    ``images`` renames the bags' images (other bags), each run adds per-pair seed noise."""
    rng = rng or np.random.default_rng(0)
    out = []
    for _ in range(runs):
        run = []
        for (sc, size, k), d in difficulty.items():
            imgs = (images or (lambda s, b, n: [f"{s}-{b}-{i:04d}.jpg" for i in range(n)]))(f"{sc}{size}", k, size)
            e = shrink * d * rng.lognormal(0, 0.1, d.size)
            run.append([sc, size, k, ["inf" if not math.isfinite(x) else float(x) for x in e], [str(x) for x in imgs]])
        out.append(run)
    return out


def make_bag_study(tmp_path, name, feature, runs):
    from pipeline.metrics.uncertainty import combine_bag_runs_interval
    from tuner.select import _as_bags
    iv = combine_bag_runs_interval([_as_bags(r) for r in runs], taus=(10,))
    d = study_dir(tmp_path, name)
    d.mkdir(parents=True, exist_ok=True)
    (d / "test.json").write_text(json.dumps({"runs": [{"seed": k, "bag_errors": r} for k, r in enumerate(runs)]}))
    return StudyInfo(name=name, task="multiview", feature=feature, num_features=2048, ransac="degensac", attrs={},
                     best=None, n_complete=1, test={"mAA10": iv["mAA10"], "runs": len(runs), "mAA10_ci": iv["mAA10_ci"]})


def test_multiview_ranks_pair_the_same_bags_and_say_why_when_bags_differ(tmp_path):
    """`tune results --task multiview` ranked by overlapping intervals even where both studies were tested on the
    same bags: with each bag's difficulty shared by both methods (known truth: B's errors are 0.7 x A's on every
    pair of every bag), B shared rank 1 with A. Tested on the same bags (scene, size, images) the ranks now pair
    them; on other bags (another bag draw) they fall back to the intervals and the ties column says why."""
    rng = np.random.default_rng(7)
    diff = {}
    for sc, size, count in (("Herz-Jesus-P8", 5, 12), ("entry-P10", 5, 12), ("entry-P10", 8, 4)):
        for k in range(count):
            diff[(sc, size, k)] = rng.lognormal(0.8, 1.0) * rng.lognormal(0, 0.3, size * (size - 1) // 2)
    runs_a = bag_runs(diff, 1.0, rng=rng)
    a = make_bag_study(tmp_path, "a", "sift", runs_a)
    b = make_bag_study(tmp_path, "b", "rootsift", bag_runs(diff, 0.7, rng=rng))
    assert b.test["mAA10_ci"][0] <= a.test["mAA10_ci"][1]  # unpaired, the intervals overlap
    rows, _ = results_rows([a, b], studies_dir=tmp_path)
    assert [(r["feature"], r["rank"]) for r in rows] == [("rootsift", 1), ("sift", 2)], rows
    assert rows[1]["ties"] == ""
    twin = make_bag_study(tmp_path, "c", "orb", [list(reversed(r)) for r in runs_a])  # A's bags in another order
    rows, _ = results_rows([a, twin], studies_dir=tmp_path)
    assert [r["rank"] for r in rows] == [1, 1] and "paired bootstrap and sign-flip test on the test bags" in rows[1]["ties"]
    # another bag draw: the same scenes and sizes, other images under the same indices
    other = make_bag_study(tmp_path, "d", "rootsift", bag_runs(diff, 0.7, rng=rng,
                                                               images=lambda s, k, n: [f"x{s}{k}-{i}" for i in range(n)]))
    warned = []
    rows, _ = results_rows([a, other], studies_dir=tmp_path, warn=warned.append)
    assert [r["rank"] for r in rows] == [1, 1], rows
    assert "95% intervals overlap (unpaired: " in rows[1]["ties"] and "the bags differ" in rows[1]["ties"], rows
    assert len(warned) == 1 and "the multiview ranks are not paired" in warned[0]
