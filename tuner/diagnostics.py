"""What a finished study should make its user doubt: one-line warnings about the frozen optimum.

    from tuner.diagnostics import optimum_warnings
    for w in optimum_warnings(study, frozen):   # frozen: tuner.freeze.frozen_from_study(study)
        print("warning:", w)

- **on a bound**: a searched value of the optimum lies on (within ``EDGE`` of the range, on the log scale where
  the parameter is log-uniform) a bound of the search space, so the true optimum may lie outside it; the
  warning suggests the wider range to search. Not warned: a bound that is the parameter's own limit (r = 1,
  no ratio test, cannot be widened) and Gamma at its calibrated upper bound Gamma_max(B) (that is the budget
  binding, as the protocol intends);
- **Gamma_max is the search ceiling** (``tuner.budget.GAMMA_CEILING``): the estimator never reached B seconds
  per pair at any cap measured, so the budget never bound Gamma and the study did not compare settings under
  the budget (unless trials ran over B at their own r / eta: then the warning says so, not "never bound");
- **every trial scored 0**: no completed trial has a non-zero objective, so the "optimum" is arbitrary (e.g.
  SIFT on ScanNet's indoor pairs: no pose within 10 degrees at any setting).

Every function returns plain strings (no "warning:" prefix); :func:`optimum_warnings` is all of them.
"""
from __future__ import annotations

import math

#: A value within this fraction of its range (log range for log-uniform parameters) from a bound is "on" it.
EDGE = 0.02
#: How the warnings name the objective.
METRIC_LABELS = {"mAA10": "mAA(10°)", "mAA5": "mAA(5°)"}


def _g(v) -> str:
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int):
        return f"{v:,}" if abs(v) >= 10_000 else str(v)
    return f"{float(v):.4g}"


def _position(v: float, low: float, high: float, log: bool) -> float | None:
    """Where ``v`` lies in [low, high] as a fraction (0 = low, 1 = high); None for an empty range."""
    if log and low > 0 and high > 0 and v > 0:
        lo, hi, x = math.log(low), math.log(high), math.log(v)
    else:
        lo, hi, x = float(low), float(high), float(v)
    if not hi > lo:
        return None
    return (x - lo) / (hi - lo)


def _wider(name: str, side: str, low: float, high: float, log: bool, typ: str):
    """A suggested new bound on ``side``: half / twice the bound (log-uniform), else half the range further,
    clipped to the parameter's valid range (the protocol table); None when the bound cannot move."""
    from tuner.protocol import LEAVES
    lf = LEAVES.get(name)
    if log:
        new = low / 2.0 if side == "low" else high * 2.0
    else:
        span = high - low
        new = low - span / 2.0 if side == "low" else high + span / 2.0
    if lf is not None:
        if side == "low" and lf.low is not None:
            floor = float(lf.low)
            if new < floor or (lf.low_open and new <= floor):
                new = (floor + low) / 2.0 if lf.low_open else floor
        if side == "high" and lf.high is not None and new > float(lf.high):
            new = float(lf.high)
    if typ == "int":
        new = int(math.floor(new)) if side == "low" else int(math.ceil(new))
        new = max(new, 1)
    else:
        new = float(f"{new:.3g}")
    bound = low if side == "low" else high
    return None if new == bound else new


def _at_limit(name: str, side: str, bound: float) -> bool:
    """The bound is the parameter's own limit (the protocol table's range): it cannot be widened."""
    from tuner.protocol import LEAVES
    lf = LEAVES.get(name)
    if lf is None:
        return False
    limit = lf.low if side == "low" else lf.high
    return limit is not None and float(bound) == float(limit)


def bound_warnings(space: dict, params: dict, *, source: str = "", calibrated=()) -> list[str]:
    """Warnings for searched values of ``params`` that lie on a bound of ``space`` (a resolved search-space spec:
    ``{"params": {name: {"type", "low", "high", "log"}}}``). ``calibrated``: parameters whose upper bound is
    the calibrated Gamma_max (not warned at that bound). ``source``: the space's file, for the message."""
    from tuner.protocol import LEAVES
    out = []
    for name, spec in (space or {}).get("params", {}).items():
        if name not in params or spec.get("type") == "categorical":
            continue
        low, high = spec.get("low"), spec.get("high")
        if not isinstance(low, (int, float)) or not isinstance(high, (int, float)):
            continue
        v = params[name]
        pos = _position(float(v), float(low), float(high), bool(spec.get("log")))
        if pos is None:
            continue
        side = "low" if pos <= EDGE else "high" if pos >= 1.0 - EDGE else None
        if side is None or _at_limit(name, side, low if side == "low" else high):
            continue
        if side == "high" and name in calibrated:
            continue
        lf = LEAVES.get(name)
        label = f"{name} ({lf.label})" if lf is not None and lf.label and lf.label != name else name
        unit = f" {lf.unit}" if lf is not None and lf.unit and lf.unit != "iterations" else ""
        where = f" of the search space{' ' + source if source else ''}"
        msg = (f"the optimum's {label} = {_g(v)}{unit} lies on the {'lower' if side == 'low' else 'upper'} bound"
               f"{where} [{_g(low)}, {_g(high)}]: the best value may lie outside the range")
        new = _wider(name, side, float(low), float(high), bool(spec.get("log")), spec.get("type", "float"))
        if new is not None:
            msg += f"; search a wider one (e.g. {side}: {_g(new)} in a --space file)"
        out.append(msg)
    return out


