"""Which trial a study freezes, how flat its optimum is, and what a test run is compared against.

    from tuner.select import select_trial, flat_region, reference_config
    trial, info = select_trial(study, "one-se")     # the trial to freeze and why
    flat_region(study, best)                         # trials within the optimum's 95% interval

Selection rules (``--select``), all over the study's COMPLETE trials within the budget
(:func:`tuner.protocol.trial_within_budget`, THE feasibility rule):

- ``best``: the highest validation mAA(10) (:func:`tuner.protocol.best_feasible`; ties: the faster, then the
  earlier trial).
- ``one-se``: the one-standard-error rule (Breiman et al.; Hastie, Tibshirani & Friedman, ESL 7.10). SE is the
  best trial's bootstrap standard error, read from its 95% interval as half-width / 1.96. Every trial whose value
  is within one SE of the best is as good as the best given the validation pairs. Among them we freeze the one
  closest to their centroid in normalised (log eta, r, log Gamma) space: the middle of the near-optimal plateau.
  Why this and not "the simplest model" of the classic rule: (eta, r, Gamma) have no complexity order (a larger
  eta is not simpler than a smaller one), but the risk we guard against is concrete: the optimum of the
  validation scenes sits elsewhere on the test scenes, and the point farthest from the plateau's edges is the
  one a shifted plateau is most likely still to contain, whereas the best trial is the one whose value the
  noise of the validation pairs lifted most.
- ``smooth``: the best of a smoothed surface: each trial's value is averaged with the values of its
  ``SMOOTH_K`` nearest neighbours (Euclidean, normalised (log eta, r, log Gamma) space); the trial with the
  highest average is frozen (ties: the higher own value). A lucky trial surrounded by poor ones loses to one in a
  good neighbourhood.
- ``confirmed``: the highest mean over each candidate's own value and its runs at more seeds, after ``tune
  --confirm N`` re-evaluated the N best trials (and the task's defaults) (:mod:`tuner.confirm`); the best trial
  when the study holds no confirmation.
- ``lower-bound``: the highest lower end of the trial's validation 95% interval (the scene-stratified pair
  bootstrap every trial stores as ``mAA10_ci``; ties: the higher value, then the earlier trial). A trial whose
  value is high because a few pairs happened to succeed has a wide interval and a low lower end; one that is good
  on most pairs keeps a high lower end. Trials without a stored interval count with their value as lower end.

Normalised space: each searched numeric parameter mapped to [0, 1] over its search range (log scale where the
space says ``log: true``: eta and Gamma); categorical parameters (the strategy) are not coordinates.

Which rule generalises best from validation to test was measured by ``benchmarks/selection_rules.py``:
on the earlier three-scene Strecha data (leave-one-scene-out, 15 folds) best 0.678, one-se 0.671 (p 0.79), smooth
0.650 (p 0.03); on the six scenes (December 2026, benchmarks/results/default-split-and-freeze-rules.md: 2048 SIFT, DEGENSAC, 14 trials; 24 leave-one-family-out and
12 two-families-vs-two folds) mean held-out mAA(10) one-se 0.565, best 0.556, lower-bound 0.556, smooth 0.538;
best - one-se -0.009 (sign-flip p 0.20), lower-bound - one-se -0.008 (p 0.24), smooth - one-se -0.027 (p 0.01).
Best, one-se and lower-bound cannot be told apart (one-se's lead is within the noise and was a deficit of -0.008
on the three scenes), smooth is worse. ``DEFAULT_RULE`` stays ``best``: a default changes on a measured
difference, and no alternative has one.
"""
from __future__ import annotations

import math

import numpy as np

from pipeline.errors import ImtuneError

RULES = ("best", "one-se", "smooth", "lower-bound")
#: the rule of a study whose best trials were re-evaluated at more seeds (``tune --confirm N``, :mod:`tuner.confirm`)
CONFIRMED = "confirmed"
ALL_RULES = RULES + (CONFIRMED,)
#: the study's user attribute holding the confirmation (tuner.confirm.confirm_candidates)
CONFIRMATION_ATTR = "confirmation"
DEFAULT_RULE = "best"  # benchmarks/selection_rules.py: no rule beats it measurably (benchmarks/results/default-split-and-freeze-rules.md)
SMOOTH_K = 5
Z95 = 1.959963984540054  # normal quantile of 0.975: SE = half-width / Z95

