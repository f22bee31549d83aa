"""Verdicts: from the studies' test records (and, for the "optimal value differs" findings, their trials) to
"holds", "does not hold" or "inconclusive".

Rules (the report states the one each finding uses):

- ``better`` — the claim "B beats A": the paired bootstrap of mAA(10)(B) - mAA(10)(A) on the same test pairs
  (:func:`pipeline.metrics.uncertainty.paired_bootstrap`). 95% CI containing 0: inconclusive. Otherwise the
  paired sign-flip test must agree (p < 0.05): then CI above 0 holds, below 0 does not hold; when they
  disagree (the percentile bootstrap is too narrow on a few dozen pairs, the sign-flip test is exact) the
  verdict is inconclusive. A finding with several such relations combines them ("all": holds when every
  one holds, does not hold when any is reversed; "any": holds when one holds and none is reversed); the one
  relation that alone decides (a reversal for "all", a relation that holds for "any") must be significant at the
  Bonferroni level 0.05 / m over the m relations.
  With tuning replicates (``--replicates K``, K >= 2 for both studies) the difference, its CI and p come from
  :func:`pipeline.metrics.replicates.replicated_difference` of the K x N per-pair mAA(10) scores (each replicate's
  mean over its test runs, scene-weighted): variance components of replicates x pairs (pairs, tuning and seed noise
  each counted once) and a t test, so the interval holds the tuning variance; a verdict needs K >= 3 on both sides
  (else inconclusive); P(B > A) for one new tuning of each, with its interval, is reported beside it. With K = 1
  every verdict says the tuning variance was not measured.
- ``small_gain`` — the claim "B adds at most a little over A": holds when the upper end of the CI of B - A is
  <= SMALL_GAIN (in mAA(10), 0..1), does not hold when its lower end is above SMALL_GAIN, inconclusive
  otherwise (a CI containing 0 but reaching past the margin says nothing either way).
- ``regions`` — "the optimal value of a parameter differs": each study's *flat region* is the range of the
  parameter over its feasible completed trials whose validation mAA(10) lies within the 95% interval of the
  best trial (value >= the interval's lower end). Two studies *differ* when their flat regions do not overlap;
  they are the *same* when both flat regions fit in one band (r: 0.05 wide; eta: a factor
  1.5), i.e. the data pin both optima to one value; otherwise (overlapping but wide regions: too few pairs or
  trials to tell) the comparison is *unclear*. A group of several studies differs
  when some pair differs and is the same when every pair is. The finding holds when every group differs,
  does not hold when some group is the same, and is inconclusive otherwise (also when a study is missing).
"""
from __future__ import annotations

import math

from pipeline.metrics.uncertainty import (
    DEFAULT_LEVEL,
    bonferroni,
    combine_runs_interval,
    paired_bootstrap,
    paired_direction,
    paired_relative,
)
from tuner.findings.definitions import SMALL_GAIN, Finding

HOLDS, FAILS, UNSURE, NOT_RUN = "holds", "does not hold", "inconclusive", "not run"
#: a finding `tune findings --only` did not select and whose studies are not all finished (its report says the command)
NOT_RUN_YET = "not run yet"
#: the band two flat regions must fit in to count as the same optimum: ("abs", width) or ("ratio", max / min)
SAME_BAND = {"ratio": ("abs", 0.05), "threshold": ("ratio", 1.5)}
#: the unit of a region parameter's values (the ratio test r has none)
UNITS = {"threshold": "px"}


def directional(ci, p_value: float | None = None, level: float = DEFAULT_LEVEL) -> str:
    """The ``better`` rule on the CI of B - A (and the paired test's p-value, when given): the verdict of
    :func:`pipeline.metrics.uncertainty.paired_direction`, the rule `tune compare` uses too."""
    return {1: HOLDS, -1: FAILS, 0: UNSURE}[paired_direction(ci, p_value, level)]


def small_gain(ci, margin: float = SMALL_GAIN) -> str:
    """The ``small_gain`` rule on the CI of B - A."""
    lo, hi = float(ci[0]), float(ci[1])
    if hi <= margin:
        return HOLDS
    if lo > margin:
        return FAILS
    return UNSURE


