"""Make optuna-dashboard tell the same story as imtune.

    from tuner.annotate import annotate_study
    annotate_study(study, frozen)      # frozen: the dict of tuner.freeze.freeze(), or None

What it writes (all idempotent: a second call with the same study and frozen trial writes nothing):

- the metric name, ``study.set_metric_names(["mAA(10°)"])``, so the dashboard's axes and "Best Trial"
  card say "mAA(10°)" rather than "Objective 0";
- a dashboard note on every infeasible trial (a completed trial whose budget constraint is > 0 or whose
  user attribute ``feasible`` is False): "over budget: median estimator CPU time X s > B s per pair; never
  frozen" (its user attribute ``feasible`` = False is written by the objective while it runs; Optuna
  does not allow user attributes on a finished trial);
- a note on the frozen trial ("frozen by imtune"), or, with ``frozen=None``, on the best feasible trial
  (what ``freeze`` would pick);
- a note on the study: the metric, the budget, the frozen (or best feasible) trial, and which trials are
  over budget — including the warning that the dashboard's own "Best Trial" ranks by value only and
  ignores the budget, when its best trial is an over-budget one.

Notes are Markdown (optuna-dashboard's ``save_note``). imtune's part of a note is its first paragraph,
starting with ``**imtune**``; whatever a user wrote in the note below it is kept.
"""
from __future__ import annotations

import math
import re
import warnings

METRIC_NAME = "mAA(10°)"
MARK = "**imtune**"
SECONDS_NAME = "median estimator CPU time per pair (s)"  # the second objective of a pareto study


from tuner.protocol import trial_within_budget as is_feasible  # noqa: E402  (the one feasibility rule)


def median_seconds(trial, budget: float | None) -> float | None:
    """The trial's median estimator seconds per pair: its user attribute, else B + the budget constraint."""
    med = trial.user_attrs.get("ransac_seconds_median")
    if isinstance(med, (int, float)) and math.isfinite(med):
        return float(med)
    c = trial.constraints.get("budget")
    if c is not None and budget is not None:
        return float(budget) + float(c)
    return None


def _s(x: float | None) -> str:
    """Seconds with 3 significant digits ("0.832", "12.4"); "?" when unknown."""
    return "?" if x is None else f"{x:.3g}"


def over_budget_text(median: float | None, budget: float | None) -> str:
    """The one-line label of an infeasible trial (note, reports, plots)."""
    return (f"over budget: median estimator CPU time {_s(median)} s > {_s(budget)} s per pair; never frozen")


def _params_text(params: dict) -> str:
    names = {"ratio": "r", "threshold": "eta", "max_iters": "Gamma", "strategy": "strategy"}
    out = []
    for k, v in params.items():
        unit = " px" if k == "threshold" else ""
        val = f"{v:.4g}" if isinstance(v, float) else str(v)
        out.append(f"{names.get(k, k)} = {val}{unit}")
    return ", ".join(out)


def _merge(existing: str, block: str) -> str:
    """imtune's block first; the user's own text (everything after imtune's first paragraph) kept."""
    rest = existing or ""
    if rest.startswith(MARK):
        rest = rest.split("\n\n", 1)[1] if "\n\n" in rest else ""
    rest = rest.strip("\n")
    if not block:
        return rest
    return block + ("\n\n" + rest if rest else "")


def _trial_handle(study):
    """A factory of ``optuna.Trial`` objects for finished trials, for optuna-dashboard's ``save_note`` /
    ``get_note`` (which take a Study or a live Trial). Built on a twin of the study with a RandomSampler:
    ``optuna.Trial(...)`` calls the sampler's ``before_trial``, which some samplers (grid) use to write
    to the trial, which a finished trial refuses."""
    import optuna
    twin = optuna.load_study(study_name=study.study_name, storage=study._storage,
                             sampler=optuna.samplers.RandomSampler(seed=0))
    return lambda t: optuna.Trial(twin, t._trial_id)


def _set_note(obj, block: str) -> bool:
    from optuna_dashboard import get_note, save_note
    old = get_note(obj)
    new = _merge(old, block)
    if new == old:
        return False
    save_note(obj, new)
    return True