#: the untuned "paper defaults" a test run is compared with (r 0.85 mutual, eta 0.5 px, Gamma 50k)
PAPER_DEFAULTS = {"ratio": 0.85, "strategy": "both", "threshold": 0.5, "max_iters": 50_000,
                  "min_confidence": 0.1}  # LightGlue's published filter_threshold (--matcher lightglue: r's place)
REFERENCE_LABEL = "paper defaults (r 0.85 both, eta 0.5 px, Gamma 50,000)"

PARAM_LABEL = {"threshold": ("eta", "px"), "ratio": ("r", ""), "max_iters": ("Gamma", "")}


def check_rule(rule: str | None) -> str:
    rule = DEFAULT_RULE if rule is None else str(rule)
    if rule not in ALL_RULES:
        raise ImtuneError(f"unknown selection rule {rule!r} (choose {', '.join(ALL_RULES)})")
    return rule


# ------------------------------------------------------------------------------------------ trials

def feasible_trials(study) -> list:
    """COMPLETE trials with a value, within the budget (THE feasibility rule)."""
    from optuna.trial import TrialState

    from tuner.protocol import trial_within_budget
    return [t for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
            if _value(t) is not None and math.isfinite(_value(t)) and trial_within_budget(t)]


def _value(trial) -> float | None:
    """The trial's mAA(10): ``tuner.protocol.trial_value`` (a pareto study's first objective) where it exists."""
    try:
        from tuner.protocol import trial_value
    except ImportError:  # the protocol of before pareto studies
        return None if trial.value is None else float(trial.value)
    v = trial_value(trial)
    return None if v is None else float(v)


def numeric_params(space_spec: dict | None) -> dict[str, dict]:
    """The searched numeric parameters of a (resolved) search-space spec: name -> {low, high, log}."""
    out = {}
    for name, p in ((space_spec or {}).get("params") or {}).items():
        if p.get("type") in ("float", "int") and isinstance(p.get("low"), (int, float)) \
                and isinstance(p.get("high"), (int, float)):
            out[name] = {"low": float(p["low"]), "high": float(p["high"]), "log": bool(p.get("log"))}
    return out


def normalise(value: float, p: dict) -> float:
    """``value`` mapped to [0, 1] over the search range (log scale for log parameters); 0 for a one-point range."""
    lo, hi, v = p["low"], p["high"], float(value)
    if p["log"] and lo > 0 and hi > 0 and v > 0:
        lo, hi, v = math.log(lo), math.log(hi), math.log(v)
    return 0.0 if hi == lo else (v - lo) / (hi - lo)


def coordinates(trials: list, space_spec: dict | None) -> np.ndarray:
    """(n_trials, n_numeric_params) normalised coordinates; a parameter a trial lacks sits at 0.5."""
    ps = numeric_params(space_spec)
    X = np.full((len(trials), len(ps)), 0.5)
    for i, t in enumerate(trials):
        for j, (name, p) in enumerate(ps.items()):
            if name in t.params:
                X[i, j] = normalise(t.params[name], p)
    return X


def interval_of(trial, objective: str = "mAA10") -> list[float] | None:
    ci = (trial.user_attrs or {}).get(f"{objective}_ci")
    return [float(ci[0]), float(ci[1])] if ci and len(ci) == 2 else None


def standard_error(trial, objective: str = "mAA10") -> float | None:
    """The trial's bootstrap standard error: the 95% interval's half-width / 1.96 (None without an interval)."""
    ci = interval_of(trial, objective)
    return None if ci is None else (ci[1] - ci[0]) / (2.0 * Z95)


# ------------------------------------------------------------------------------------------ rules

_SHORT = {"threshold": "eta", "ratio": "r", "max_iters": "Gamma"}  # the notes' names of the searched parameters