def combine(statuses: list[str], how: str = "all") -> str:
    if not statuses:
        return UNSURE
    if how == "any":
        if FAILS not in statuses and HOLDS in statuses:
            return HOLDS
        return FAILS if all(s == FAILS for s in statuses) else UNSURE
    if FAILS in statuses:
        return FAILS
    return HOLDS if all(s == HOLDS for s in statuses) else UNSURE


# ------------------------------------------------------------------------------------------ regions

def flat_region(trials: list, best: tuple, ci_low: float, param: str) -> list | None:
    """[min, max] of ``param`` over the trials (params, value) with value >= ``ci_low``; None if the parameter
    was not searched. Always contains the best trial's value."""
    vals = [p[param] for p, v in trials if param in p and v >= ci_low]
    if param in best[0]:
        vals.append(best[0][param])
    if not vals:
        return None
    return [float(min(vals)), float(max(vals))]


def compare_regions(a: dict, b: dict, param: str = "ratio") -> str:
    """'differs' / 'same' / 'unclear' for two {"optimum", "region"} dicts (see the module docstring)."""
    ra, rb = a["region"], b["region"]
    if ra[1] < rb[0] or rb[1] < ra[0]:
        return "differs"
    lo, hi = min(ra[0], rb[0]), max(ra[1], rb[1])
    kind, width = SAME_BAND.get(param, ("abs", 0.0))
    narrow = (hi - lo <= width) if kind == "abs" else (lo > 0 and hi / lo <= width)
    return "same" if narrow else "unclear"


def group_status(regions: dict, roles, param: str = "ratio") -> tuple[str, list]:
    """(differs / same / unclear, pairwise [(role a, role b, status)]) of a group; a missing study: unclear."""
    present = [r for r in roles if regions.get(r)]
    pairs = [(a, b, compare_regions(regions[a], regions[b], param)) for i, a in enumerate(present)
             for b in present[i + 1:]]
    if len(present) < len(roles) or not pairs:
        st = "differs" if any(p[2] == "differs" for p in pairs) else "unclear"
        return st, pairs
    if any(p[2] == "differs" for p in pairs):
        return "differs", pairs
    if all(p[2] == "same" for p in pairs):
        return "same", pairs
    return "unclear", pairs


# ------------------------------------------------------------------------------------------ per finding

def _replicated(*outcomes) -> bool:
    """Whether every outcome has tuning replicates (K >= 2): then its comparisons hold the tuning variance."""
    return all(o.others for o in outcomes)


def _replicate_scores(o, tau: int = 10) -> list[dict]:
    """Per replicate of ``o``: {(scene, pair): the pair's mAA(tau) score averaged over the replicate's test runs}."""
    import numpy as np

    from pipeline.metrics.uncertainty import pair_scores
    out = []
    for r in o.replicates():
        per_run = []
        for run in r.test_runs or []:
            sc = pair_scores([x["err"] for x in run], tau)
            per_run.append({(str(x["scene"]), str(x["pair"])): float(v) for x, v in zip(run, sc)})
        keys = _common(per_run) if per_run else set()
        out.append({k: float(np.mean([d[k] for d in per_run])) for k in keys})
    return out


def _common(scores: list[dict]) -> set:
    """The pairs every replicate of ``scores`` (:func:`_replicate_scores`) scored."""
    return set.intersection(*(set(d) for d in scores))


def _matrix(scores: list[dict], keys: list):
    """K x N: each replicate's score of each pair of ``keys``."""
    import numpy as np
    return np.array([[d[k] for k in keys] for d in scores])


