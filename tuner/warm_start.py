"""``--warm-start STUDY``: a new study's first trials are the frozen optimum and the best feasible trials of other
studies in the same storage, projected into its search space."""
from __future__ import annotations

from pipeline.errors import ImtuneError
from tuner.protocol import best_feasible
from tuner.study_identity import load_study

WARM_START_BEST = 3  # feasible trials taken from each warm-start study, besides its frozen optimum


def _source_picks(src, best: int) -> list:
    """The frozen optimum of a study (its selection rule; the best feasible trial by default) and its ``best``
    best feasible complete trials, best first, without repeats."""
    from optuna.trial import TrialState

    from tuner.protocol import trial_value, trial_within_budget
    picks = []
    try:
        from tuner.select import select_trial
        frozen = select_trial(src, src.user_attrs.get("select"))[0]
    except (ImportError, ImtuneError):
        frozen = best_feasible(src)
    if frozen is not None:
        picks.append(frozen)
    ok = [t for t in src.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
          if trial_value(t) is not None and trial_within_budget(t)]
    ok.sort(key=lambda t: (-trial_value(t), t.number))
    for t in ok:
        if len(picks) >= best + (1 if frozen is not None else 0):
            break
        if all(t.number != q.number for q in picks):
            picks.append(t)
    return picks


def project_params(params: dict, space) -> dict:
    """Trial parameters of another study projected into ``space`` (a resolved SearchSpace): parameters ``space``
    does not search are dropped; numbers are clipped to its range (so Gamma is capped by this study's Gamma_max),
    rounded for integers and snapped to a step; a categorical value is kept only if ``space`` allows it."""
    import math as _m
    out = {}
    for name, p in space.params.items():
        if name not in params or params[name] is None:
            continue
        v = params[name]
        if p.type == "categorical":
            if v in list(p.choices):
                out[name] = v
            continue
        try:
            x = float(v)
        except (TypeError, ValueError):
            continue
        if not _m.isfinite(x):
            continue
        lo, hi = float(p.low), float(p.high)
        x = min(max(x, lo), hi)
        if p.step:
            x = lo + round((x - lo) / float(p.step)) * float(p.step)
            x = min(max(x, lo), hi)
        out[name] = int(round(x)) if p.type == "int" else float(x)
    return out


def warm_start(study, storage, space, sources: list, best: int = WARM_START_BEST, say=None) -> list[dict]:
    """``--warm-start STUDY`` (repeatable): enqueue the frozen optimum and the ``best`` best feasible trials of each
    source study (in the same storage) as this study's first trials, with the values the source fixed, projected into
    its space (:func:`project_params`), without repeats. Only a study without trials is warm-started (a resumed study keeps
    its history); an unknown source is a one-line error naming the studies in the storage. Returns what was
    enqueued ([{"study", "trial", "params"}]), also recorded in the study's user attribute ``warm_start``."""
    if not sources:
        return []
    srcs = check_warm_start_sources(storage, study.study_name, sources)
    if study.get_trials(deepcopy=False):
        if say is not None:
            say(f"warm start skipped: study {study.study_name} already has trials")
        return []
    done, seen = [], set()
    for src in srcs:
        # the source's pinned values (--fix, a scalar in its space) are part of its optimum: a parameter it fixed
        # and this study searches takes that value, not a random draw beside the source's other values
        fixed = (src.user_attrs.get("search_space_resolved") or {}).get("fixed") or {}
        for t in _source_picks(src, best):
            params = project_params({**fixed, **t.params}, space)
            key = tuple(sorted(params.items()))
            if not params or key in seen:
                continue
            seen.add(key)
            study.enqueue_trial(params, user_attrs={"warm_start": f"{src.study_name}#{t.number}"},
                                skip_if_exists=True)
            done.append({"study": src.study_name, "trial": t.number, "params": params})
    study.set_user_attr("warm_start", done)
    if say is not None:
        say(f"warm start: {len(done)} trial(s) enqueued from {', '.join(s.study_name for s in srcs)}")
    return done


def check_warm_start_sources(storage, study_name: str, sources) -> list:
    """The ``--warm-start`` source studies, loaded; a one-line ImtuneError for the study itself or a study not in the
    storage (naming the studies there). ``tuner.study.setup_study`` calls it before it creates the study."""
    srcs = []
    for name in dict.fromkeys(sources or ()):
        if name == study_name:
            raise ImtuneError(f"--warm-start {name}: a study cannot warm-start itself")
        try:
            srcs.append(load_study(storage, name))
        except ImtuneError as e:
            raise ImtuneError(f"--warm-start {name}: {e}") from None
    return srcs


def start_at_defaults(study, space, base, sampler: str, say=None) -> dict | None:
    """A new study of a task with ``Task.start_at_defaults`` (the reconstruction task) runs the task's defaults first:
    every searched parameter at its value in ``base`` (the command line's configuration with the task's defaults),
    projected into ``space`` (:func:`project_params`), enqueued with the user attribute ``start`` "task defaults".
    Not with the grid sampler (its grid is the plan) nor for a study that already has trials (a resume, a warm
    start). Returns the parameters enqueued (None if none), also recorded in the study's user attribute
    ``start_at_defaults``."""
    if sampler == "grid" or study.get_trials(deepcopy=False):
        return None
    from tuner.protocol import value_of
    params = project_params({n: value_of(base, n) for n in space.params}, space)
    if not params:
        return None
    study.enqueue_trial(params, user_attrs={"start": "task defaults"}, skip_if_exists=True)
    study.set_user_attr("start_at_defaults", params)
    if say is not None:
        say("first trial: the task's defaults (" + ", ".join(f"{k} {v:g}" for k, v in params.items()) + ")")
    return params