def select_trial(study, rule: str | None = None, objective: str = "mAA10", k: int = SMOOTH_K):
    """(trial, info) of ``rule`` (see the module docstring); (None, info) when no trial is feasible.

    info: ``{"rule", "best_trial", "best_value", "note", ...}`` — for one-se also ``se`` and ``within_one_se``
    (trial numbers); for smooth ``k`` and ``smoothed_value``."""
    from tuner.protocol import best_feasible
    rule = check_rule(rule)
    best = best_feasible(study)
    info: dict = {"rule": rule, "best_trial": None if best is None else best.number,
                  "best_value": None if best is None else _value(best), "note": ""}
    from pipeline.tasks import is_timed
    spec = study.user_attrs.get("search_space_resolved")
    # a multiview study has no budget and searches r alone: its notes named the stereo budget, eta and Gamma
    within = " within the budget" if is_timed(study.user_attrs.get("task", "stereo")) else ""
    ps = sorted(numeric_params(spec).items(), key=lambda x: list(_SHORT).index(x[0]) if x[0] in _SHORT else len(_SHORT))
    where = "normalised (" + ", ".join(("log " if p["log"] else "") + _SHORT.get(n, n) for n, p in ps) + ")"
    if best is None or rule == "best":
        info["note"] = f"the highest validation value{within}"
        return best, info
    if rule == CONFIRMED:
        got = pick_confirmed(study)
        if got is None:
            info["note"] = "no confirmation stored (tune --confirm N): the best trial"
            return best, info
        info.update(got[1])
        return got[0], info
    cands = feasible_trials(study)
    X = coordinates(cands, spec)
    values = np.array([_value(t) for t in cands])
    if rule == "one-se":
        se = standard_error(best, objective)
        if se is None:
            info["note"] = "no interval stored for the best trial (older imtune): the best trial"
            return best, info
        idx = [i for i, v in enumerate(values) if v >= _value(best) - se - 1e-12]
        centre = X[idx].mean(axis=0)
        d = np.linalg.norm(X[idx] - centre, axis=1) if X.shape[1] else np.zeros(len(idx))
        # closest to the plateau's centre; ties: the higher value, then the earlier trial
        pick = min(idx, key=lambda i: (round(float(d[idx.index(i)]), 12), -values[i], cands[i].number))
        info.update(se=se, within_one_se=sorted(cands[i].number for i in idx),
                    note=f"{len(idx)} trial(s) within one SE ({se:.4f}) of the best: the one closest to their "
                         f"centre in {where}")
        return cands[pick], info
    if rule == "lower-bound":
        lows = np.array([(interval_of(t, objective) or [v])[0] for t, v in zip(cands, values)])
        pick = max(range(len(cands)), key=lambda i: (round(float(lows[i]), 12), values[i], -cands[i].number))
        info.update(lower_bound=float(lows[pick]),
                    note=f"the highest lower end of the validation 95% interval ({lows[pick]:.3f})")
        return cands[pick], info
    # smooth
    kk = int(max(0, min(int(k), len(cands) - 1)))
    if kk == 0 or X.shape[1] == 0:
        info.update(k=kk, smoothed_value=_value(best), note="too few trials to smooth: the best trial")
        return best, info
    D = np.linalg.norm(X[:, None, :] - X[None, :, :], axis=2)
    sm = np.empty(len(cands))
    for i in range(len(cands)):
        order = np.argsort(D[i], kind="stable")
        nn = [j for j in order if j != i][:kk]
        sm[i] = float(np.mean(np.concatenate([[values[i]], values[nn]])))
    pick = max(range(len(cands)), key=lambda i: (round(sm[i], 12), values[i], -cands[i].number))
    info.update(k=kk, smoothed_value=float(sm[pick]),
                note=f"the best value averaged with its {kk} nearest trials in {where}")
    return cands[pick], info