def gamma_ceiling_warning(budget: dict, ceiling: int | None = None, over: int = 0, completed: int = 0) -> str | None:
    """A warning when Gamma_max(B) is the search ceiling: the budget never bound the iteration cap. ``over`` of
    ``completed`` trials ran over B at their own settings: then it did bind, the calibration missed it."""
    from tuner.budget import GAMMA_CEILING
    budget = budget or {}
    gmax = budget.get("gamma_max")
    if gmax is None:
        return None
    cal = budget.get("calibration") or {}
    ceiling = int(ceiling if ceiling is not None else cal.get("ceiling") or GAMMA_CEILING)
    if int(gmax) < ceiling:
        return None
    b = budget.get("seconds_per_pair")
    head = (f"Gamma_max = {_g(int(gmax))} is the search ceiling (the largest iteration cap imtune searches): the estimator "
            f"stayed within the {_g(b) if b is not None else 'B'} s per pair budget at every cap measured")
    if over:  # "never bound Gamma" beside trials timed over B at their r / eta: the calibration's settings missed it
        return (f"{head} at the calibration's r and eta, yet {over} of {completed} completed trials ran over it at "
                "their own: the budget binds at some settings and Gamma_max did not follow it (time it at a "
                "smaller eta: a --space file whose 'calibration' section sets threshold; see the Budgets page of the docs)")
    return (f"{head}, so the budget never bound Gamma (a faster machine, an estimator that stops early, or a loose "
            "--budget)")


def zero_score_warning(values: list, objective: str = "mAA10") -> str | None:
    """A warning when every completed trial's objective is 0 (``values``: their values)."""
    vals = [v for v in values if v is not None]
    if not vals or any(float(v) != 0.0 for v in vals):
        return None
    metric = METRIC_LABELS.get(objective, objective)
    return (f"every trial scored {metric} = 0 ({len(vals)} completed): no setting recovered a single pose "
            "within the threshold, so the frozen optimum is arbitrary; check that the feature suits the data "
            "(e.g. SIFT on indoor ScanNet pairs) and the ground truth (`tune evaluate` with default settings)")


def optimum_warnings(study, frozen: dict) -> list[str]:
    """Every warning about a study's frozen optimum (see the module doc): on a bound, Gamma_max at the ceiling,
    every trial scoring 0. ``study``: an Optuna study created by imtune; ``frozen``: its frozen settings."""
    from optuna.trial import TrialState

    from pipeline.tasks import TASKS  # not tuner.freeze.task_of: freeze records these warnings (no import cycle)
    attrs = dict(study.user_attrs)
    task = TASKS.get((frozen or attrs).get("task", "stereo"))
    out = []
    # t.value raises on a pareto (two-objective) study's trials: the first value is the objective (mAA(10°)),
    # as tuner.protocol.trial_value reads it
    completed = [float(t.values[0]) if t.values else None
                 for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))]
    z = zero_score_warning(completed, task.objective)
    if z:
        out.append(z)
    space = (frozen or {}).get("search_space") or attrs.get("search_space_resolved") or {}
    original = (attrs.get("search_space") or {}).get("params", {})
    calibrated = [k for k, v in original.items() if isinstance(v, dict) and "calibrated" in (v.get("low"), v.get("high"))]
    params = (frozen or {}).get("params") or {}
    if not z:  # with every score 0 the optimum's position means nothing
        out += bound_warnings(space, params, source=attrs.get("search_space_source", ""), calibrated=calibrated)
    if "max_iters" in params or "max_iters" in (space.get("fixed") or {}):
        from tuner.protocol import trial_within_budget
        done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        g = gamma_ceiling_warning(attrs.get("budget") or (frozen or {}).get("budget"),
                                  over=sum(not trial_within_budget(t) for t in done), completed=len(done))
        if g:
            out.append(g)
    return out
