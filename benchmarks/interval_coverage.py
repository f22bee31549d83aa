"""Do imtune's 95% intervals and paired tests mean what they say? Simulations with a known truth.

Pair errors are drawn from known distributions (per scene: LogNormal(mu, sigma) degrees, failed = inf with a
known probability), so the true mAA(10) is analytic (the lognormal CDF at 1..10 deg) and a true difference a
Monte-Carlo count over 400,000 pairs. Every figure applies imtune's own functions
(``pipeline.metrics.uncertainty``) to many simulated data sets and counts:

- ``intervals``: coverage of ``maa_intervals`` (overall and per scene) against the truth, beside the plain
  percentile bootstrap (no pseudo-scores), at 8-12 pairs per scene (`--quick`) and 33-73 (the protocol);
- ``paired``: ``paired_bootstrap`` under the null (B the same method as A: type-I error of p < 0.05, of "CI
  excludes 0" and of the verdict rule ``significant``) and under two alternatives (power, CI coverage of the
  true difference), one run or three runs per method, with and without a run effect shared by all pairs;
- ``relative``: coverage of ``paired_relative`` (the relative difference (B - A) / A of findings 1 and 3) of the
  true ratio of mAAs (each configuration's mAA by Monte Carlo over 10^6 pairs per scene), at 6, 10, 15, 30 and 73
  pairs per scene (3 scenes), B better by 6% and 10%, worse by 8%, with the misses below / above the interval;
- ``runs``: coverage of ``combine_runs_interval`` (three runs, per-pair seed noise, optional shared run effect);
- ``ranking``: ``rank_with_ties`` on k methods with the same error distribution: how often a table splits one off
  rank 1 (a false "significantly worse");
- ``bags``: two multiview methods on the same bags with a known common bag effect (each bag's difficulty scales
  both methods' errors; some bags fail for both): ``paired_bags`` (the per-bag differences) against the unpaired
  stratified bootstrap of the difference and against "95% intervals overlap" (``bag_intervals``, the rule
  `tune results` falls back to): coverage of the true B - A, mean width, and the rate of "different".

    python benchmarks/interval_coverage.py                  # all, 1000 data sets each (about 3 min on 2 cores)
    python benchmarks/interval_coverage.py relative --sims 600
    python benchmarks/interval_coverage.py paired --sims 400

Binomial sd of a coverage near 0.95 over 1000 data sets: 0.007.

Measured (2 cores, `--sims 1000` for intervals, 600 for paired / runs / ranking; before -> after this branch):
- intervals, 8-12 pairs per scene: easy scene (true 0.978, 12 pairs) 0.384 -> 1.000, good (0.877, 10 pairs)
  0.696 -> 0.986, middling (0.745, 8 pairs) 0.787 -> 0.987, overall 0.876 -> 0.990; at 33-73 pairs: easy (55)
  0.662 -> 0.994, good (40 / 73) 0.896 / 0.930 -> 0.958 / 0.951, middling / hard 0.934-0.940 -> 0.943-0.949,
  overall 0.934 / 0.942 -> 0.962 / 0.945, width +2-10% there;
- paired (400 data sets), one run: type-I error of the verdict rule 0.040 at 10 pairs per scene, 0.045 at 25
  (the sign-flip test is exact); CI coverage 0.89-0.90 -> 0.93-0.94 at 10 pairs, 0.92-0.93 -> 0.94-0.95 at 25;
  three runs, no run effect: type-I 0.035 (runs pooled: 0.058), coverage 0.955; a run effect shared by all
  pairs of a run (sd 0.15 in log error): runs pooled type-I 0.27, coverage 0.71-0.79 -> with the runs' index
  0.105, coverage 0.88-0.90 (its variance rests on 2 degrees of freedom: not fully fixed);
- relative (`relative --sims 600`, 231 s): the plain percentile interval of the ratio covered 0.855-0.887 at 6
  pairs per scene, 0.870-0.897 at 10, 0.915-0.925 at 15, 0.930-0.945 at 30, 0.928-0.938 at 73 (misses mostly above
  when B is better: the ratio is skewed); with Hesterberg's expansion (the level from the ratio's linearisation)
  0.917-0.942, 0.907-0.927, 0.940-0.943, 0.938-0.953, 0.930-0.940, width +30% / +15% / +8% / +4% / +1%. BCa
  (0.83) and a bootstrap-t on the linearised standard error (0.87) did worse at 10 pairs (150 data sets);
- runs: combine_runs_interval overall 0.95-0.97, per scene 0.92-0.99, with or without a shared run effect;
- ranking: identical methods split off rank 1 in 0.27 (5 methods) / 0.53 (10) of tables -> 0.025 / 0.017
  (2 methods: 0.033);
- bags (`bags --sims 400 --resamples 1000`, 1011 s): two multiview methods on the same 65 bags (4 strata of 8-25),
  a common bag effect of sd 1 (0.3) in log error plus 5-15% of bags failing for both: paired_bags covers the true
  B - A 0.950-0.955 (0.943-0.955) with mean width 0.019-0.038 (0.017-0.026), type-I error of the verdict rule 0.033
  (0.045), power 1.000 at B - A = +0.033 and +0.066; the unpaired bootstrap of B - A is 7-14 times wider (0.26;
  0.19-0.20, coverage 1.000) and excludes 0 in 0.000 (0.005 / 0.100) of data sets; the two 95% intervals were never
  disjoint (0.000 everywhere): the unpaired ranks shared rank 1 for every one of these differences.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.metrics.uncertainty import (  # noqa: E402
    bag_intervals,
    combine_runs_interval,
    maa_from_errors,
    maa_intervals,
    pair_scores,
    paired_bags,
    paired_bootstrap,
    paired_relative,
    rank_with_ties,
    stratified_interval,
)

# scene kinds: LogNormal(mu, sigma) error in degrees, failure probability
KINDS = {"easy": (-1.0, 0.5, 0.02), "good": (0.0, 0.7, 0.05), "mid": (0.5, 0.8, 0.10), "hard": (1.2, 0.9, 0.20)}


def true_maa(mu: float, sigma: float, fail: float, tau: int = 10) -> float:
    return float(np.mean([(1 - fail) * stats.lognorm.cdf(k, sigma, scale=math.exp(mu)) for k in range(1, tau + 1)]))


def draw(rng, n, mu, sigma, fail):
    e = rng.lognormal(mu, sigma, n)
    e[rng.random(n) < fail] = np.inf
    return e


def records(errs: dict) -> list[dict]:
    return [{"scene": s, "pair": f"p{i}", "err": float(x)} for s, e in errs.items() for i, x in enumerate(e)]


def intervals(sims: int, resamples: int) -> None:
    print("== maa_intervals: coverage of the true mAA(10) [mean width]; 'plain' = percentile bootstrap without "
          "the pseudo-scores")
    for label, sizes in (("quick", {"easy": 12, "good": 10, "mid": 8}), ("quick", {"mid": 10, "hard": 12, "good": 12}),
                         ("protocol", {"easy": 55, "good": 40, "mid": 33}),
                         ("protocol", {"mid": 55, "hard": 40, "good": 73})):
        truth = {s: true_maa(*KINDS[s]) for s in sizes}
        overall = float(np.mean(list(truth.values())))
        rng = np.random.default_rng(1)
        hit = {k: [0, 0] for k in ["overall", *sizes]}
        width = {k: [0.0, 0.0] for k in hit}
        for i in range(sims):
            errs = {s: draw(rng, n, *KINDS[s]) for s, n in sizes.items()}
            ci = maa_intervals(records(errs), taus=(10,), n_resamples=resamples, seed=i)
            groups = [pair_scores(errs[s]) for s in sizes]
            plain = {"overall": stratified_interval(groups, [1 / len(groups)] * len(groups), n_resamples=resamples,
                                                    seed=i)}
            for s, g in zip(sizes, groups):
                plain[s] = stratified_interval([g], [1.0], n_resamples=resamples, seed=i)
            for k in hit:
                t = overall if k == "overall" else truth[k]
                new = ci["mAA10_ci"] if k == "overall" else ci["scenes"][k]["mAA10_ci"]
                for j, c in enumerate((plain[k], new)):
                    hit[k][j] += c[0] <= t <= c[1]
                    width[k][j] += (c[1] - c[0]) / sims
        print(f"  {label:8s} " + "; ".join(
            f"{k}{'' if k == 'overall' else f' ({sizes[k]} pairs, true {truth[k]:.3f})'}: plain {hit[k][0] / sims:.3f} "
            f"[{width[k][0]:.3f}] -> {hit[k][1] / sims:.3f} [{width[k][1]:.3f}]" for k in hit), flush=True)


PAIRED = {"a": (0.5, 0.8, 0.10), "b": (1.2, 0.9, 0.20), "c": (0.0, 0.7, 0.05)}


def paired_draw(rng, n, shrink, runs=1, run_sd=0.0, with_runs=True):
    """A and B on the same pairs (shared difficulty and shared hard failures), B's errors scaled by ``shrink``;
    per run, per-pair seed noise (LogNormal(0, 0.4)) and optionally a run effect exp(N(0, run_sd)) on every pair
    of every scene of that run (each configuration's runs their own). ``with_runs``: records carry their run."""
    base = {s: (rng.lognormal(mu, sigma, n), rng.random(n) < fail) for s, (mu, sigma, fail) in PAIRED.items()}
    a, b = [], []
    for sh, out in ((1.0, a), (shrink, b)):
        for k in range(runs):
            g = math.exp(rng.normal(0, run_sd)) if run_sd else 1.0
            for s, (difficulty, hard) in base.items():
                e = sh * difficulty * rng.lognormal(0, 0.4, n) * g
                e[hard | (rng.random(n) < 0.03)] = np.inf
                out += [{"scene": s, "pair": f"p{i}", "err": float(x), **({"run": k} if with_runs else {})}
                        for i, x in enumerate(e)]
    return a, b


def paired_truth(shrink: float) -> float:
    rng = np.random.default_rng(99)
    n = 400_000
    out = []
    for mu, sigma, fail in PAIRED.values():
        difficulty = rng.lognormal(mu, sigma, n)
        hard = rng.random(n) < fail
        v = []
        for sh in (1.0, shrink):
            e = sh * difficulty * rng.lognormal(0, 0.4, n)
            e[hard | (rng.random(n) < 0.03)] = np.inf
            v.append(pair_scores(e).mean())
        out.append(v[1] - v[0])
    return float(np.mean(out))


def paired(sims: int, resamples: int) -> None:
    print("== paired_bootstrap (3 scenes): rate of p < 0.05 / CI excluding 0 / significant (the verdict rule), "
          "and CI coverage of the true B - A")
    for n, runs, run_sd, with_runs in ((10, 1, 0.0, True), (25, 1, 0.0, True), (25, 3, 0.0, True),
                                       (25, 3, 0.15, False), (25, 3, 0.15, True)):
        print(f"  {n} pairs/scene, {runs} run(s), run effect sd {run_sd}"
              + ("" if runs == 1 else ", records with their run" if with_runs else ", runs pooled (no run index)"))
        for shrink in (1.0, 0.8, 0.65):
            truth = paired_truth(shrink) if shrink != 1.0 else 0.0
            rng = np.random.default_rng(5)
            rej = excl = sig = cov = 0
            for i in range(sims):
                a, b = paired_draw(rng, n, shrink, runs, run_sd, with_runs)
                r = paired_bootstrap(a, b, seed=i, n_resamples=resamples)
                rej += r["p_value"] < 0.05
                excl += not (r["ci"][0] <= 0 <= r["ci"][1])
                sig += r["significant"]
                cov += r["ci"][0] <= truth <= r["ci"][1]
            print(f"    true B - A {truth:+.4f}: p<0.05 {rej / sims:.3f}  CI excludes 0 {excl / sims:.3f}  significant {sig / sims:.3f}  "
                  f"CI coverage {cov / sims:.3f}", flush=True)


def relative_truth(shrink: float, n: int = 1_000_000) -> float:
    """The true (mAA_B - mAA_A) / mAA_A of :func:`paired_draw`'s model (one run, scenes weighted alike): each
    configuration's mAA(10) by Monte Carlo over ``n`` pairs per scene, then their ratio."""
    rng = np.random.default_rng(98)
    m = np.zeros(2)
    for mu, sigma, fail in PAIRED.values():
        difficulty = rng.lognormal(mu, sigma, n)
        hard = rng.random(n) < fail
        for j, sh in enumerate((1.0, shrink)):
            e = sh * difficulty * rng.lognormal(0, 0.4, n)
            e[hard | (rng.random(n) < 0.03)] = np.inf
            m[j] += pair_scores(e).mean() / len(PAIRED)
    return float((m[1] - m[0]) / m[0])


def relative(sims: int, resamples: int) -> None:
    print("== paired_relative (3 scenes, one run): CI coverage of the true (mAA_B - mAA_A) / mAA_A [mean width, "
          "misses below / above]")
    truths = {shrink: relative_truth(shrink) for shrink in (0.8, 0.65, 1.3)}
    for n in (6, 10, 15, 30, 73):
        for shrink, truth in truths.items():
            rng = np.random.default_rng(7)
            cov = below = above = 0
            width = 0.0
            for i in range(sims):
                a, b = paired_draw(rng, n, shrink)
                ci = paired_relative(a, b, seed=i, n_resamples=resamples)["ci"]
                cov += ci[0] <= truth <= ci[1]
                below += truth < ci[0]
                above += truth > ci[1]
                width += min(ci[1] - ci[0], 10.0) / sims
            print(f"  {n:3d} pairs/scene, true relative {truth:+.4f}: coverage {cov / sims:.3f} [{width:.3f}, "
                  f"{below / sims:.3f} / {above / sims:.3f}]", flush=True)


def runs_coverage(sims: int, resamples: int) -> None:
    print("== combine_runs_interval (3 runs, 3 scenes): coverage of the mAA(10) expected over pairs and seeds")
    scenes = {"a": KINDS["mid"], "b": KINDS["hard"], "c": KINDS["good"]}
    for n, run_sd in ((10, 0.0), (10, 0.15), (40, 0.0), (40, 0.15)):
        rng = np.random.default_rng(99)
        truth = {}
        for s, (mu, sigma, fail) in scenes.items():
            big = 400_000
            e = rng.lognormal(mu, sigma, big) * rng.lognormal(0, 0.4, big) * np.exp(rng.normal(0, run_sd, big))
            e[rng.random(big) < fail] = np.inf
            truth[s] = pair_scores(e).mean()
        overall = float(np.mean(list(truth.values())))
        rng = np.random.default_rng(3)
        hit = dict.fromkeys(["overall", *scenes], 0)
        for i in range(sims):
            base = {s: (rng.lognormal(mu, sigma, n), rng.random(n) < fail) for s, (mu, sigma, fail) in scenes.items()}
            runs = []
            for _ in range(3):
                g = math.exp(rng.normal(0, run_sd))
                errs = {}
                for s, (d, hard) in base.items():
                    e = d * rng.lognormal(0, 0.4, n) * g
                    e[hard] = np.inf
                    errs[s] = e
                runs.append(records(errs))
            o = combine_runs_interval(runs, taus=(10,), seed=i, n_resamples=resamples)
            hit["overall"] += o["mAA10_ci"][0] <= overall <= o["mAA10_ci"][1]
            for s in scenes:
                hit[s] += o["scenes"][s]["mAA10_ci"][0] <= truth[s] <= o["scenes"][s]["mAA10_ci"][1]
        print(f"  {n} pairs/scene, run effect sd {run_sd}: " + "  ".join(f"{k} {v / sims:.3f}" for k, v in hit.items()),
              flush=True)


def ranking(sims: int, resamples: int) -> None:
    print("== rank_with_ties: k methods with the same error distribution on the same pairs (25 per scene, 3 scenes): "
          "share of tables where some method is split off rank 1 (should be <= 5%)")
    for k in (2, 5, 10):
        rng = np.random.default_rng(1)
        split = 0
        n_sims = max(50, sims // k)
        for i in range(n_sims):
            base = {s: (rng.lognormal(mu, sigma, 25), rng.random(25) < fail) for s, (mu, sigma, fail) in PAIRED.items()}
            items = []
            for m in range(k):
                errs = {}
                for s, (d, hard) in base.items():
                    e = d * rng.lognormal(0, 0.4, 25)
                    e[hard | (rng.random(25) < 0.03)] = np.inf
                    errs[s] = e
                items.append((f"m{m}", records(errs)))
            split += any(r["rank"] != 1 for r in rank_with_ties(items, n_resamples=resamples, seed=i))
        print(f"  {k} methods: {split / n_sims:.3f} of {n_sims} tables", flush=True)


# (scene, bag size) -> (bags, mu of the bag's difficulty LogNormal(mu, 1.0) in degrees, probability that the bag fails
# for every method): the protocol's sizes at the counts a small scene gives
BAGS = {("A", 5): (25, 0.3, 0.05), ("A", 10): (12, 0.8, 0.10), ("B", 5): (20, 0.6, 0.10), ("B", 10): (8, 1.2, 0.15)}
BAG_SD, PAIR_SD = 1.0, 0.4  # sd of log difficulty across bags (the common bag effect), of per-pair noise


def bag_draw(rng, shrink: float, bag_sd: float = BAG_SD):
    """Bag records of A and of B on the same bags: a pair's error = shrink x the bag's difficulty x its own noise."""
    a, b = [], []
    for (scene, size), (count, mu, fail) in BAGS.items():
        n = size * (size - 1) // 2
        for k in range(count):
            d = rng.lognormal(mu, bag_sd)
            dead = rng.random() < fail
            imgs = [f"{scene}{size}-{k}-{j}" for j in range(size)]
            for sh, out in ((1.0, a), (shrink, b)):
                e = np.full(n, np.inf) if dead else sh * d * rng.lognormal(0, PAIR_SD, n)
                out.append({"scene": scene, "bag_size": size, "bag": k, "images": imgs, "errors": list(e)})
    return a, b


def bag_truth(shrink: float, bag_sd: float = BAG_SD) -> float:
    """True B - A of the multiview mAA(10) (mean over a scene's sizes, then scenes): a bag's mAA is the mean of its
    pairs' scores, so its expectation is a pair's, by Monte Carlo over 10^6 pairs per stratum."""
    rng = np.random.default_rng(97)
    n = 1_000_000
    per_scene: dict = {}
    for (scene, _), (_, mu, fail) in BAGS.items():
        d = rng.lognormal(mu, bag_sd, n)
        alive = rng.random(n) >= fail
        noise = rng.lognormal(0, PAIR_SD, n)
        diff = [pair_scores(np.where(alive, sh * d * noise, np.inf)).mean() for sh in (1.0, shrink)]
        per_scene.setdefault(scene, []).append(diff[1] - diff[0])
    return float(np.mean([np.mean(v) for v in per_scene.values()]))


def bags(sims: int, resamples: int) -> None:
    print("== two multiview methods on the same bags with a common bag effect (4 strata, 8-25 bags): paired_bags vs "
          "the unpaired bootstrap of B - A vs '95% intervals overlap'; coverage of the true B - A [mean width], "
          "rate of 'different'")
    for bag_sd, shrink in ((BAG_SD, 1.0), (BAG_SD, 0.85), (BAG_SD, 0.7), (0.3, 1.0), (0.3, 0.85), (0.3, 0.7)):
        truth = bag_truth(shrink, bag_sd) if shrink != 1.0 else 0.0
        rng = np.random.default_rng(11)
        cov = {"paired": 0, "unpaired": 0}
        width = {"paired": 0.0, "unpaired": 0.0}
        diff = {"paired": 0, "unpaired": 0, "overlap": 0}
        for i in range(sims):
            a, b = bag_draw(rng, shrink, bag_sd)
            p = paired_bags(a, b, seed=i, n_resamples=resamples)
            strata = list(BAGS)
            w = {st: 1.0 / (2 * sum(1 for s2 in strata if s2[0] == st[0])) for st in strata}
            ga = [np.array([maa_from_errors(r["errors"]) for r in a if (r["scene"], r["bag_size"]) == st]) for st in strata]
            gb = [np.array([maa_from_errors(r["errors"]) for r in b if (r["scene"], r["bag_size"]) == st]) for st in strata]
            u = stratified_interval(gb + ga, [w[st] for st in strata] + [-w[st] for st in strata], seed=i,
                                    n_resamples=resamples, expand=True)
            ia, ib = bag_intervals(a, taus=(10,), seed=i, n_resamples=resamples), \
                bag_intervals(b, taus=(10,), seed=i, n_resamples=resamples)
            for k, ci in (("paired", p["ci"]), ("unpaired", u)):
                cov[k] += ci[0] <= truth <= ci[1]
                width[k] += (ci[1] - ci[0]) / sims
            diff["paired"] += p["significant"]
            diff["unpaired"] += not (u[0] <= 0 <= u[1])
            (la, ha), (lb, hb) = ia["mAA10_ci"], ib["mAA10_ci"]
            diff["overlap"] += hb < la or ha < lb
        print(f"  bag effect sd {bag_sd:g}, true B - A {truth:+.4f}: paired {cov['paired'] / sims:.3f} [{width['paired']:.3f}], "
              f"significant {diff['paired'] / sims:.3f}; unpaired {cov['unpaired'] / sims:.3f} "
              f"[{width['unpaired']:.3f}], CI excludes 0 {diff['unpaired'] / sims:.3f}; intervals disjoint "
              f"{diff['overlap'] / sims:.3f}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", nargs="*", default=["intervals", "paired", "relative", "runs", "ranking", "bags"],
                    help="intervals, paired, relative, runs, ranking, bags")
    ap.add_argument("--sims", type=int, default=1000, help="simulated data sets per setting (default 1000)")
    ap.add_argument("--resamples", type=int, default=1000, help="bootstrap resamples / sign patterns (default 1000)")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    for w in a.what:
        {"intervals": intervals, "paired": paired, "relative": relative, "runs": runs_coverage, "ranking": ranking,
         "bags": bags}[w](a.sims, a.resamples)
    print(f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