def pick_confirmed(study) -> tuple[object, dict] | None:
    """(trial, info) of the confirmed rule, or None when the study holds no confirmation: the candidate with the
    highest confirmed mean (ties: the higher own value, then the earlier trial), unless the task's defaults are a
    candidate and that lead over them is within one standard error of the paired differences (same seeds) -- then
    the defaults. Why: the defaults were chosen on evidence (for reconstruction, COLMAP's own settings measured
    cause by cause); a setting replaces them on a measured difference, not on a lead the seeds' noise explains (the
    one-standard-error rule, ESL 7.10, with the defaults as the simpler model)."""
    block = study.user_attrs.get(CONFIRMATION_ATTR)
    if not isinstance(block, dict) or not block.get("trials"):
        return None
    by_number = {t.number: t for t in study.get_trials(deepcopy=False)}
    rows = [(int(k), v) for k, v in block["trials"].items() if int(k) in by_number]
    if not rows:
        return None
    num, best = max(rows, key=lambda kv: (round(kv[1]["mean"], 12), kv[1]["values"][0], -kv[0]))
    others = ", ".join(f"#{k} {v['mean']:.3f}" for k, v in sorted(rows, key=lambda kv: -kv[1]["mean"]))
    note = (f"the highest mean over its own value and {block['seeds']} more seeds among {len(rows)} candidates "
            f"({others})")
    info: dict = {}
    defaults = [(k, v) for k, v in rows if v.get("defaults")]
    if defaults and defaults[0][0] != num:
        dnum, dv = defaults[0]
        d = np.asarray(best["values"], float) - np.asarray(dv["values"], float)
        se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("inf")
        info.update(lead_over_defaults=float(d.mean()), lead_se=se)
        if not d.mean() > se:
            num, best = dnum, dv
            note = (f"the task's defaults (#{dnum}): the best confirmed mean led them by {d.mean():+.3f}, within one "
                    f"standard error ({se:.3f}) of the paired differences over {len(d)} seeds; candidates {others}")
        else:
            note += f"; it leads the defaults by {d.mean():+.3f} (se {se:.3f})"
    info.update(confirmed_mean=best["mean"], confirmed_values=best["values"], note=note)
    return by_number[num], info


# ------------------------------------------------------------------------------------------ robustness

def flat_region(study, optimum, objective: str = "mAA10") -> dict | None:
    """How flat the optimum is: the completed feasible trials whose value lies within the optimum's 95% interval
    (value >= its lower end), how many, and per searched numeric parameter the min / max they span and the share
    of the (log) search range that is. None without an interval for the optimum."""
    ci = interval_of(optimum, objective) if optimum is not None else None
    if ci is None:
        return None
    cands = feasible_trials(study)
    inside = [t for t in cands if ci[0] - 1e-12 <= _value(t) <= ci[1] + 1e-12]
    ps = numeric_params(study.user_attrs.get("search_space_resolved"))
    params = {}
    for name, p in ps.items():
        vals = [float(t.params[name]) for t in inside if name in t.params]
        if not vals:
            continue
        lo, hi = min(vals), max(vals)
        params[name] = {"min": lo, "max": hi, "search_low": p["low"], "search_high": p["high"],
                        "share_of_range": round(normalise(hi, p) - normalise(lo, p), 4)}
    return {"interval": ci, "optimum_trial": optimum.number, "trials": len(inside), "of": len(cands),
            "params": params,
            "note": f"{len(inside)} of {len(cands)} completed feasible trials have a validation mAA(10) within the "
                    f"optimum's 95% interval "
                    f"[{ci[0]:.3f}, {ci[1]:.3f}]"}


def flat_text(flat: dict | None) -> str:
    """One readable line of :func:`flat_region`."""
    if not flat:
        return "flatness: unknown (no interval stored for the optimum)"
    parts = []
    for name, r in flat["params"].items():
        sym, unit = PARAM_LABEL.get(name, (name, ""))
        fmt = (lambda v: f"{int(round(v)):,}") if name == "max_iters" else (lambda v: f"{v:.3g}")
        parts.append(f"{sym} {fmt(r['min'])}-{fmt(r['max'])}{(' ' + unit) if unit else ''} "
                     f"({100 * r['share_of_range']:.0f}% of its range)")
    return (f"flat region: {flat['trials']} of {flat['of']} trials with validation mAA(10°) within the optimum's 95% "
            f"interval "
            f"[{flat['interval'][0]:.3f}, {flat['interval'][1]:.3f}]" + (": " + ", ".join(parts) if parts else ""))


def optimum_warnings(study, frozen: dict) -> list[str]:
    """The one-line warnings about a frozen optimum (on a bound of the search space with the wider range to
    search, Gamma_max at the search ceiling, every trial scoring 0): ``tuner.diagnostics.optimum_warnings``, the
    one implementation (what `tune run` prints at freeze time and frozen.yaml keeps under ``warnings``)."""
    try:
        from tuner.diagnostics import optimum_warnings as _warnings
    except ImportError:  # a checkout without the diagnostics module
        return []
    return list(_warnings(study, frozen))


# ------------------------------------------------------------------------------------------ reference

