"""Accuracy against cost: the paper's "performance vs cost" figure made a study.

    tune --feature sift --ransac degensac --objective pareto     # study sift-8000-degensac-stereo-pareto
    tune plot --study sift-8000-degensac-stereo-pareto           # its report, with the Pareto front
    tune plot --pareto A-pareto B-pareto                         # the fronts of several studies on one figure

    from tuner.pareto import pareto_front, best_within_budget, fig_overlay, write_overlay
    front = pareto_front(study)              # [FrozenTrial], fastest first: no other trial is both faster and better
    best = best_within_budget(study)         # the highest mAA(10°) among trials whose time <= B (what freeze picks)
    write_overlay(storage, ["A-pareto", "B-pareto"], "studies/pareto.html")

A pareto study (``tune --objective pareto``) is a two-objective Optuna study: maximize mAA(10°) on the validation
scenes, minimize the median estimator seconds per pair (the budget statistic, ``Task.budget_seconds``), over eta,
r and Gamma (Gamma searched up to Gamma_max(span x B), ``--pareto-span``, default 4, so that the front crosses B).
Its trials are never pruned (Optuna prunes single-objective studies only) and carry no budget constraint (a
trial over B is a point of the front); the user attribute ``feasible`` says whether a trial is within B.

The front of a study is the set of its completed trials that no other trial dominates (at least as accurate and
at least as fast, strictly better in one). For a pareto study it is Optuna's ``study.best_trials``; it is
computed here from (mAA(10°), median seconds) so that a single-objective study's trials give a front too
(those of a TPE search under the budget are concentrated below B) and the overlay can mix both kinds.
The best trial within a budget B is read off the front: the highest mAA(10°) among the trials within B
(:func:`tuner.protocol.within_budget`), the faster of equal mAA(10°) — for the study's own B this is
:func:`tuner.protocol.best_feasible`, which ``freeze`` writes to frozen.yaml.
"""
from __future__ import annotations

import html
import math
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.protocol import trial_value, within_budget

TIME_AXIS = "median estimator CPU time per pair (s)"
METRIC = "mAA(10°)"
COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")


def is_pareto(study) -> bool:
    """A two-objective (``--objective pareto``) study."""
    return len(study.directions) > 1


def trial_seconds(trial) -> float | None:
    """The trial's median estimator seconds per pair: its second value in a pareto study, else the user
    attribute the objective records; None when unknown or not finite."""
    if trial.values is not None and len(trial.values) > 1:
        v = trial.values[1]
    else:
        v = trial.user_attrs.get("ransac_seconds_median")
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


@dataclass(frozen=True)
class Point:
    """One completed trial in the accuracy-cost plane."""
    trial: object  # FrozenTrial
    mAA10: float
    seconds: float

    @property
    def number(self) -> int:
        return self.trial.number


def points(study) -> list[Point]:
    """The study's COMPLETE trials with a value and a measured time, fastest first."""
    from optuna.trial import TrialState
    out = []
    for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        v, s = trial_value(t), trial_seconds(t)
        if v is not None and math.isfinite(v) and s is not None:
            out.append(Point(t, float(v), s))
    return sorted(out, key=lambda p: (p.seconds, -p.mAA10, p.number))


def front_of(pts: list[Point]) -> list[Point]:
    """The non-dominated points (maximize mAA10, minimize seconds), fastest first; equal points are all kept
    (as Optuna's ``study.best_trials``). Written out because it must also serve single-objective studies,
    for which Optuna has no front; a sweep over the points sorted by time is the whole 2-D algorithm."""
    out: list[Point] = []
    best = -math.inf
    for p in sorted(pts, key=lambda p: (p.seconds, -p.mAA10, p.number)):
        if p.mAA10 > best:
            out.append(p)
            best = p.mAA10
        elif out and p.mAA10 == out[-1].mAA10 and p.seconds == out[-1].seconds:
            out.append(p)  # the same point twice: neither dominates the other
    return out


def pareto_front(study) -> list:
    """The FrozenTrials on the study's accuracy-cost Pareto front, fastest first."""
    return [p.trial for p in front_of(points(study))]


