"""Paired comparisons of two configurations on the same pairs (bags): the difference, its interval, a sign-flip
p-value, and the verdict rule."""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from pipeline.metrics.uncertainty.bags import _bag_unit, _bag_weights, bags_differ
from pipeline.metrics.uncertainty.intervals import _expanded_level, _stratified
from pipeline.metrics.uncertainty.scores import DEFAULT_LEVEL, DEFAULT_RESAMPLES, _stats, maa_from_errors, pair_scores

# ------------------------------------------------------------------------------------------ paired test

def _mean_scores(records: Sequence[Mapping], tau: int) -> dict[tuple, float]:
    """(scene, pair) -> score, averaged over duplicate keys (records of repeated runs)."""
    acc: dict[tuple, list[float]] = {}
    for r in records:
        acc.setdefault((r["scene"], _pair_key(r["pair"])), []).append(r["err"])
    return {k: float(pair_scores(v, tau).mean()) for k, v in acc.items()}



def _pair_key(p):
    return tuple(p) if isinstance(p, list) else p



def _sign_flip_p(d: np.ndarray, w: np.ndarray, n_resamples: int, rng: np.random.Generator) -> float:
    """Two-sided p-value of a paired sign-flip (randomisation) test of sum_p w_p d_p = 0.

    Under the null that A and B are exchangeable on every pair (e.g. two draws of the same method), each
    d_p is as likely to be -d_p: the test's size is exact for any score distribution, ties and
    discreteness included, which a bootstrap test's is only asymptotically. p = (1 + #{|D*| >= |D|}) /
    (1 + n_resamples) (the +1 counts the observed sign pattern, so p is never 0); identical inputs
    (every d_p = 0) give exactly 1."""
    wd = w * d
    obs = abs(float(wd.sum()))
    if not np.any(wd):
        return 1.0
    tol = 1e-12 * max(1.0, obs)
    hits, done = 0, 0
    batch = max(1, min(int(n_resamples), 2_000_000 // max(1, wd.size)))
    while done < n_resamples:
        m = min(batch, n_resamples - done)
        eps = rng.integers(0, 2, size=(m, wd.size), dtype=np.int8) * 2 - 1
        hits += int(np.count_nonzero(np.abs(eps @ wd) >= obs - tol))
        done += m
    return float(min(1.0, (1 + hits) / (1 + n_resamples)))



def _run_variance(run_diffs, weights=None) -> tuple[float, int]:
    """(G, R): the variance of the run-to-run effect shared by all pairs in the difference B - A, and the number
    of runs, from ``run_diffs`` = per scene an (R, n_s) array of per-run pair score differences (run k of A with
    run k of B: the same seed). As :func:`combine_runs_interval`: G = max(0, s2 - W), s2 the sample variance of
    the runs' overall differences, W = sum_p w_p^2 v_p their part due to per-pair noise (v_p: the variance of
    pair p's difference over the runs). (0, R) with fewer than two runs."""
    if not run_diffs:
        return 0.0, 0
    R = run_diffs[0].shape[0]
    if R < 2:
        return 0.0, R
    w = list(weights) if weights is not None else [1.0 / len(run_diffs)] * len(run_diffs)  # per scene (stratum)
    per_run = sum(wg * g.mean(axis=1) for g, wg in zip(run_diffs, w))
    W = sum(float(np.sum(np.var(g, axis=0, ddof=1))) * (wg / g.shape[1]) ** 2 for g, wg in zip(run_diffs, w))
    return max(0.0, float(np.var(per_run, ddof=1)) - W), R



def _paired_stats(groups_a, groups_b, n_resamples, seed, level, method, run_diffs=None, weights=None) -> dict:
    """groups_*: per-scene score arrays on the common pairs (same order in a and b); run_diffs: per scene the
    (R, n_s) per-run differences when the records carry their runs (see :func:`paired_bootstrap`); weights: per
    group (default 1 / the group count: scenes weigh alike; multiview strata weigh as the task averages)."""
    S = len(groups_a)
    w_groups = list(weights) if weights is not None else ([1.0 / S] * S if S else [])
    maa_a = float(sum(w * g.mean() for g, w in zip(groups_a, w_groups) if g.size))
    maa_b = float(sum(w * g.mean() for g, w in zip(groups_b, w_groups) if g.size))
    diffs = [b - a for a, b in zip(groups_a, groups_b)]
    ci, se = _stratified(diffs, w_groups, n_resamples, seed, level, method, expand=True)
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    w = np.concatenate([np.full(g.size, wg / g.size) for g, wg in zip(diffs, w_groups) if g.size]) if diffs else d
    p = _sign_flip_p(d, w, int(n_resamples), np.random.default_rng(seed))
    diff = float(sum(wg * g.mean() for g, wg in zip(diffs, w_groups) if g.size))
    G, R = _run_variance(run_diffs, w_groups) if run_diffs is not None else (0.0, 0)
    run_note = None
    if G > 0 and np.any(d):
        # a run effect shared by all pairs: neither the bootstrap over pairs nor the sign flips of pairs see it.
        # Total variance V = V_b + G / R with Welch-Satterthwaite df (G rests on R - 1 degrees of freedom); the CI
        # is widened about the difference by t_df sqrt(V) / (z sqrt(V_b)), and p is the larger of the sign-flip p
        # and that of t = difference / sqrt(V) (both must reject).
        V = se * se + G / R
        df = V * V / ((G / R) ** 2 / (R - 1))
        t = float(_stats().t.ppf(0.5 + level / 2, df))
        z = float(_stats().norm.ppf(0.5 + level / 2))
        if se > 0:
            k = t * math.sqrt(V) / (z * se)
            ci = [diff - (diff - ci[0]) * k, diff + (ci[1] - diff) * k]
        else:
            ci = [diff - t * math.sqrt(V), diff + t * math.sqrt(V)]
        p = max(p, float(2.0 * _stats().t.sf(abs(diff) / math.sqrt(V), df)))
        run_note = {"run_variance": G, "runs": R, "df": df}
    if d.size and 2.0 / 2.0 ** d.size >= round(1.0 - level, 12):
        # n pairs whose sign flips cannot give p < 1 - level (n <= 5 at 95%): no paired test rejects any difference,
        # so the interval from inverting it is the whole range of a score difference (a bootstrap of 1-5 pairs
        # printed [d, d] for one pair). A hand-written rule: scipy has no interval for this case.
        ci = [-1.0, 1.0]
    if not np.any(d):  # identical scores: exactly 0, whatever the rounding of maa_b - maa_a
        diff, ci = 0.0, [0.0, 0.0]
    return {"a": maa_a, "b": maa_b, "difference": diff, "ci": [float(ci[0]), float(ci[1])], "p_value": p,
            "significant": paired_direction(ci, p, level) != 0, "pairs": int(d.size), "run_effect": run_note}



def paired_bootstrap(records_a: Sequence[Mapping], records_b: Sequence[Mapping], tau: int = 10,
                     n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL, *,
                     method: str = "percentile") -> dict:
    """Paired comparison of configuration B against A (the first) on the pairs both evaluated.

    Records are matched on (scene, pair); pairs present in only one are dropped (counted). Duplicate keys
    (records of repeated runs) are averaged per pair, which is exactly the mean of the runs' mAAs.
    ``difference`` = mAA_b - mAA_a ("B vs the first"; > 0: B is better), the overall mAA being the mean
    over scenes. ``ci``: stratified percentile bootstrap of the difference, resampling the *same* pair
    indices for A and B (i.e. resampling per-pair score differences) within each scene, at the expanded level
    of :func:`stratified_interval` (``expand``: the plain one covered 89-90% at 10 pairs per scene). ``p_value``:
    two-sided paired sign-flip randomisation test (see ``_sign_flip_p``: exact size under "A and B are
    exchangeable on each pair"), with the same resample count and seed. "significant": the CI excludes 0 and
    the sign-flip test agrees (:func:`paired_direction`, the one rule for verdicts, shared ranks and "no
    significant difference"; p and the CI come from different resamplings and can disagree at the margin).

    Repeated runs: records that carry their ``run`` index (0, 1, ...: run k of A and of B share the task's k-th
    seed) let the comparison see a run effect shared by all pairs, which averaging each pair over the runs hides
    from both the bootstrap and the sign flips (as :func:`combine_runs_interval` does for one configuration):
    where the runs' differences vary beyond their per-pair noise, the CI is widened and p is the larger of the
    sign-flip p and a t-test's on the total variance (``run_effect``: {"run_variance", "runs", "df"}, else None).
    B = A with a run effect of sd 0.15 in log error (3 runs, 25 pairs x 3 scenes) was "significant" in 27% of
    simulated data sets with the runs pooled, 10.5% with them (G rests on 2 degrees of freedom and is often
    estimated 0); without a run effect 3.5% (pooled 5.8%), at some cost in power (B - A = +0.038: 0.50 against
    0.58). Counting the runs' whole variance instead of G (no subtraction of W) would hold 4.5% but halve that
    power where no run effect exists (``benchmarks/interval_coverage.py paired``).

    Returns ``{"mAA<tau>_a", "mAA<tau>_b", "difference", "ci": [lo, hi], "p_value", "significant",
    "pairs" (common), "dropped_a", "dropped_b" (pairs only in A / only in B), "tau", "level",
    "scenes": {name: {the same keys without "scenes"}}}``. Identical inputs give difference 0,
    ci [0, 0] and p_value 1.0 exactly. Raises ValueError when no pair is common to both."""
    tau = int(tau)
    sa, sb = _mean_scores(records_a, tau), _mean_scores(records_b, tau)
    common = [k for k in sa if k in sb]
    if not common:
        raise ValueError(f"no common (scene, pair) between the two sets of records ({len(sa)} and {len(sb)} "
                         "pairs): they were not evaluated on the same pairs")
    names = []
    for k in common:
        if k[0] not in names:
            names.append(k[0])
    ka, kb = f"mAA{tau}_a", f"mAA{tau}_b"

    def pack(st, dropped_a, dropped_b):
        return {ka: st["a"], kb: st["b"], "difference": st["difference"], "ci": st["ci"], "p_value": st["p_value"],
                "significant": st["significant"], "pairs": st["pairs"], "dropped_a": dropped_a,
                "dropped_b": dropped_b, "tau": tau, "level": level, "run_effect": st["run_effect"]}
    ga = [np.array([sa[k] for k in common if k[0] == n]) for n in names]
    gb = [np.array([sb[k] for k in common if k[0] == n]) for n in names]
    rd = _run_differences(records_a, records_b, common, names, tau)
    out = pack(_paired_stats(ga, gb, n_resamples, seed, level, method, rd),
               len(sa) - len(common), len(sb) - len(common))
    out["scenes"] = {}
    for j, (n, a, b) in enumerate(zip(names, ga, gb)):
        out["scenes"][n] = pack(_paired_stats([a], [b], n_resamples, seed, level, method,
                                              [rd[j]] if rd is not None else None),
                                sum(1 for k in sa if k[0] == n and k not in sb),
                                sum(1 for k in sb if k[0] == n and k not in sa))
    return out



_UNBOUNDED = 1e9  # a relative difference this large stands for "A scores 0 on that resample"



def paired_relative(records_a: Sequence[Mapping], records_b: Sequence[Mapping], tau: int = 10,
                    n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL) -> dict:
    """The relative difference (mAA_b - mAA_a) / mAA_a of B against A on their common pairs (records as for
    :func:`paired_bootstrap`, runs averaged per pair), with its expanded percentile bootstrap interval: the pairs
    are resampled jointly (a pair's A and B scores together, within each scene) and the ratio recomputed on each
    resample, so the interval carries the uncertainty of the denominator too, which dividing the interval of
    B - A by the estimated mAA_a would drop. ``scipy.stats.bootstrap`` with one (2, n_s) sample per scene, at
    the level of Hesterberg's expansion (:func:`stratified_interval`'s ``expand``) computed from the ratio's
    linearisation (d_i - relative * a_i) / mAA_a: the plain percentile interval covered the true ratio 0.86-0.89
    of the time at 6 pairs per scene (3 scenes), 0.87-0.90 at 10, 0.92-0.93 at 15, 0.93-0.95 at 30 and 73; the
    expanded one 0.92-0.94, 0.91-0.93, 0.94, 0.94-0.95 and 0.93-0.94 (``benchmarks/interval_coverage.py
    relative``, 600 data sets: binomial sd 0.009; a ratio of mAAs is skewed, the misses lean to one side).

    Returns ``{"relative": float | None, "ci": [lo, hi] | None, "pairs"}``: None where mAA_a is 0 (no ratio);
    identical scores give 0 and [0, 0]; where some resample has mAA_a = 0 the interval is unbounded above or
    below (inf); on too few pairs for any paired test to reject (n <= 5 at 95%, as :func:`paired_bootstrap`)
    the whole range [-1, inf]."""
    tau = int(tau)
    sa, sb = _mean_scores(records_a, tau), _mean_scores(records_b, tau)
    common = [k for k in sa if k in sb]
    if not common:
        raise ValueError("no common (scene, pair) between the two sets of records")
    names = list(dict.fromkeys(k[0] for k in common))
    samples = [np.array([[sa[k] for k in common if k[0] == n], [sb[k] for k in common if k[0] == n]])
               for n in names]
    w = 1.0 / len(names)
    ma = sum(w * x[0].mean() for x in samples)
    mb = sum(w * x[1].mean() for x in samples)
    if ma <= 0:
        return {"relative": None, "ci": None, "pairs": len(common)}
    rel = float((mb - ma) / ma)
    if all(np.array_equal(x[0], x[1]) for x in samples):
        return {"relative": 0.0, "ci": [0.0, 0.0], "pairs": len(common)}
    if 2.0 / 2.0 ** len(common) >= round(1.0 - level, 12):
        # as paired_bootstrap: on n <= 5 pairs (at 95%) no paired test rejects any difference, so the interval is
        # the whole range of a relative difference, -100% (B scores 0) to unbounded; the percentile bootstrap of
        # the ratio gave one that excluded 0 beside a difference's [-1, 1] (3 pairs: +114% [+43%, +inf%], p 0.26)
        return {"relative": rel, "ci": [-1.0, math.inf], "pairs": len(common)}
    var = [x for x in samples if x.shape[1] >= 2]
    const_a = sum(w * x[0].mean() for x in samples if x.shape[1] < 2)
    const_b = sum(w * x[1].mean() for x in samples if x.shape[1] < 2)
    if not var:
        return {"relative": rel, "ci": [rel, rel], "pairs": len(common)}

    def statistic(*xs, axis=-1):
        a = const_a + sum(w * x[0].mean(axis=axis) for x in xs)
        b = const_b + sum(w * x[1].mean(axis=axis) for x in xs)
        # a resample where A scores 0: an unbounded gain, held as a large finite value (percentiles of inf: nan)
        return np.where(a > 0, (b - a) / np.where(a > 0, a, 1.0), np.where(b > a, _UNBOUNDED, 0.0))
    # Hesterberg's expanded percentile interval, as for B - A (the plain one under-covered on few pairs,
    # ``benchmarks/interval_coverage.py relative``): the level comes from the ratio's linearisation, each pair's
    # (d_i - rel * a_i) / mAA_a (d = b - a), whose stratified mean is the ratio's first-order error
    lin = [(x[1] - x[0] - rel * x[0]) / ma for x in var]
    expanded = _expanded_level(lin, [w] * len(lin), level)
    res = _stats().bootstrap(tuple(var), statistic, n_resamples=int(n_resamples), vectorized=True, paired=False,
                             confidence_level=expanded, method="percentile", rng=np.random.default_rng(seed), axis=-1)
    ci = [float(v) if v < _UNBOUNDED else math.inf
          for v in (res.confidence_interval.low, res.confidence_interval.high)]
    return {"relative": rel, "ci": [min(ci[0], rel), max(ci[1], rel)], "pairs": len(common)}



def _run_differences(records_a, records_b, common, names, tau) -> list[np.ndarray] | None:
    """Per scene (in ``names`` order) the (R, n_s) array of per-run score differences B - A on the ``common``
    pairs, when every record of both carries its ``run`` index and R >= 2 runs of both have every common pair
    (run k of A with run k of B); None otherwise."""
    def by_run(records):
        out: dict = {}
        for r in records:
            if "run" not in r:
                return None
            out.setdefault(r["run"], {}).setdefault((r["scene"], _pair_key(r["pair"])), []).append(r["err"])
        return {k: {key: float(pair_scores(v, tau).mean()) for key, v in d.items()} for k, d in out.items()}
    ra, rb = by_run(records_a), by_run(records_b)
    if not ra or not rb:
        return None
    runs = sorted(set(ra) & set(rb), key=str)
    if len(runs) < 2 or not all(k in ra[r] and k in rb[r] for r in runs for k in common):
        return None
    return [np.array([[rb[r][k] - ra[r][k] for k in common if k[0] == n] for r in runs]) for n in names]



def paired_bags(bags_a: Sequence[Mapping], bags_b: Sequence[Mapping], tau: int = 10,
                n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL) -> dict:
    """:func:`paired_bootstrap` for the multiview task: B against A on the bags both evaluated (bag records as
    for :func:`combine_bag_runs_interval`, each bag's mAA(tau) averaged over the runs; records carrying their
    ``run`` index let the comparison see a run effect). The same bootstrap, sign-flip test, verdict rule and
    keys, with bags for pairs ("pairs": the common bags) and strata (scene, bag size) weighted as the task
    averages them. Bags are matched on their scene, size and images (:func:`_bag_unit`), never on their index
    alone, which names other images under another bag seed or bag count; :func:`bags_differ` says whether two
    sets hold the same bags. Raises ValueError when no bag is common to both."""
    tau = int(tau)

    def scores(records):
        acc: dict = {}
        for r in records:
            acc.setdefault(_bag_unit(r), []).append(maa_from_errors(r["errors"], tau))
        return {k: float(np.mean(v)) for k, v in acc.items()}

    def by_run(records):
        out: dict = {}
        for r in records:
            if "run" not in r:
                return None
            out.setdefault(r["run"], {})[_bag_unit(r)] = maa_from_errors(r["errors"], tau)
        return out
    sa, sb = scores(bags_a), scores(bags_b)
    common = [k for k in sa if k in sb]
    if not common:
        why = bags_differ(bags_a, bags_b) or "they were not evaluated on the same bags"
        raise ValueError(f"no common bag between the two sets of records ({len(sa)} and {len(sb)} bags): {why}")
    names = list(dict.fromkeys(k[0][0] for k in common))
    ra, rb = by_run(bags_a), by_run(bags_b)
    runs = sorted(set(ra) & set(rb), key=str) if ra and rb else []
    paired_runs = len(runs) >= 2 and all(k in ra[r] and k in rb[r] for r in runs for k in common)
    ka, kb = f"mAA{tau}_a", f"mAA{tau}_b"

    def part(scene_names):
        w = _bag_weights((k[0] for k in common if k[0][0] in scene_names), scene_names)
        ga = [np.array([sa[k] for k in common if k[0] == st]) for st in w]
        gb = [np.array([sb[k] for k in common if k[0] == st]) for st in w]
        rd = ([np.array([[rb[r][k] - ra[r][k] for k in common if k[0] == st] for r in runs]) for st in w]
              if paired_runs else None)
        st = _paired_stats(ga, gb, n_resamples, seed, level, "percentile", rd, weights=list(w.values()))
        mine = {k for k in common if k[0][0] in scene_names}
        return {ka: st["a"], kb: st["b"], "difference": st["difference"], "ci": st["ci"], "p_value": st["p_value"],
                "significant": st["significant"], "pairs": st["pairs"],
                "dropped_a": sum(1 for k in sa if k[0][0] in scene_names and k not in mine),
                "dropped_b": sum(1 for k in sb if k[0][0] in scene_names and k not in mine),
                "tau": tau, "level": level, "run_effect": st["run_effect"], "units": "bags"}
    out = part(names)
    out["scenes"] = {n: part([n]) for n in names}
    return out



def format_p(p: float, alpha: float = 0.05) -> str:
    """A p-value to 3 significant digits, with as many more as it takes to stay on its side of ``alpha``: 0.04996
    reads "0.04996", not "0.05" beside a verdict that needs p < 0.05."""
    p, alpha = float(p), round(float(alpha), 12)  # 1 - 0.95 is 0.05000000000000004
    for d in range(3, 10):
        t = f"{p:.{d}g}"
        if (float(t) < alpha) == (p < alpha):
            return t
    return repr(p)



#: the rule of :func:`paired_direction` in words (`tune compare` prints it; the findings report states its own)
DIRECTION_RULE = ("B or A is better only when the 95% CI of B - A excludes 0 and the paired sign-flip test agrees "
                  "(p < 0.05); otherwise no significant difference")



def paired_direction(ci, p_value: float | None = None, level: float = DEFAULT_LEVEL) -> int:
    """Which of two configurations is better from a paired comparison of B - A (:func:`paired_bootstrap`): +1 B,
    -1 A, 0 neither. The CI containing 0 is 0; otherwise the paired sign-flip test must agree (p < 1 - level),
    else 0 too: on a few dozen pairs the percentile bootstrap is too narrow, the sign-flip test is exact (the
    two come from different resamplings and can disagree at the margin). One rule for `tune findings`' verdicts
    (``tuner.findings.analysis.directional``), `tune compare` and the test reports' comparison with a reference;
    ``p_value`` None: the CI alone."""
    lo, hi = float(ci[0]), float(ci[1])
    if lo <= 0.0 <= hi:
        return 0
    if p_value is not None and not float(p_value) < round(1.0 - level, 12):  # 1 - 0.95 is 0.05000000000000004
        return 0  # the exact sign-flip test does not confirm the bootstrap interval
    return 1 if lo > 0 else -1