def annotate_study(study, frozen: dict | int | None = None) -> dict:
    """Name the metric and write the dashboard notes (see the module doc). ``frozen``: the frozen settings
    (the dict :func:`tuner.freeze.freeze` returns, or a trial number); None marks the best feasible trial
    as imtune's pick without calling it frozen. Returns what it found: ``{"frozen": n or None, "best_feasible":
    n or None, "over_budget": [n, ...], "dashboard_best": n or None, "notes_written": k}``. Without
    optuna-dashboard installed only the metric name is written."""
    import optuna
    from optuna.trial import TrialState

    from tuner.protocol import trial_value as _value  # a pareto study's trials have two values: mAA10 first

    attrs = study.user_attrs
    names = [METRIC_NAME] + [SECONDS_NAME] * (len(study.directions) - 1)  # pareto: the time objective too
    with warnings.catch_warnings():  # set_metric_names is "experimental" in Optuna 5
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        if list(study.metric_names or []) != names:
            study.set_metric_names(names)
    budget = (attrs.get("budget") or {}).get("seconds_per_pair")
    from pipeline.tasks import TASKS
    untimed = attrs.get("task", "stereo") in TASKS and not TASKS.get(attrs.get("task", "stereo")).timed
    trials = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    over = [t for t in trials if not is_feasible(t)]
    feasible = [t for t in trials if is_feasible(t) and _value(t) is not None]
    best_feas = max(feasible, key=lambda t: (_value(t), -float(t.user_attrs.get("ransac_seconds_median", 0.0)),
                                             -t.number)) if feasible else None
    frozen_no = frozen.get("trial") if isinstance(frozen, dict) else frozen
    frozen_no = int(frozen_no) if frozen_no is not None else None
    pick = frozen_no if frozen_no is not None else (best_feas.number if best_feas else None)
    # (a pareto study's dashboard shows its Pareto front, over-budget trials included: no single Best Trial)
    valued = [t for t in trials if _value(t) is not None and len(study.directions) == 1]
    # what the dashboard's "Best Trial" card shows: the highest value, constraints ignored
    dash_best = max(valued, key=lambda t: _value(t)) if valued else None
    out = {"frozen": frozen_no, "best_feasible": best_feas.number if best_feas else None,
           "over_budget": [t.number for t in over], "dashboard_best": dash_best.number if dash_best else None,
           "notes_written": 0}
    try:
        import optuna_dashboard  # noqa: F401
    except ImportError:
        return out

    handle = _trial_handle(study)
    by_no = {t.number: t for t in trials}
    blocks: dict[int, str] = {}
    for t in over:
        blocks[t.number] = f"{MARK} · " + over_budget_text(median_seconds(t, budget), budget)
    if pick is not None and pick in by_no:
        t = by_no[pick]
        med = median_seconds(t, budget)
        cost = "" if untimed or budget is None else (
            f"; median estimator CPU time {_s(med)} s <= {_s(budget)} s per pair")
        if frozen_no is not None and not is_feasible(t):  # a frozen file of an older rule: say both
            blocks[t.number] += "; yet frozen (frozen.yaml of this study): refreeze with `tune test --study NAME`"
        elif frozen_no is not None:
            blocks[t.number] = (f"{MARK} · **frozen**: the best feasible trial, {METRIC_NAME} = {_value(t):.3f}"
                                f"{cost}; its settings are in frozen.yaml and run on the test scenes")
        else:
            blocks[t.number] = (f"{MARK} · best feasible trial (what `tune` freezes), {METRIC_NAME} = {_value(t):.3f}"
                                f"{cost}; not frozen yet")
    written = 0
    noted = _trials_with_imtune_note(study)
    for t in trials:
        # trials imtune labels now, and those it labelled before (a trial frozen by an earlier freeze)
        if t.number in blocks or t._trial_id in noted:
            written += _set_note(handle(t), blocks.get(t.number, ""))

    lines = [f"{MARK} · metric: {METRIC_NAME} on the validation scenes "
             f"({', '.join((attrs.get('data') or {}).get('val_scenes') or []) or '?'}), maximised"]
    if not untimed and budget is not None:
        gmax = (attrs.get("budget") or {}).get("gamma_max")
        lines.append(f"budget B = {_s(budget)} s median estimator CPU time per pair"
                     + (f" (Gamma_max = {gmax} iterations)" if gmax else "")
                     + "; trials over it are infeasible and never frozen")
    if pick is not None and pick in by_no:
        t = by_no[pick]
        word = "frozen" if frozen_no is not None else "best feasible (not frozen yet)"
        lines.append(f"{word}: trial {t.number}, {METRIC_NAME} = {_value(t):.3f}"
                     + (f" ({_params_text(t.params)})" if t.params else ""))
    elif trials:
        lines.append("no feasible trial yet: nothing can be frozen")
    if over:
        nums = ", ".join(str(t.number) for t in over[:20]) + (", ..." if len(over) > 20 else "")
        lines.append(f"over budget: {len(over)} of {len(trials)} completed trials (trial {nums})")
    if dash_best is not None and not is_feasible(dash_best):
        lines.append(f"the dashboard's Best Trial ranks by value only and ignores the budget: its trial "
                     f"{dash_best.number} ({METRIC_NAME} = {_value(dash_best):.3f}) is over budget")
    written += _set_note(study, "  \n".join(lines))
    out["notes_written"] = written
    return out


def _trials_with_imtune_note(study) -> set[int]:
    """Trial ids whose dashboard note starts with imtune's block, from one read of the study's system
    attributes (where optuna-dashboard keeps notes: ``dashboard:<trial_id>:note_str:<chunk>``)."""
    out = set()
    for k, v in study._storage.get_study_system_attrs(study._study_id).items():
        m = re.fullmatch(r"dashboard:(\d+):note_str:0", k)
        if m and str(v).startswith(MARK):
            out.add(int(m.group(1)))
    return out