#: named reference pipelines a task may run (``Task.references``, ``Task.reference_task``)
NAMED_REFERENCES = ("colmap", "imc2025-baseline")


def reference_spec(value: str | None) -> str:
    """``--reference``: None = the task's default (``Task.default_reference``), "paper" = the paper defaults,
    "colmap" = COLMAP's own pipeline, "imc2025-baseline" = the IMC 2025 baseline (both ``Task.reference_task``),
    "none" = no comparison, else a file or study."""
    if value is not None and not isinstance(value, str):
        return "given"  # a resolved configuration (Source or (config, label))
    if value is None or str(value).strip().lower() in ("", "default", "defaults"):
        return "default"
    low = str(value).strip().lower()
    return low if low in ("none", "paper", *NAMED_REFERENCES) else str(value)


def reference_kind(value, task) -> str:
    """:func:`reference_spec` with the task's default resolved: "paper", a named reference ("colmap",
    "imc2025-baseline"), "none", "given" or a file / study; a named reference the task does not run is a one-line
    ImtuneError."""
    kind = reference_spec(value)
    if kind == "default":
        kind = getattr(task, "default_reference", "paper") if task is not None else "paper"
    from pipeline.tasks.base import Task
    has = task is not None and (type(task).reference_task is not Task.reference_task if not isinstance(task, type)
                                else task.reference_task is not Task.reference_task)
    named = tuple(getattr(task, "references", ()) or ()) or (("colmap",) if has else ())
    if kind in NAMED_REFERENCES and kind not in named:
        name = getattr(task, "name", "stereo")
        what = ("COLMAP's own pipeline" if kind == "colmap" else "the IMC 2025 baseline")
        raise ImtuneError(f"--reference {kind}: {what} is the reconstruction task's reference, not the "
                          f"{name} task's (give paper, none, a config file or a study)")
    return kind


def reference_task_of(value, task):
    """The task the reference's runs use: :meth:`Task.reference_task` for a named reference ("colmap",
    "imc2025-baseline"), else ``task`` itself."""
    kind = reference_kind(value, task)
    return task.reference_task(kind) if kind in NAMED_REFERENCES else task


def colmap_reference_label(num_features: int) -> str:
    """What the "colmap" reference runs, with pycolmap's version."""
    from pipeline.features.colmap_sift import _pycolmap_version
    return (f"COLMAP out of the box (pycolmap {_pycolmap_version()}: its SIFT at {num_features} features, exhaustive "
            "matching, default verification, incremental mapper, min_model_size 3, max_num_models 25)")


def baseline_reference_label(num_features: int) -> str:
    """What the "imc2025-baseline" reference runs, with pycolmap's and kornia's versions."""
    from pipeline.features.colmap_sift import _pycolmap_version
    from pipeline.features.kornia_base import package_version
    return (f"IMC 2025 baseline (ALIKED at {num_features} keypoints + LightGlue, kornia "
            f"{package_version('kornia')}; COLMAP's verification and incremental mapper, pycolmap "
            f"{_pycolmap_version()}, min_model_size 3, max_num_models 25)")


def reference_task_note(reference, task_name: str, flag: str = "--reference",
                        use: str = "test it is compared on") -> str | None:
    """The warning for ``--reference`` naming a study (or its frozen.yaml) of another task than the one tested: its
    settings were tuned for that task, and the parameters this task uses that it never tuned run as they are (a
    multiview study's eta 0.5 px and Gamma 1000 on stereo pairs). None otherwise."""
    frozen = getattr(reference, "frozen", None) or {}
    other = frozen.get("task") or "stereo"
    if not frozen or other == task_name:
        return None
    from tuner.protocol import LEAVES, searchable, value_of
    tuned = list(frozen.get("params") or {})
    untuned = [f"{LEAVES[p].label} {value_of(reference.conf, p):g}{' ' + LEAVES[p].unit if p == 'threshold' else ''}"
               for p in searchable(task_name) if p not in searchable(other)]
    name = reference.study or getattr(reference, "path", None) or "the reference"
    tail = f"; its {', '.join(untuned)} were never tuned and run as they are" if untuned else ""
    return (f"{flag} {name} is a {other} study: it tuned {', '.join(tuned) or 'nothing'} for the {other} task, "
            f"not for the {task_name} {use}{tail}")