def replicated_relation(oa, ob, n_resamples: int, seed: int = 0, level: float = DEFAULT_LEVEL,
                        tau: int = 10) -> dict:
    """B - A of two replicated studies on the test pairs every replicate of both scored: the K_a x N and K_b x N
    per-pair score matrices, scene-weighted (:func:`pipeline.metrics.replicates.scene_weights`: a plain mean is the benchmark's
    mean over scenes), into :func:`pipeline.metrics.replicates.replicated_difference` (variance components, t with
    Satterthwaite df). Keys as :func:`paired_bootstrap`'s, plus ``p_b_beats_a`` (with ``p_b_beats_a_ci``),
    ``detectable`` (80% power), ``plan`` and ``replicates`` [K_a, K_b]."""
    import numpy as np

    from pipeline.metrics.replicates import replicated_difference, scene_weights
    sa, sb = _replicate_scores(oa, tau), _replicate_scores(ob, tau)
    in_a, in_b = _common(sa), _common(sb)
    keys = sorted(in_a & in_b)
    strata = np.array([k[0] for k in keys])
    scale = scene_weights(strata)[None, :]
    a, b = _matrix(sa, keys) * scale, _matrix(sb, keys) * scale
    d = replicated_difference(b, a, strata, alpha=1 - level, seed=int(seed))
    return {"mAA10_a": float(a.mean()), "mAA10_b": float(b.mean()), "difference": d.diff, "ci": [d.low, d.high],
            "p_value": d.p_value, "p_b_beats_a": d.p_a_beats_b,
            "p_b_beats_a_ci": list(d.p_a_beats_b_ci) if d.p_a_beats_b_ci else None, "df": d.df,
            "detectable": d.mde, "plan": d.plan, "verdict_allowed": d.verdict_allowed, "pairs": len(keys),
            "dropped_a": len(in_a - in_b), "dropped_b": len(in_b - in_a), "replicates": [len(sa), len(sb)]}


def _difference(oa, ob, n_resamples: int, seed: int, level: float = DEFAULT_LEVEL) -> dict:
    """B - A on the same test pairs: :func:`replicated_relation` when both studies have replicates, else the paired
    bootstrap of their test runs."""
    if _replicated(oa, ob):
        return replicated_relation(oa, ob, n_resamples, seed, level)
    return paired_bootstrap(_flat(oa.test_runs), _flat(ob.test_runs), tau=10, n_resamples=n_resamples, seed=seed,
                            level=level)


def _flat(runs) -> list:
    """The test runs' records in one list, each with its run index (run k of two studies: the k-th seed), which
    lets the paired bootstrap see a run effect shared by all pairs (pipeline.metrics.uncertainty.paired_bootstrap)."""
    return [{**r, "run": k} for k, run in enumerate(runs) for r in run]


def study_figures(o, n_resamples: int) -> dict:
    """What a finding reports of one study: test mAA(10) (test.json's mean over runs) with its 95% interval
    (:func:`combine_runs_interval` of the runs' pair records), the frozen parameters, Gamma_max."""
    d = {"study": o.name, "label": o.spec.text(), "ok": o.ok}
    if o.ran_now is not None:
        d["ran_now"] = dict(o.ran_now)
    if not o.ok:
        d["reason"] = o.reason
        if o.compute:  # it ran trials (a calibration) and could not be frozen: the run's compute still counts them
            d.update(compute=dict(o.compute), frozen=o.frozen is not None)
        return d
    budget = (o.attrs.get("budget") or {})
    from tuner.diagnostics import gamma_ceiling_warning
    d.update(params=(o.frozen or {}).get("params"), fixed=(o.frozen or {}).get("fixed"),
             gamma_max=budget.get("gamma_max"), validation_mAA10=(o.frozen or {}).get("value"),
             trials=len(o.trials), compute=dict(o.compute or {}),
             # Gamma_max at the search ceiling is a lower bound (the budget never bound it), not a measured cap;
             # the freeze's warnings (that, an optimum on a bound of the space) qualify the frozen values shown
             gamma_max_at_ceiling=gamma_ceiling_warning(budget) is not None, trials_over_budget=o.over_budget,
             warnings=[str(w) for w in (o.frozen or {}).get("warnings") or []])
    if o.test is not None and o.test_runs:
        ci = combine_runs_interval(o.test_runs, taus=(5, 10), n_resamples=n_resamples)
        mean = o.test.get("mean") or {}
        d.update(mAA10=mean.get("mAA10"), mAA10_ci=ci["mAA10_ci"], mAA5=mean.get("mAA5"), mAA5_ci=ci["mAA5_ci"],
                 mAA10_records=ci["mAA10"], test_runs=len(o.test_runs), pairs=(o.test.get("data") or {}).get("pairs"),
                 within_budget=(o.test.get("budget") or {}).get("within_budget"), records=o.records_note,
                 test_file=o.test_path)
        if o.others:
            d["replicated"] = replicated_figures(o, n_resamples)
            d["mAA10"], d["mAA10_ci"] = d["replicated"]["mAA10"], d["replicated"]["mAA10_ci"]
    return d