def study_budget(study) -> float | None:
    b = (study.user_attrs.get("budget") or {}).get("seconds_per_pair")
    return float(b) if b is not None else None


def best_within_budget(study, budget: float | None = None):
    """The trial of the front with the highest mAA(10°) among those within ``budget`` (default: the study's B),
    the fastest (then the earliest) of equal mAA(10°); None when no trial is within it. At the study's own B
    it agrees with :func:`tuner.protocol.best_feasible` (the trial ``freeze`` writes)."""
    b = study_budget(study) if budget is None else float(budget)
    ok = [p for p in points(study) if within_budget(p.seconds, b)]
    if not ok:
        return None
    return max(ok, key=lambda p: (p.mAA10, -p.seconds, -p.number)).trial


def front_summary(study, budget: float | None = None) -> dict:
    """JSON-able: the study's front (trial, mAA10, seconds, params, within budget) and its best trial within B."""
    b = study_budget(study) if budget is None else float(budget)
    best = best_within_budget(study, budget)

    def row(p: Point) -> dict:
        return {"trial": p.number, "mAA10": p.mAA10, "seconds": p.seconds, "params": dict(p.trial.params),
                "within_budget": within_budget(p.seconds, b)}
    pts = points(study)
    return {"study": study.study_name, "pareto_study": is_pareto(study), "budget": b, "trials": len(pts),
            "front": [row(p) for p in front_of(pts)],
            "best_within_budget": row(Point(best, trial_value(best), trial_seconds(best))) if best is not None else None}


def _label(study, several_estimators: dict) -> str:
    a = study.user_attrs
    est = a.get("ransac") or study.study_name
    if several_estimators.get(est, 0) > 1:
        return study.study_name
    return f"{est} ({a.get('feature', '?')}, {a.get('num_features', '?')} features)"


def _hover(p: Point) -> str:
    names = {"ratio": "r", "threshold": "eta", "max_iters": "Gamma"}
    return f"trial {p.number}: " + ", ".join(
        f"{names.get(k, k)} = {v:.4g}" if isinstance(v, float) else f"{names.get(k, k)} = {v}"
        for k, v in p.trial.params.items())


def _check_study(storage, name: str):
    from tuner.study_identity import load_study
    study = load_study(storage, name)
    if not study.user_attrs.get("imtune"):
        raise ImtuneError(f"study {name!r} was not created by imtune: no Pareto front to draw")
    if not points(study):
        raise ImtuneError(f"study {name!r} has no completed trial with a measured estimator time (a task that times "
                          f"no estimator, or no trial yet): run `tune --objective pareto` first")
    return study