def reference_config(frozen: dict, spec, task=None):
    """(PipelineConfig, label) of the reference a test run is compared with; None for "none".

    ``spec``: None / "paper" — the frozen configuration (the study's feature, matcher, estimator) with the paper
    defaults for the protocol parameters its task uses (r 0.85 mutual, eta 0.5 px, Gamma 50k); "none"; a
    resolved configuration: a ``(PipelineConfig, label)`` pair or a :class:`tuner.sources.Source` (the CLI resolves
    ``--reference FILE|STUDY`` with :func:`tuner.sources.resolve_source`, which reads frozen files itself)."""
    from pipeline.config_files import pipeline_from_dict
    from tuner.protocol import config_for, searchable
    if hasattr(spec, "conf") and hasattr(spec, "label"):
        return spec.conf, spec.label
    if isinstance(spec, tuple) and len(spec) == 2:
        return spec
    if task is None:
        from pipeline.tasks import TASKS
        task = TASKS.get(frozen.get("task", "stereo"))()
    kind = reference_kind(spec, task)
    if kind == "none":
        return None
    if kind == "colmap":  # the frozen configuration carries the feature count; the reference task ignores the rest
        base = pipeline_from_dict(frozen["config"])
        return base, colmap_reference_label(base.feature.num_features)
    if kind == "imc2025-baseline":  # ALIKED + LightGlue at the frozen configuration's feature count
        from pipeline.tasks.reconstruction import baseline_config
        base = baseline_config(pipeline_from_dict(frozen["config"]))
        return base, baseline_reference_label(base.feature.num_features)
    if kind != "paper":
        raise ImtuneError(f"reference {spec!r}: resolve a config file or study first "
                          "(tuner.sources.resolve_source), or give 'paper', 'colmap', 'imc2025-baseline' or "
                          "'none'")
    base = pipeline_from_dict(frozen["config"])
    values = {k: v for k, v in PAPER_DEFAULTS.items() if k in searchable(task, base)}
    return config_for(base, values), reference_label(values)


def reference_label(values: dict) -> str:
    """"paper defaults (...)" naming the defaults a task's reference sets: all four for stereo
    (:data:`REFERENCE_LABEL`), only r and the strategy for multiview (COLMAP's own RANSAC: no eta, no Gamma)."""
    parts = []
    if "min_confidence" in values:
        parts.append(f"c {values['min_confidence']:g}")
    if "ratio" in values:
        parts.append(f"r {values['ratio']:g}" + (f" {values['strategy']}" if "strategy" in values else ""))
    elif "strategy" in values:
        parts.append(str(values["strategy"]))
    if "threshold" in values:
        parts.append(f"eta {values['threshold']:g} px")
    if "max_iters" in values:
        parts.append(f"Gamma {values['max_iters']:,}")
    return f"paper defaults ({', '.join(parts)})" if parts else "paper defaults"


# ------------------------------------------------------------------------------------------ test runs

TEST_INTERVAL_NOTE = (
    "95% interval of the mean over the test runs (pipeline.metrics.uncertainty.combine_runs_interval): a "
    "percentile bootstrap over pairs stratified by scene of the run-averaged pair scores, each scene's with two "
    "pseudo-pairs (one failed, one perfect; the interval centred on the mean) for small and easy scenes (this "
    "already contains the per-pair seed noise), widened by the run-to-run variation shared by all pairs (the "
    "variance of the runs' mAAs beyond what per-pair noise explains, G / R, with Student's t at "
    "Welch-Satterthwaite degrees of freedom); the std over runs is reported beside it")
BAG_TEST_INTERVAL_NOTE = (
    "95% interval of the mean over the test runs (pipeline.metrics.uncertainty.combine_bag_runs_interval): the "
    "same as for stereo pairs with bags for pairs: a percentile bootstrap over bags stratified by scene and bag "
    "size (weighted as the multiview mAA averages them) of the run-averaged bag scores (each bag's mAA over its "
    "pairs), two pseudo-bags per stratum, widened by the run-to-run variation shared by all bags")


def interval_units(test: dict) -> str:
    """What a test result's interval resamples: "bags" (a multiview test, :data:`BAG_TEST_INTERVAL_NOTE`) or
    "pairs"."""
    return "bags" if (test.get("interval") or {}).get("method") == BAG_TEST_INTERVAL_NOTE else "pairs"