def replicated_figures(o, n_resamples: int) -> dict:
    """The tuned figure of a replicated study: the mean test mAA(10) over its K replicates with the two-level
    interval (:func:`pipeline.metrics.replicates.replicated_maa_interval`, what `tune --replicates` reports), each
    replicate's study, seed-derived name, frozen parameters and own mAA(10), and the spread of r, eta, Gamma."""
    import numpy as np

    from pipeline.metrics.replicates import replicated_maa_interval
    from tuner.replicates import param_spread
    scores = _replicate_scores(o)
    keys = sorted(_common(scores))
    iv = replicated_maa_interval(_matrix(scores, keys), np.array([k[0] for k in keys]), n_boot=int(n_resamples), seed=0)
    each = [{"study": r.name, "params": (r.frozen or {}).get("params"), "mAA10": (r.test or {}).get("mean", {}).get("mAA10")}
            for r in o.replicates()]
    spread = {p: [lo, hi] for p, (lo, hi) in param_spread([e["params"] for e in each]).items()}
    return {"K": len(scores), "mAA10": iv.mean, "mAA10_ci": [iv.low, iv.high], "se_pairs": iv.se_pairs,
            "se_between": iv.se_between, "pairs": len(keys), "replicates": each, "spread": spread}


def _validation_value(o) -> float:
    """The validation mAA(10) of a study's frozen trial (the best feasible trial's when no frozen value)."""
    v = (o.frozen or {}).get("value")
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    return float(o.best[1]) if o.best else float("-inf")


def relation(outcomes: dict, a: str, b: str, n_resamples: int, seed: int = 0) -> dict | None:
    oa, ob = outcomes.get(a), outcomes.get(b)
    if not (oa and ob and oa.ok and ob.ok and oa.test_runs and ob.test_runs):
        return None
    pb = _difference(oa, ob, n_resamples, seed)
    ma = pb["mAA10_a"]
    out = {"a": a, "b": b, "mAA10_a": ma, "mAA10_b": pb["mAA10_b"], "difference": pb["difference"],
           "relative": (pb["difference"] / ma) if ma else None, "relative_ci": None, "ci": pb["ci"],
           "p_value": pb["p_value"], "pairs": pb["pairs"], "dropped": [pb["dropped_a"], pb["dropped_b"]]}
    if "replicates" in pb:  # the replicated comparison: P(B > A) with its interval; no joint ratio bootstrap
        out.update({k: pb[k] for k in ("p_b_beats_a", "p_b_beats_a_ci", "detectable", "plan", "replicates",
                                       "verdict_allowed")})
    else:
        rel = paired_relative(_flat(oa.test_runs), _flat(ob.test_runs), tau=10, n_resamples=n_resamples, seed=seed)
        out["relative_ci"] = rel["ci"]
    return out


def _bonferroni_decider(computed: list, statuses: list[str], how: str, outcomes: dict, n_resamples: int,
                        seed: int) -> list[str]:
    """The status that alone decides a combined verdict (``all``: one reversal, does not hold; ``any``: one relation
    that holds) must be significant at the Bonferroni level over the m relations, 0.05 / m: at 0.05 each, m claimed
    '>' of which some are truly equal gave a false verdict up to m times as often as the stated 5%. The other way
    (``all`` holding: every relation holds at 0.05) is an intersection-union test, valid at 0.05 as it is. A status
    not confirmed at 0.05 / m becomes inconclusive; the relation records ``level`` (the confirming CI level)."""
    m = sum(1 for _, c in computed if c is not None)
    decider = FAILS if how == "all" else HOLDS
    if m < 2 or decider not in statuses:
        return statuses
    level, _, resamples = bonferroni(DEFAULT_LEVEL, m, n_resamples)
    out = list(statuses)
    for i, ((roles, c), st) in enumerate(zip(computed, statuses)):
        if st != decider or c is None:
            continue
        oa, ob = outcomes[roles[0]], outcomes[roles[1]]
        pb = _difference(oa, ob, resamples, seed, level)
        c["level"], c["ci_at_level"], c["p_value_at_level"] = level, pb["ci"], pb["p_value"]
        if directional(pb["ci"], pb["p_value"], level) != st:
            out[i] = UNSURE
    return out