def fig_overlay(storage, names: list[str], title: str | None = None):
    """One figure: per study its completed trials (faint), its Pareto front (a step line: the best mAA(10°)
    reachable within each time) and its best trial within B (a star); the budget B as a vertical line; a log
    time axis. ``names``: study names in ``storage`` (pareto or single-objective)."""
    import plotly.graph_objects as go
    if not names:
        raise ImtuneError("no study to draw: name one or more studies after --pareto")
    studies = [_check_study(storage, n) for n in dict.fromkeys(names)]
    counts: dict = {}
    for st in studies:
        est = st.user_attrs.get("ransac") or st.study_name
        counts[est] = counts.get(est, 0) + 1
    fig = go.Figure()
    xs: list[float] = []  # every time drawn: the axis range
    budgets: dict[float, list[str]] = {}
    for k, st in enumerate(studies):
        color = COLORS[k % len(COLORS)]
        label = _label(st, counts)
        pts = [p for p in points(st) if p.seconds > 0]  # a log axis: a zero time cannot be drawn
        front = front_of(pts)
        xs += [p.seconds for p in pts]
        fig.add_trace(go.Scatter(
            x=[p.seconds for p in pts], y=[p.mAA10 for p in pts], mode="markers", name=f"{label}: trials",
            legendgroup=label, marker=dict(color=color, size=6, opacity=0.3), text=[_hover(p) for p in pts],
            hovertemplate="%{text}<br>median %{x:.3g} s per pair<br>mAA(10°) %{y:.3f}<extra></extra>"))
        fig.add_trace(go.Scatter(
            x=[p.seconds for p in front], y=[p.mAA10 for p in front], mode="lines+markers", line_shape="hv",
            name=f"{label}: Pareto front", legendgroup=label, line=dict(color=color, width=2.5),
            marker=dict(color=color, size=9), text=[_hover(p) for p in front],
            hovertemplate="%{text}<br>median %{x:.3g} s per pair<br>mAA(10°) %{y:.3f}<extra></extra>"))
        b = study_budget(st)
        best = best_within_budget(st)
        if best is not None:
            bp = Point(best, trial_value(best), trial_seconds(best))
            fig.add_trace(go.Scatter(
                x=[bp.seconds], y=[bp.mAA10], mode="markers", legendgroup=label,
                name=f"{label}: best within B (trial {bp.number}, {METRIC} {bp.mAA10:.3f})",
                marker=dict(color=color, size=16, symbol="star", line=dict(color="black", width=1)),
                text=[_hover(bp)], hovertemplate="%{text}<br>median %{x:.3g} s per pair<br>mAA(10°) %{y:.3f}"
                                                 "<extra>best within budget</extra>"))
        if b is not None:
            budgets.setdefault(b, []).append(label)
    for b, who in sorted(budgets.items()):
        xs.append(b)
        text = f"budget B = {b:g} s" + ("" if len(budgets) == 1 else f" ({', '.join(who)})")
        fig.add_vline(x=b, line_dash="dash", line_color="red")
        # the label placed by hand: on a log axis an annotation's x is log10 (plotly's add_vline label is not)
        fig.add_annotation(x=math.log10(b), xref="x", y=1.0, yref="paper", yanchor="bottom", xanchor="center",
                           text=text, showarrow=False, font=dict(color="red"))
    fig.update_layout(
        title=title or (f"Validation {METRIC} vs {TIME_AXIS.split(' (')[0]}: Pareto front"
                        + ("s" if len(studies) > 1 else "") + f" of {len(studies)} stud{'ies' if len(studies) > 1 else 'y'}"),
        # plotly's own 1-2-5 log ticks ("D2"); tuner.plots (which imports this module) has its own tick text
        xaxis=dict(title=TIME_AXIS, type="log", dtick="D2",
                   range=[math.log10(min(xs) / 1.5), math.log10(max(xs) * 1.5)] if xs else None),
        yaxis_title=METRIC,
        height=650, legend=dict(orientation="h", yanchor="top", y=-0.15, xanchor="left", x=0))
    return fig


def fig_front(study):
    """The Pareto front of one study (for its report): :func:`fig_overlay` of that study alone."""
    return fig_overlay(study._storage, [study.study_name],
                       title=f"Validation {METRIC} vs {TIME_AXIS.split(' (')[0]}: Pareto front of {study.study_name}")


def write_overlay(storage, names: list[str], out: Path | str) -> Path:
    """An offline HTML page (plotly.js embedded): the overlay figure and, per study, its best trial within B."""
    import plotly.io as pio

    from pipeline.fileio import atomic_write
    from tuner.study_identity import load_study
    fig = fig_overlay(storage, names)
    rows = []
    for n in dict.fromkeys(names):
        s = front_summary(load_study(storage, n))
        b = s["best_within_budget"]
        best = ("none within B" if b is None else
                f"trial {b['trial']}: {METRIC} {b['mAA10']:.3f} at {b['seconds']:.3g} s per pair ("
                + ", ".join(f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {v}" for k, v in b["params"].items())
                + ")")
        rows.append(f"<tr><td>{html.escape(n)}</td><td>{s['budget']}</td><td>{s['trials']}</td>"
                    f"<td>{len(s['front'])}</td><td>{html.escape(best)}</td></tr>")
    table = ("<table border='1' cellpadding='4' style='border-collapse:collapse'><tr><th>study</th><th>B (s per pair)"
             "</th><th>trials</th><th>on the front</th><th>best within B (what `tune test` freezes)</th></tr>"
             + "".join(rows) + "</table>")
    doc = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>imtune Pareto fronts</title>"
           "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}</style></head><body>"
           + pio.to_html(fig, full_html=False, include_plotlyjs=True, div_id="pareto-fronts") + table
           + "</body></html>")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, doc)
    return out
