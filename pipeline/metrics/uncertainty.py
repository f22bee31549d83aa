"""How sure an mAA is, and whether a difference between two configurations is real.

Everything here rests on one fact: mAA(tau) is *linear* in per-pair scores. With
``score_p = mean over k = 1..tau of [err_p <= k]`` (0 for a failure, err = inf), a scene's mAA is the
mean of its pairs' scores, and the benchmark's overall mAA (the mean over scenes of the per-scene mAA)
is ``sum_p w_p score_p`` with ``w_p = 1 / (n_scenes * n_pairs_in_scene)``. So

- a confidence interval is a bootstrap of that weighted mean, resampling pairs *within* each scene
  (stratified by scene: every resample keeps each scene's pair count and the scenes' equal weights);
- a paired comparison of A and B on the same pairs is the same statistic of ``score_b - score_a``;
- averaging repeated runs pair by pair gives exactly the mean of the runs' mAAs.

Conventions (all functions):

- ``n_resamples`` bootstrap resamples (default 2000), ``seed`` (default 0: the same inputs always give
  the same interval), ``level`` (default 0.95). Intervals are percentile intervals from
  ``scipy.stats.bootstrap`` (``method="BCa"`` is accepted; it falls back to the percentile interval
  where BCa is undefined, e.g. when every resample gives the same value): for an mAA with the pseudo-scores
  below, for a paired difference at the expanded level of :func:`stratified_interval`; rankings compare at
  a Bonferroni level (:func:`rank_with_ties`).
- Intervals are ``[lo, hi]`` lists of floats; keys are ``mAA5_ci``, ``mAA10_ci`` (one per tau).
- Small and easy scenes (:data:`SCORE_RANGE`): the mAA intervals (stereo, multiview, repeated runs) take the
  spread of resamples of each scene's (bag group's) scores together with two pseudo-scores at the ends of a
  score's range, one failed (0) and one perfect (1) -- the "add two" of Agresti & Coull (1998) for a
  proportion, here for a mean of scores bounded in [0, 1] -- and centre it at the plain estimate (the pseudo-
  scores widen the interval, they do not move it). Why: a pair score is bounded, and an easy scene's is
  skewed against 1 with rare failures. The plain percentile bootstrap of 12 pairs of a scene with true
  mAA(10) 0.978 (2% failures) covered the truth 38% of the time (most samples hold no failure: every resample
  is 1.0 and the "95%" interval [1, 1]), 66% at 55 pairs; 10 pairs of a scene at 0.877 70%; three such scenes'
  overall mAA 88%. With the pseudo-scores: 93-100% per scene and 95-99% overall from 8 to 73 pairs per
  scene (conservative at 8-12 pairs), within 10% of the plain width at 33-73 pairs of middling scenes
  (``benchmarks/interval_coverage.py intervals`` measures it). A scene with one pair is resampled the same
  way (one pair says little); a scene without pairs is the constant 0 the task reports. :func:`stratified_interval` adds nothing unless asked (``pseudo``).
- Errors are in degrees; ``inf`` (or the string ``"inf"`` of a JSON file) and NaN count as failures,
  exactly as :func:`pipeline.metrics.pose.mean_average_accuracy` treats them.

numpy + scipy only; nothing above ``pipeline.metrics`` is imported.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from pipeline.metrics.pose import mean_average_accuracy

__all__ = ["pair_scores", "maa_from_errors", "maa_intervals", "bag_intervals", "paired_bootstrap", "paired_direction",
           "DIRECTION_RULE",
           "rank_with_ties", "rank_by_intervals", "combine_runs_interval", "combine_bag_runs_interval",
           "paired_bags", "bags_differ", "is_bag_records", "stratified_interval", "holm", "bonferroni",
           "DEFAULT_RESAMPLES", "DEFAULT_LEVEL", "SCORE_RANGE", "STD_DDOF", "format_p", "paired_relative"]

DEFAULT_RESAMPLES = 2000
DEFAULT_LEVEL = 0.95
#: the standard deviation over repeated test runs is the sample one (``Task.aggregate``, the ``mAA<tau>_std`` of
#: :func:`combine_runs_interval`): the runs are a sample of seeds; ddof 0 reads 0.82 of it at 3 runs
STD_DDOF = 1
#: the range of a pair's (a bag's) mAA score: the two pseudo-scores every scene's resamples include (module doc)
SCORE_RANGE = (0.0, 1.0)


def _stats():
    """scipy.stats, imported on first use: it takes about 1 s to import, and every `tune` command (its help, a
    one-line error) imports this module through the task registry."""
    from scipy import stats
    return stats


# ------------------------------------------------------------------------------------------ scores

def _errors_array(errors) -> np.ndarray:
    """float array of errors; "inf" strings (JSON files) -> inf, None -> inf (a failure)."""
    return np.array([math.inf if e is None else float(e) for e in errors], float)


def pair_scores(errors, tau: int = 10) -> np.ndarray:
    """Per-pair contribution to mAA(tau): the fraction of thresholds 1..tau degrees that the pair's
    error is within (1 = within 1 deg, 0 = above tau deg or failed). mAA(tau) is their mean."""
    e = _errors_array(errors)
    ks = np.arange(1, int(tau) + 1, dtype=float)
    return (e[:, None] <= ks[None, :]).mean(axis=1) if e.size else np.zeros(0)


def maa_from_errors(errors, tau: int = 10) -> float:
    """mAA(tau) of a list of pair errors (degrees; inf = failure). Exactly
    :func:`pipeline.metrics.pose.mean_average_accuracy` (it is called): 0 for no pairs."""
    return mean_average_accuracy(_errors_array(errors), int(tau))


# ------------------------------------------------------------------------------------------ the core

def stratified_interval(groups: Sequence[np.ndarray], weights: Sequence[float], *,
                        n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL,
                        method: str = "percentile", pseudo: Sequence[float] = (), expand: bool = False) -> list[float]:
    """Bootstrap interval of ``sum_g weights[g] * mean(groups[g])``, resampling within each group.

    ``scipy.stats.bootstrap`` with one sample per group (``paired=False`` resamples each sample
    independently, which is exactly the stratified bootstrap), vectorised: 2000 resamples of 55 pairs
    take about a millisecond. Groups of one value are constants (scipy needs two observations per
    sample); with no group of two or more distinct values the interval is ``[v, v]``.

    ``pseudo``: values added to every non-empty group before resampling (the mAA intervals pass
    :data:`SCORE_RANGE`, see the module doc); the resamples' interval is then shifted by the difference between
    the plain weighted mean (the point estimate) and that of the augmented groups, and clipped to the range of
    ``pseudo``.

    ``expand``: Hesterberg's *expanded percentile* interval (Hesterberg 2015, "What teachers should know about
    the bootstrap", Sec. 4.2): the bootstrap distribution of a mean has the plug-in variance, (n - 1) / n of the
    unbiased one, and a percentile interval uses the normal quantile z where the sample's own variance calls for
    Student's t; so the percentiles taken are those of the level whose normal quantile is
    sqrt(V / V_plugin) t_df (V = sum_g w_g^2 s_g^2 / n_g with ddof 1, df by Welch-Satterthwaite over the groups).
    The paired differences use it: at 10 pairs per scene (3 scenes) the plain percentile interval of B - A
    covered the true difference 89-90% of the time, the expanded one 92-94%, 94-96% at 25 pairs
    (``benchmarks/interval_coverage.py paired``). scipy.stats.bootstrap has no such method; it is only the
    level passed to it."""
    return _stratified(groups, weights, n_resamples, seed, level, method, pseudo, expand)[0]


def _expanded_level(groups, weights, level: float) -> float:
    """The level whose percentile interval is Hesterberg's expanded percentile interval at ``level`` (see
    :func:`stratified_interval`); ``level`` itself where no group has two values or all are constant."""
    parts = [(w * w * float(np.var(g, ddof=1)) / g.size, w * w * float(np.var(g)) / g.size, g.size)
             for g, w in zip(groups, weights) if g.size >= 2]
    V = sum(p[0] for p in parts)
    V_plugin = sum(p[1] for p in parts)
    if V <= 0 or V_plugin <= 0:
        return level
    df = V * V / sum(p[0] ** 2 / (p[2] - 1) for p in parts if p[0] > 0)
    q = math.sqrt(V / V_plugin) * float(_stats().t.ppf(0.5 + level / 2, df))
    return float(1.0 - 2.0 * _stats().norm.sf(q))


def _stratified(groups, weights, n_resamples, seed, level, method="percentile",
                pseudo: Sequence[float] = (), expand: bool = False) -> tuple[list[float], float]:
    """(interval, bootstrap standard error) of :func:`stratified_interval`."""
    if method not in ("percentile", "BCa", "basic"):
        raise ValueError(f"unknown bootstrap method {method!r} (percentile, BCa or basic)")
    groups = [np.asarray(g, float) for g in groups]
    weights = [float(w) for w in weights]
    if not groups:
        return [0.0, 0.0], 0.0
    if expand:
        level = _expanded_level(groups, weights, level)
    point = float(sum(w * (g.mean() if g.size else 0.0) for g, w in zip(groups, weights)))
    if len(pseudo):  # the spread of the resamples with the pseudo-values, centred at the plain estimate
        extra = np.asarray(pseudo, float)
        groups = [np.concatenate([g, extra]) if g.size else g for g in groups]
        (lo, hi), se = _stratified(groups, weights, n_resamples, seed, level, method)
        centre = float(sum(w * (g.mean() if g.size else 0.0) for g, w in zip(groups, weights)))
        lo, hi = point - (centre - lo), point + (hi - centre)
        return [float(min(point, max(lo, extra.min()))), float(max(point, min(hi, extra.max())))], se
    const = float(sum(w * g.mean() for g, w in zip(groups, weights) if g.size == 1))
    var = [(g, w) for g, w in zip(groups, weights) if g.size >= 2]
    if not var or all(np.ptp(g) == 0 for g, _ in var):
        return [point, point], 0.0  # nothing to resample: degenerate interval
    ws = np.array([w for _, w in var])

    def statistic(*samples, axis=-1):
        return const + sum(wi * np.mean(s, axis=axis) for wi, s in zip(ws, samples))

    def run(m):
        res = _stats().bootstrap(tuple(g for g, _ in var), statistic, n_resamples=int(n_resamples), vectorized=True,
                                 paired=False, confidence_level=level, method=m, rng=np.random.default_rng(seed))
        ci = [float(res.confidence_interval.low), float(res.confidence_interval.high)]
        return ci, float(res.standard_error)
    if method == "BCa":
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DegenerateDataWarning: fall back below
            ci, se = run("BCa")
        if all(math.isfinite(v) for v in ci):
            return ci, se
        method = "percentile"
    return run(method)


def _by_key(records: Iterable[Mapping], key_fields: Sequence[str]) -> dict:
    out: dict = {}
    for r in records:
        out.setdefault(tuple(r[k] for k in key_fields), []).append(r)
    return out


def _scene_order(records: Iterable[Mapping], scenes: Sequence[str] | None) -> list[str]:
    names = list(scenes) if scenes is not None else []
    for r in records:
        if r["scene"] not in names:
            names.append(r["scene"])
    return names


# ------------------------------------------------------------------------------------------ stereo

def maa_intervals(records: Sequence[Mapping], taus: Sequence[int] = (5, 10), n_resamples: int = DEFAULT_RESAMPLES,
                  seed: int = 0, level: float = DEFAULT_LEVEL, *, scenes: Sequence[str] | None = None,
                  method: str = "percentile") -> dict:
    """Bootstrap intervals of the stereo mAA(tau), overall and per scene.

    records: stereo pair records (dicts with "scene", "pair" and "err" in degrees, inf = failure) of one
    run. Overall mAA = mean over scenes of per-scene mAA (as ``pipeline.tasks.stereo.combine``); the
    bootstrap resamples pairs within each scene and recomputes that mean. ``scenes``: names of scenes to
    count even if they have no record (their mAA is 0, as the stereo task reports it).

    Returns ``{"mAA5_ci": [lo, hi], "mAA10_ci": [lo, hi], "scenes": {name: {"mAA5_ci": ..., "mAA10_ci": ...}}}``
    (one ``mAA<tau>_ci`` per tau). A scene with one pair gets ``[v, v]``."""
    names = _scene_order(records, scenes)
    per = _by_key(records, ("scene",))
    out: dict = {"scenes": {n: {} for n in names}}
    for tau in taus:
        key = f"mAA{int(tau)}_ci"
        groups = [pair_scores([r["err"] for r in per.get((n,), [])], tau) for n in names]
        w = 1.0 / len(names) if names else 0.0
        out[key] = stratified_interval(groups, [w] * len(groups), n_resamples=n_resamples, seed=seed, level=level,
                                       method=method, pseudo=SCORE_RANGE)
        for n, g in zip(names, groups):
            out["scenes"][n][key] = stratified_interval([g], [1.0], n_resamples=n_resamples, seed=seed, level=level,
                                                        method=method, pseudo=SCORE_RANGE)
    return out


# ------------------------------------------------------------------------------------------ multiview

def bag_intervals(bag_records: Sequence[Mapping], taus: Sequence[int] = (5, 10),
                  n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL, *,
                  scenes: Sequence[str] | None = None, method: str = "percentile") -> dict:
    """Bootstrap intervals of the multiview mAA(tau), overall and per scene, resampling bags.

    bag_records: multiview bag records (dicts with "scene", "bag_size" and "errors", the pair errors of
    the bag in degrees). The multiview mAA is computed as ``pipeline.tasks.multiview`` does: each bag's
    mAA over its pairs; the mean over the bags of one size (``summarize_bags``); the mean over the
    scene's bag sizes (``summarize_scene``); the mean over scenes (``combine``). The bootstrap resamples
    bags within each (scene, bag size) group, so each resample keeps every group's bag count and weight.
    ``scenes``: names to count even without bags (mAA 0 there, as the task reports it). Same keys as
    :func:`maa_intervals`."""
    names = _scene_order(bag_records, scenes)
    groups_of = _by_key(bag_records, ("scene", "bag_size"))
    out: dict = {"scenes": {n: {} for n in names}}
    for tau in taus:
        key = f"mAA{int(tau)}_ci"
        all_g, all_w = [], []
        for n in names:
            sizes = sorted({s for (sc, s) in groups_of if sc == n}, key=float)
            g = [np.array([maa_from_errors(r["errors"], tau) for r in groups_of[(n, s)]]) for s in sizes]
            if g:
                w = [1.0 / len(sizes)] * len(sizes)
            else:  # a scene without bags: mAA 0, a constant (an empty group)
                g, w = [np.zeros(0)], [1.0]
            out["scenes"][n][key] = stratified_interval(g, w, n_resamples=n_resamples, seed=seed, level=level,
                                                        method=method, pseudo=SCORE_RANGE)
            all_g += g
            all_w += [x / len(names) for x in w]
        out[key] = stratified_interval(all_g, all_w, n_resamples=n_resamples, seed=seed, level=level, method=method,
                                       pseudo=SCORE_RANGE)
    return out


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


# ------------------------------------------------------------------------------------------ multiview runs

def _bag_unit(r: Mapping) -> tuple:
    """A bag record's key: ((scene, bag size), its images) -- what makes two records the same bag. The runs of one
    test reconstruct the same bags (only COLMAP's seed varies); two configurations do only where their bags were
    drawn alike (the bag seed and the scene's 3D points; each bag size has its own generator, seeded by the bag seed
    and the size, so another count of one size changes no other size's bags and more bags of a size keep the first
    ones), so the bag index alone can name another bag in each. A record without its images (a test.json of an
    earlier imtune) is keyed by its index, which names the same bag only within one test."""
    imgs = r.get("images")
    st = (r["scene"], int(r["bag_size"]))
    return (st, tuple(str(x) for x in imgs)) if imgs else (st, int(r["bag"]))


def is_bag_records(records: Sequence[Mapping]) -> bool:
    """Whether records are multiview bag records ("scene", "bag_size", "errors"), not stereo pair records."""
    return bool(records) and all("errors" in r and "bag_size" in r for r in records)


def bags_differ(bags_a: Sequence[Mapping], bags_b: Sequence[Mapping]) -> str | None:
    """Why two sets of bag records (each maybe several runs' records) cannot be compared bag by bag, or None when
    they hold the same bags (scene, size and images; :func:`_bag_unit`). A reason names what to do about it."""
    def known(recs):
        return all(r.get("images") for r in recs)
    if not (known(bags_a) and known(bags_b)):
        return ("a test.json of an earlier imtune does not record its bags' images, so its bags cannot be matched "
                "(rerun `tune test` to record them)")
    ka, kb = {_bag_unit(r) for r in bags_a}, {_bag_unit(r) for r in bags_b}
    if ka != kb:
        return (f"the bags differ ({len(ka - kb)} of {len(ka)} bags only in one, {len(kb - ka)} of {len(kb)} only in "
                "the other: another bag seed, bag sizes or counts, scenes, or 3D points)")
    return None


def _bag_weights(strata: Iterable[tuple], scene_names: Sequence[str]) -> dict:
    """{(scene, size): weight} as the multiview task averages: the mean over a scene's bag sizes, then over the
    scenes (a scene without bags counts 0, its weight going to no stratum)."""
    strata = list(dict.fromkeys(strata))
    out = {}
    for n in scene_names:
        mine = [st for st in strata if st[0] == n]
        for st in sorted(mine, key=lambda x: x[1]):
            out[st] = 1.0 / (len(scene_names) * len(mine))
    return out


def combine_bag_runs_interval(runs: Sequence[Sequence[Mapping]], taus: Sequence[int] = (5, 10),
                              n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL) -> dict:
    """:func:`combine_runs_interval` for the multiview task's repeated test runs: ``runs`` one list of bag records
    ("scene", "bag_size", "bag", "errors": the bag's pair errors in degrees) per run. A bag's score is its
    mAA(tau) over its pairs; the bootstrap resamples bags within each (scene, bag size) stratum, weighted as
    :func:`bag_intervals` and the task weigh them, with the same pseudo-scores and run-effect widening. Same
    keys as :func:`combine_runs_interval`."""
    runs = [list(r) for r in runs]
    names = _scene_order([x for run in runs for x in run], None)
    out: dict = {"runs": len(runs), "scenes": {n: {} for n in names}}

    def one(tau, scene_names) -> dict:
        per_run = [{_bag_unit(x): maa_from_errors(x["errors"], tau) for x in run if x["scene"] in scene_names}
                   for run in runs]
        w = _bag_weights((k[0] for pr in per_run for k in pr), scene_names)
        return _combine_runs(per_run, w, n_resamples, seed, level)

    return _per_tau_and_scene(one, taus, names, out)


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


def _item(it) -> tuple[str, Sequence[Mapping]]:
    if isinstance(it, Mapping):
        return str(it["name"]), it["records"]
    name, recs = it
    return str(name), recs


def rank_with_ties(items, tau: int = 10, n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0,
                   level: float = DEFAULT_LEVEL) -> list[dict]:
    """Rank methods by mAA(tau), sharing ranks where a difference is not significant.

    items: ``[(name, records), ...]`` or ``[{"name", "records"}, ...]``, records as for
    :func:`paired_bootstrap` (several runs' records may be concatenated: they are averaged per pair), or multiview
    bag records as for :func:`paired_bags` (every item's: then each comparison is :func:`paired_bags` on the common
    bags, and the mAA the multiview task's weighting of bags, sizes and scenes).
    The methods are ordered by mAA(tau) (highest first; ties keep the given order); each one is compared
    by :func:`paired_bootstrap` with the *leader* of the rank above it (the first, best method holding that rank;
    it as A, this one as B) and shares that rank when the difference is not significant (its CI contains 0, or
    the sign-flip test does not confirm it: ``significant``). Ranks are competition ranks (1, 1, 3): a method
    that differs significantly from the leader gets its position and leads a new rank. Comparing with the leader,
    not the row directly above, keeps small steps from chaining a tie from the top far down (C sharing rank 1
    through B though A and C differ significantly: 14 of 15 rows at rank 1 in a real table). Two methods without
    a common pair are not compared (no shared rank; the note says so).

    Multiplicity: the leader is the best of several noisy estimates and a table makes many comparisons, so each is
    made at the Bonferroni level over the k (k - 1) / 2 pairs of the k methods the ranking could compare
    (``level`` 0.95, 5 methods: the 99.5% CI and p < 0.005; the sign-flip test and the bootstrap get at least 20 /
    alpha resamples, at most 100,000, so that p can reach it). At 5% per comparison, five methods with the same
    error distribution were split off rank 1 in 28% of simulated tables (ten: 56%); Holm over the k - 1
    comparisons actually made still 9% (the leader is selected); over all pairs about 1.5%.

    Returns, best first: ``[{"name", "rank", "mAA<tau>", "shared": bool (rank shared with the rank's leader),
    "comparison": paired_bootstrap overall figures against that leader (None for the first), "note": str}, ...]``."""
    tau = int(tau)
    named = [_item(it) for it in items]
    n_pairs_of_methods = max(1, len(named) * (len(named) - 1) // 2)
    level_each, alpha, resamples_each = bonferroni(level, n_pairs_of_methods, n_resamples)  # every pair (docstring)
    bags = bool(named) and all(is_bag_records(recs) for _, recs in named)
    compare = paired_bags if bags else paired_bootstrap
    vals = [_bag_value(recs, tau) if bags else _pair_value(recs, tau) for _, recs in named]
    order = sorted(range(len(named)), key=lambda i: -vals[i])
    out: list[dict] = []
    for pos, i in enumerate(order):
        name, recs = named[i]
        row = {"name": name, "rank": pos + 1, f"mAA{tau}": vals[i], "shared": False, "comparison": None, "note": ""}
        if out:
            lead = next(k for k, r in enumerate(out) if r["rank"] == out[-1]["rank"])  # the rank's leader
            above = out[lead]
            try:
                cmp = compare(named[order[lead]][1], recs, tau=tau, n_resamples=resamples_each, seed=seed,
                              level=level_each)
            except ValueError:  # evaluated on different pairs: nothing to pair, never a shared rank
                row["note"] = f"not compared with {above['name']}: no common {'bags' if bags else 'pairs'}"
                out.append(row)
                continue
            cmp = {k: v for k, v in cmp.items() if k != "scenes"}
            row["comparison"] = cmp
            lo, hi = cmp["ci"]
            how = (f"{100 * level_each:.3g}% CI, p={format_p(cmp['p_value'], alpha)}" if n_pairs_of_methods == 1 else
                   f"{100 * level_each:.3g}% CI, p={format_p(cmp['p_value'], alpha)} against {alpha:.2g}: Bonferroni "
                   f"over the "
                   f"{n_pairs_of_methods} pairs of {len(named)} methods")
            if not cmp["significant"]:
                row["rank"], row["shared"] = above["rank"], True
                row["note"] = (f"rank shared with {above['name']}: difference {cmp['difference']:+.4f} "
                               f"[{lo:+.4f}, {hi:+.4f}] not significant ({how})")
            else:
                row["note"] = (f"below {above['name']}: difference {cmp['difference']:+.4f} "
                               f"[{lo:+.4f}, {hi:+.4f}] ({how})")
        out.append(row)
    return out


def _pair_value(records: Sequence[Mapping], tau: int) -> float:
    """The stereo mAA(tau) of pair records (runs averaged per pair): the mean over scenes of the scenes' means."""
    by_scene: dict = {}
    for (scene, _), v in _mean_scores(records, tau).items():
        by_scene.setdefault(scene, []).append(v)
    return float(np.mean([np.mean(v) for v in by_scene.values()])) if by_scene else 0.0


def _bag_value(records: Sequence[Mapping], tau: int) -> float:
    """The multiview mAA(tau) of bag records (runs averaged per bag), weighted as the task averages: the mean over
    each (scene, size) stratum's bags, over a scene's sizes, then over the scenes."""
    acc: dict = {}
    for r in records:
        acc.setdefault(_bag_unit(r), []).append(maa_from_errors(r["errors"], tau))
    w = _bag_weights((k[0] for k in acc), _scene_order(records, None))
    return float(sum(wst * np.mean([np.mean(v) for k, v in acc.items() if k[0] == st]) for st, wst in w.items()))


def rank_by_intervals(items: Sequence[Mapping], key: str = "mAA10") -> list[dict]:
    """Rank with ties when only intervals are known (no pair records to pair): each method shares the
    rank above it when its ``<key>_ci`` interval overlaps that of the rank's leader (as :func:`rank_with_ties`).
    Conservative (overlapping 95% intervals can still hide a significant paired difference: two methods on the same pairs are
    positively correlated, which only the paired test uses). items: ``{"name", key, key + "_ci"}``;
    an item without an interval never shares. Same return shape as :func:`rank_with_ties`
    (``comparison`` is None)."""
    order = sorted(range(len(items)), key=lambda i: -float(items[i][key]))
    out: list[dict] = []
    for pos, i in enumerate(order):
        it = items[i]
        row = {"name": str(it["name"]), "rank": pos + 1, key: float(it[key]), "shared": False, "comparison": None,
               "note": ""}
        if out:
            lead = next(k for k, r in enumerate(out) if r["rank"] == out[-1]["rank"])  # the rank's leader
            above = items[order[lead]]
            ci, ci_above = it.get(f"{key}_ci"), above.get(f"{key}_ci")
            if ci and ci_above and ci[1] >= ci_above[0]:
                row["rank"], row["shared"] = out[-1]["rank"], True
                row["note"] = f"rank shared with {above['name']}: 95% intervals overlap (unpaired comparison)"
        out.append(row)
    return out


# ------------------------------------------------------------------------------------------ repeated runs

def _per_tau_and_scene(one, taus, names, out: dict) -> dict:
    """Fill ``out`` (``{"runs", "scenes": {name: {}}}``) with ``one(tau, scene_names)``'s value, interval and std
    per tau, overall and per scene: the keys of :func:`combine_runs_interval`."""
    for tau in taus:
        k = f"mAA{int(tau)}"
        o = one(int(tau), names)
        out[k], out[k + "_ci"], out[k + "_std"] = o["value"], o["ci"], o["std"]
        for n in names:
            o = one(int(tau), [n])
            out["scenes"][n][k], out["scenes"][n][k + "_ci"], out["scenes"][n][k + "_std"] = o["value"], o["ci"], o["std"]
    return out


def _combine_runs(per_run: list[dict], weights: dict, n_resamples: int, seed: int, level: float) -> dict:
    """The estimate of :func:`combine_runs_interval` (steps 1-4) on scores already computed: ``per_run`` one
    ``{(stratum, unit): score}`` per run, ``weights`` {stratum: weight} (summing to 1; a unit weighs its stratum's
    weight / the stratum's unit count). Stereo: strata are scenes, units pairs; multiview: strata are (scene, bag
    size), units bags. Returns {"value", "ci", "std" (the sample std over runs, ddof 1: :data:`STD_DDOF`; 0 for
    one run)}."""
    R = len(per_run)
    z = float(_stats().norm.ppf(0.5 + level / 2))
    keys = list(dict.fromkeys(k for pr in per_run for k in pr))
    groups, wgroups, wpair, vpair = [], [], [], []
    for st, wst in weights.items():
        ks = [k for k in keys if k[0] == st]
        mat = [[pr[k] for pr in per_run if k in pr] for k in ks]
        groups.append(np.array([np.mean(v) for v in mat]) if ks else np.zeros(0))
        wgroups.append(wst)
        for v in mat:
            wpair.append(wst / len(ks))
            vpair.append(np.var(v, ddof=1) if len(v) > 1 else 0.0)
    M = float(sum(w * g.mean() for g, w in zip(groups, wgroups) if g.size))
    run_vals = []
    for pr in per_run:
        run_vals.append(float(sum(wst * np.mean([v for k, v in pr.items() if k[0] == st] or [0.0])
                                  for st, wst in weights.items())))
    (lo, hi), se = _stratified(groups, wgroups, n_resamples, seed, level, pseudo=SCORE_RANGE)
    if R > 1:
        W = float(np.sum(np.square(wpair) * np.asarray(vpair)))
        G = max(0.0, float(np.var(run_vals, ddof=1)) - W)
        if G > 0:
            Vb = se * se  # scipy's bootstrap standard error of the same resampling
            V = Vb + G / R
            # Welch-Satterthwaite: G rests on R - 1 degrees of freedom, V_b on (practically) infinitely many
            df = V * V / ((G / R) ** 2 / (R - 1))
            t = float(_stats().t.ppf(0.5 + level / 2, df))
            if Vb > 0:
                k = t * math.sqrt(V) / (z * math.sqrt(Vb))
                lo, hi = M - (M - lo) * k, M + (hi - M) * k
            else:
                h = t * math.sqrt(V)
                lo, hi = M - h, M + h
    std = float(np.std(run_vals, ddof=STD_DDOF)) if R > STD_DDOF else 0.0
    return {"value": M, "ci": [max(0.0, float(lo)), min(1.0, float(hi))], "std": std}


def combine_runs_interval(runs: Sequence[Sequence[Mapping]], taus: Sequence[int] = (5, 10),
                          n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = DEFAULT_LEVEL) -> dict:
    """Interval of the mean mAA of repeated test runs (same pairs, different estimator seeds), accounting
    for both the sampling of pairs and the run-to-run variation.

    runs: one list of stereo pair records per run. Exactly:

    1. score_{p,r}: pair p's mAA(tau) score in run r; s_p = its mean over the runs that have p. The point
       estimate M = sum_p w_p s_p (w_p = 1 / (n_scenes * n_pairs_in_scene)) is the mean of the runs' mAAs.
    2. [lo, hi]: stratified percentile bootstrap of M over pairs (of the run-averaged scores s_p, with the
       pseudo-scores of :data:`SCORE_RANGE`), with bootstrap variance V_b. It already contains the per-pair seed noise (s_p varies with the seeds).
    3. What it cannot see is a run effect shared by all pairs (machine load under a time budget, a seed
       that is good everywhere). Moment estimate: s2_run = sample variance (ddof 1) of the R runs' mAAs;
       its pair-independent part is W = sum_p w_p^2 v_p, v_p = sample variance of score_{p,r} over runs;
       shared-run variance G = max(0, s2_run - W). Total variance V = V_b + G / R.
    4. The interval is widened about M by k = t_df sqrt(V) / (z sqrt(V_b)): lo' = M - (M - lo) k,
       hi' = M + (hi - M) k, clipped to [0, 1] (z: the normal quantile of ``level``; t_df: Student's t
       with the Welch-Satterthwaite df = V^2 / ((G / R)^2 / (R - 1)), since G rests on R - 1 degrees of
       freedom); where V_b = 0, M -/+ t_df sqrt(V). G = 0 or one run: the bootstrap interval as is.

    Returns ``{"mAA5": M, "mAA5_ci": [lo', hi'], "mAA5_std": the sample std over runs (ddof 1, as the test
    run's "std": :data:`STD_DDOF`; 0 for one run), ..., "runs": R, "scenes": {name: the same per scene}}``."""
    runs = [list(r) for r in runs]
    names = _scene_order([x for run in runs for x in run], None)
    out: dict = {"runs": len(runs), "scenes": {n: {} for n in names}}

    def one(tau, scene_names) -> dict:
        per_run = []  # {(scene, pair): score}
        for run in runs:
            recs = [x for x in run if x["scene"] in scene_names]
            keys = [(x["scene"], _pair_key(x["pair"])) for x in recs]
            per_run.append(dict(zip(keys, pair_scores([x["err"] for x in recs], tau))))
        return _combine_runs(per_run, {n: 1.0 / len(scene_names) for n in scene_names}, n_resamples, seed, level)

    return _per_tau_and_scene(one, taus, names, out)