def analyse(f: Finding, outcomes: dict, n_resamples: int = 2000, seed: int = 0) -> dict:
    """{"measured", "difference", "ci", "p_value", "verdict", "rule"} of finding ``f`` from its studies'
    outcomes (role -> StudyOutcome)."""
    measured = {"studies": {role: study_figures(o, n_resamples) for role, o in outcomes.items()}}
    missing = {role: o.reason for role, o in outcomes.items() if not o.ok}
    if missing:
        measured["missing"] = missing
    out = {"measured": measured, "difference": None, "ci": None, "p_value": None}
    if f.rule in ("better", "small_gain"):
        rels = f.relations
        if f.pick_best_b:  # the best available B, chosen on validation, against the common A
            cands = [(r, b) for r in rels if (b := relation(outcomes, *r, n_resamples, seed)) is not None]
            measured["relations"] = [c for _, c in cands]
            if not cands:
                return {**out, "verdict": NOT_RUN, "measured": {**measured, "reason": _reason(missing)}}
            # chosen by its frozen validation mAA(10), as the protocol chooses settings: the highest *test* value,
            # then tested on those same test pairs, was a maximum of noisy estimates (biased towards B)
            key = max(cands, key=lambda c: _validation_value(outcomes[c[0][1]]))[1]
            measured["key"] = (f"{key['b']} (the best on validation of {', '.join(r[1] for r, _ in cands)}) "
                               f"vs {key['a']}")
            st = small_gain(key["ci"]) if key.get("verdict_allowed", True) else UNSURE
        else:
            computed = [(r, relation(outcomes, *r, n_resamples, seed)) for r in rels]
            measured["relations"] = [c for _, c in computed if c is not None]
            key_roles = f.key or rels[0]
            key = relation(outcomes, *key_roles, n_resamples, seed)
            if key is None:  # the figures of the studies that ran still stand beside "not run" (finding 2's
                # ranking with shared ranks: without it the report ordered them by point estimate, '>' untested)
                return {**out, "verdict": NOT_RUN, "measured": {**measured, **_extras(f, outcomes, n_resamples, seed),
                                                                "reason": _reason(missing)}}
            measured["key"] = f"{key_roles[1]} vs {key_roles[0]}"
            if f.rule == "small_gain":
                st = small_gain(key["ci"]) if key.get("verdict_allowed", True) else UNSURE
            else:
                # a replicated relation with K = 2 on a side has no calibrated verdict (MIN_VERDICT_K): inconclusive
                statuses = [directional(c["ci"], c["p_value"]) if c is not None and c.get("verdict_allowed", True)
                            else UNSURE for _, c in computed]
                statuses = _bonferroni_decider(computed, statuses, f.combine, outcomes, n_resamples, seed)
                for (_, c), s in zip(computed, statuses):
                    if c is not None:
                        c["status"] = s
                st = combine(statuses, f.combine)
                if key.get("verdict_allowed", True) and directional(key["ci"], key["p_value"]) != st:  # the key alone says otherwise: name the deciders
                    measured["decided_by"] = [{"a": c["a"], "b": c["b"], "status": s} for (_, c), s
                                              in zip(computed, statuses) if c is not None and
                                              (s == FAILS if st == FAILS else s != HOLDS if st == UNSURE else True)]
        measured["relative_difference"] = key["relative"]
        # K >= 2 on both sides of the key: its interval holds the tuning variance; else it covers test pairs only
        measured["replicates"] = key.get("replicates") or [1, 1]
        measured["tuning_variance_measured"] = "replicates" in key
        for k in ("p_b_beats_a", "p_b_beats_a_ci", "detectable", "plan", "verdict_allowed"):
            if k in key:
                measured[k] = key[k]
        measured["relative_ci"] = key.get("relative_ci")  # joint bootstrap of the ratio (paired_relative)
        measured["relative_to"] = key["a"]  # the role the relative difference divides by (A of "B vs A")
        extra = _extras(f, outcomes, n_resamples, seed)
        if extra:
            measured.update(extra)
        return {**out, "measured": measured, "difference": key["difference"], "ci": key["ci"],
                "p_value": key["p_value"], "verdict": st}
    # regions
    regions, absent = {}, {}
    for role, o in outcomes.items():
        if not (o.ok and o.best and o.val_ci):
            absent[role] = (o.reason or o.pending or "no result" if not o.ok else
                            "no feasible trial" if not o.best else "no validation interval of its optimum")
            continue
        reg = flat_region(o.trials, o.best, o.val_ci[0], f.region_param)
        if reg is None:
            absent[role] = f"{f.region_param} was not searched"
        else:
            regions[role] = {"optimum": float(o.best[0][f.region_param]), "region": reg,
                             "validation_mAA10": o.best[1], "validation_ci": o.val_ci,
                             "trials_within": sum(1 for p, v in o.trials if v >= o.val_ci[0]), "trials": len(o.trials)}
    measured["regions"] = regions
    if absent:  # why a study has no region (its group then reads 'unclear', and the key difference may be missing)
        measured["regions_missing"] = absent
    measured["parameter"] = f.region_param
    groups, statuses = [], []
    for label, roles in f.groups:
        st, pairs = group_status(regions, roles, f.region_param)
        groups.append({"group": label, "roles": list(roles), "status": st,
                       "pairs": [{"a": a, "b": b, "status": s} for a, b, s in pairs],
                       "missing": [r for r in roles if r not in regions]})
        statuses.append({"differs": HOLDS, "same": FAILS}.get(st, UNSURE))
    measured["groups"] = groups
    # the flat regions are read off replicate 1's trials (a region over several replicates' trials is not defined)
    measured["tuning_variance_measured"] = False
    if not regions:
        return {**out, "measured": {**measured, "reason": _reason(missing)}, "verdict": NOT_RUN}
    first = [r for r in f.groups[0][1] if r in regions]
    diff = regions[first[0]]["optimum"] - regions[first[1]]["optimum"] if len(first) >= 2 else None
    unit = f" ({UNITS[f.region_param]})" if UNITS.get(f.region_param) else ""
    measured["key"] = f"optimal {f.region_param}{unit}: {first[0]} - {first[1]}" if len(first) >= 2 else None
    if diff is None:  # the table and the printed summary say why there is no difference, as for a finding not run
        lost = [r for r in f.groups[0][1] if r not in regions]
        measured["reason"] = (f"no optimal {f.region_param} difference {' - '.join(f.groups[0][1][:2])}: "
                              + "; ".join(f"{r}: {absent.get(r, 'not in this finding')}" for r in lost))
    return {**out, "measured": measured, "difference": diff, "verdict": combine(statuses, "all")}