def pair_errors(records: list[dict]) -> list | None:
    """``[[scene, pair, err], ...]`` of a task's records when they are per-pair (stereo); None otherwise."""
    if not records or not all("err" in r and "pair" in r for r in records):
        return None
    return [[r["scene"], r["pair"], r["err"]] for r in records]


def _err(e) -> float:
    return math.inf if e is None or e == "inf" else float(e)


def _as_records(errors: list) -> list[dict]:
    return [{"scene": sc, "pair": p, "err": _err(e)} for sc, p, e in errors]


def bag_errors(records: list[dict]) -> list | None:
    """``[[scene, bag size, bag, [pair errors deg], [images]], ...]`` of a task's records when they are bags
    (multiview); None otherwise. The images are the bag's identity: two studies' bags are compared bag by bag only
    where they are the same images (``pipeline.metrics.uncertainty.bags_differ``), whatever their index."""
    if not records or not all("errors" in r and "bag_size" in r and "bag" in r for r in records):
        return None
    return [[r["scene"], int(r["bag_size"]), int(r["bag"]), list(r["errors"])]
            + ([[str(n) for n in r["images"]]] if r.get("images") else []) for r in records]


def _as_bags(errors: list) -> list[dict]:
    """Bag records of :func:`bag_errors`' entries (4 fields in a test.json of an earlier imtune: no images)."""
    return [{"scene": e[0], "bag_size": e[1], "bag": e[2], "errors": [_err(x) for x in e[3]],
             **({"images": list(e[4])} if len(e) > 4 and e[4] else {})} for e in errors]


def unit_errors(records: list[dict]) -> list | None:
    """What a test run stores for its interval and its paired comparisons: :func:`pair_errors` of stereo records,
    :func:`bag_errors` of multiview ones (stored under :func:`errors_key`); None for records of neither kind."""
    e = pair_errors(records)
    return e if e is not None else bag_errors(records)


def _is_bags(errors: list) -> bool:
    """Bag entries are ``[scene, size, bag, [errors], [images]]`` (no images: an earlier imtune's), pair entries
    ``[scene, pair, err]``."""
    return bool(errors) and len(errors[0]) >= 4


def errors_key(errors: list) -> str:
    """The test run's key for :func:`unit_errors`' list: ``bag_errors`` or ``pair_errors``."""
    return "bag_errors" if _is_bags(errors) else "pair_errors"


def test_interval(mean: dict, runs_errors: list, n_resamples: int) -> dict | None:
    """Put the interval of the mean over runs (``mAA5_ci``, ``mAA10_ci``, overall and per scene) into ``mean``
    (``Task.aggregate``'s) from the runs' pair errors; returns how it was made, or None (no pair errors or
    ``n_resamples`` 0: then the runs' own intervals are all there is)."""
    if not n_resamples or not runs_errors or any(e is None for e in runs_errors):
        return None
    from pipeline.metrics.uncertainty import combine_bag_runs_interval, combine_runs_interval
    kinds = {_is_bags(e) for e in runs_errors}
    if len(kinds) != 1:
        return None
    if kinds == {True}:
        iv = combine_bag_runs_interval([_as_bags(e) for e in runs_errors], n_resamples=int(n_resamples))
        method = BAG_TEST_INTERVAL_NOTE
    else:
        iv = combine_runs_interval([_as_records(e) for e in runs_errors], n_resamples=int(n_resamples))
        method = TEST_INTERVAL_NOTE
    for k in ("mAA5", "mAA10"):
        mean[f"{k}_ci"] = iv[f"{k}_ci"]
        for name, s in (mean.get("scenes") or {}).items():
            if name in iv["scenes"]:
                s[f"{k}_ci"] = iv["scenes"][name][f"{k}_ci"]
    check = abs(float(iv["mAA10"]) - float(mean.get("mAA10", iv["mAA10"])))
    return {"method": method, "level": 0.95, "resamples": int(n_resamples), "runs": iv["runs"],
            "consistent_with_mean": bool(check < 1e-9)}