def _reason(missing: dict) -> str:
    return "; ".join(f"{k}: {v}" for k, v in missing.items()) or "no study produced test results"


def _extras(f: Finding, outcomes: dict, n_resamples: int = 2000, seed: int = 0) -> dict:
    """Finding-specific figures beside the verdict (they do not change it), with the run's resamples and seed."""
    out = {}
    if f.id == 1:  # the paper's figure is the defaults' change relative to tuned: (defaults - tuned) / tuned
        od, ot = outcomes.get("defaults"), outcomes.get("tuned")
        if od and ot and od.ok and ot.ok and od.test_runs and ot.test_runs:
            r = paired_relative(_flat(ot.test_runs), _flat(od.test_runs), tau=10, n_resamples=n_resamples, seed=seed)
            out["relative_change_of_defaults"] = {"relative": r["relative"], "ci": r["ci"]}
    if f.id == 2:
        g = {r: (o.attrs.get("budget") or {}).get("gamma_max") for r, o in outcomes.items() if o.ok}
        out["gamma_max"] = g
        vals = [v for v in g.values() if v]
        if vals:
            out["gamma_max_spread"] = max(vals) / min(vals)
        from pipeline.metrics.uncertainty import rank_with_ties
        items = [(r, _flat(o.test_runs)) for r, o in outcomes.items() if o.ok and o.test_runs]
        if items:
            out["ranking"] = [{k: row[k] for k in ("name", "rank", "mAA10", "shared", "note")}
                              for row in rank_with_ties(items, n_resamples=n_resamples, seed=seed)]
    if f.id == 4:
        out["optimal_ratio"] = {r: ((o.frozen or {}).get("params") or {}).get("ratio") for r, o in outcomes.items()
                                if o.ok}
    return out


__all__ = ["analyse", "directional", "small_gain", "combine", "flat_region", "compare_regions", "group_status",
           "HOLDS", "FAILS", "UNSURE", "NOT_RUN", "NOT_RUN_YET", "DEFAULT_LEVEL"]