def compare_reference(ref_errors: list, errors: list, n_resamples: int) -> dict | None:
    """Paired bootstrap (pipeline.metrics.uncertainty.paired_bootstrap) of the frozen settings (B) against the
    reference (A) on the same test pairs, each pair's score averaged over the runs; ``difference`` > 0: the frozen
    settings are better. None where either side has no pair errors."""
    if not ref_errors or not errors or any(e is None for e in list(ref_errors) + list(errors)):
        return None
    from pipeline.metrics.uncertainty import paired_bags, paired_bootstrap
    kinds = {_is_bags(e) for e in list(ref_errors) + list(errors)}
    if len(kinds) != 1:
        return None
    if kinds == {True}:  # the same bags for both (drawn from the ground truth), run k: the k-th seed of both
        a = [{**x, "run": k} for k, e in enumerate(ref_errors) for x in _as_bags(e)]
        b = [{**x, "run": k} for k, e in enumerate(errors) for x in _as_bags(e)]
        return paired_bags(a, b, tau=10, n_resamples=int(n_resamples or 2000))
    a = [{**x, "run": k} for k, e in enumerate(ref_errors) for x in _as_records(e)]  # run k: the k-th seed of both
    b = [{**x, "run": k} for k, e in enumerate(errors) for x in _as_records(e)]
    return paired_bootstrap(a, b, tau=10, n_resamples=int(n_resamples or 2000))


def _run_errors(run: dict) -> list | None:
    """A stored test run's :func:`unit_errors`: its ``pair_errors`` (stereo) or ``bag_errors`` (multiview)."""
    e = run.get("pair_errors")
    return e if e is not None else run.get("bag_errors")


def refresh_intervals(result: dict, n_resamples: int) -> bool:
    """Recompute a stored test result's intervals from its runs' pair errors when an earlier imtune made them with
    another method (``interval.method`` is not :data:`TEST_INTERVAL_NOTE`): the mean's (overall, per scene), the
    reference's and the paired comparison with it. A reused test.json then shows the numbers `tune results` and
    `tune findings` compute from the same pair errors. Returns whether it changed anything (the caller rewrites
    the file); False with no interval method recorded, ``n_resamples`` 0 or no pair errors (multiview: its runs'
    ``bag_errors``, read the same way)."""
    iv = result.get("interval")
    if not isinstance(iv, dict) or iv.get("method") in (TEST_INTERVAL_NOTE, BAG_TEST_INTERVAL_NOTE) or not n_resamples:
        return False
    errors = [_run_errors(r) for r in result.get("runs") or []]
    new = test_interval(result.setdefault("mean", {}), errors, n_resamples)
    if new is None:
        return False
    result["interval"] = new
    ref = result.get("reference")
    if isinstance(ref, dict) and ref.get("runs"):
        rerr = [_run_errors(r) for r in ref["runs"]]
        test_interval(ref.setdefault("mean", {}), rerr, n_resamples)
        cmp = compare_reference(rerr, errors, n_resamples)
        if cmp is not None:
            ref["comparison"] = cmp
    return True


def comparison_text(ref: dict | None) -> str:
    """One readable line of a test result's ``reference`` section."""
    if not ref:
        return "reference: none"
    c = ref.get("comparison")
    key = ref.get("objective") or "mAA10"
    m = ref.get(key)
    head = f"vs {ref.get('label')}: reference {key} " + (f"{m:.3f}" if m is not None else "?")
    per = (c or {}).get("datasets")
    if per:  # per dataset, then overall
        head += "; frozen - reference per dataset: " + ", ".join(f"{k} {v:+.3f}" for k, v in per.items())
    if not c:
        return head + f" ({ref.get('note') or 'no paired comparison'})"
    from pipeline.metrics.uncertainty import format_p, paired_direction  # the rule of findings and compare
    if not c.get("ci"):  # one difference: no interval
        return f"{head}; frozen - reference {c['difference']:+.3f} (one {c.get('units', 'pair')}: no interval)"
    lo, hi = c["ci"]
    verdict = {0: "no significant difference", 1: "frozen settings significantly better",
               -1: "frozen settings significantly WORSE: tuning did not generalise"}[
        paired_direction(c["ci"], c.get("p_value"))]
    return (f"{head}; frozen - reference {c['difference']:+.3f} [{lo:+.3f}, {hi:+.3f}], p = {format_p(c['p_value'])} "
            f"over {c['pairs']} paired {c.get('units', 'pairs')}: {verdict}")
