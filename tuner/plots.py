"""One self-contained HTML report per study (plotly; works offline — plotly.js is embedded once).

    from tuner.plots import write_report, report_sections
    path = write_report(storage, "sift-8000-degensac-stereo", "studies/sift-8000-degensac-stereo/report.html")
    for s in report_sections(storage, "sift-8000-degensac-stereo"):   # the figures, for a notebook
        s.fig.show() if s.fig else print(s.title, "-", s.note)

Sections: optimization history (over-budget trials marked), parameter importances, mAA(10°) over the
inlier threshold eta and the ratio test r (contour), mAA(10°) against the median estimator CPU time per pair
(with the budget B), mAA(10°) against the iteration cap Gamma, the mAA(10°)-against-eta curves of every
study of the same task in the storage (best mAA(10°) per eta bin: the paper's inlier-threshold figure),
for a pareto study (``tune --objective pareto``) its accuracy-cost Pareto front (:mod:`tuner.pareto`),
and the breakdowns of the frozen trial (the pick of the study's selection rule, ``--select``) by scene: accuracy against the angular threshold
(1..10°; stereo pairs, or multiview pairs of the bags) and mAA(10°) by co-visibility bin (stereo) — from
the trial's user attributes (validation scenes) and, once `tune test` has run, from
``<studies dir>/<study>/test.json`` (test scenes, mean over the runs).

Every figure has one title (its own; the page adds no second heading above it), axis titles with units
(r; eta in px; Gamma in iterations, on a log axis with 1-2-5 ticks; seconds), US spelling throughout. A
section that cannot be drawn says why and names the command that fills the gap.
"""
from __future__ import annotations

import html
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError
from tuner.annotate import METRIC_NAME, is_feasible
from tuner.protocol import trial_value as _value  # a pareto study's trials have two values: mAA10 first

METRIC = METRIC_NAME  # "mAA(10°)"
FEASIBLE = "within budget"
INFEASIBLE = "over budget (never frozen)"
# axis titles of the searched parameters (units in parentheses)
PARAM_LABELS = {"ratio": "ratio test r", "threshold": "inlier threshold eta (px)",
                "max_iters": "iteration cap Gamma (iterations)", "strategy": "matching strategy"}
PARAM_SHORT = {"ratio": "r", "threshold": "eta (px)", "max_iters": "Gamma (iterations)", "strategy": "strategy"}


@dataclass
class Section:
    """One part of the report: ``fig`` (a plotly Figure whose layout title is the section's title) or,
    when it cannot be drawn, None and ``note`` (why, and the command that fills the gap)."""
    title: str
    fig: object = None
    note: str = ""


def _runs(n: int) -> str:
    return f"{n} run" + ("" if n == 1 else "s")


def _complete(study):
    from optuna.trial import TrialState
    return study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))


def _fmt_tick(v: float, unit: str = "") -> str:
    """1-2-5 tick text: 0.1, 0.2, 0.5, 1, 2, ... ; thousands as 1k, 20k, 1M."""
    if v >= 1e6:
        s = f"{v / 1e6:g}M"
    elif v >= 1e3:
        s = f"{v / 1e3:g}k"
    else:
        s = f"{v:g}"
    return s + unit


def log_ticks(lo: float, hi: float, unit: str = "") -> dict:
    """``tickvals`` / ``ticktext`` of a readable log axis (1, 2, 5 per decade; 1, 1.5, 2, 3, 5, 7 when the
    range is under a decade) covering [lo, hi]: plotly's
    own log ticks print 2-digit mantissas or exponents ("10^4") that read badly for eta and Gamma."""
    lo, hi = float(lo), float(hi)
    if not (lo > 0 and hi > 0):
        return {}
    if hi < lo:
        lo, hi = hi, lo
    def within(mantissas):
        return [m * 10.0 ** e for e in range(math.floor(math.log10(lo)) - 1, math.ceil(math.log10(hi)) + 1)
                for m in mantissas if lo / 1.0001 <= m * 10.0 ** e <= hi * 1.0001]

    vals = within((1, 2, 5))
    if len(vals) < 3:  # less than a decade: finer steps
        vals = within((1, 1.5, 2, 3, 5, 7))
    if len(vals) < 2:  # a narrow range: the two decade-neighbours around it
        vals = sorted({10.0 ** math.floor(math.log10(lo)), 10.0 ** math.ceil(math.log10(hi))} | set(vals))
    vals = [float(f"{v:.6g}") for v in vals]
    return {"tickmode": "array", "tickvals": vals, "ticktext": [_fmt_tick(v, unit) for v in vals]}


def _log_axis(values, unit: str = "") -> dict:
    vals = [float(v) for v in values if isinstance(v, (int, float)) and v > 0]
    if not vals:
        return {"type": "log"}
    return {"type": "log", **log_ticks(min(vals), max(vals), unit)}


def _hover_params(t) -> str:
    return f"trial {t.number}: " + ", ".join(
        f"{PARAM_SHORT.get(k, k).split(' (')[0]} = {v:.4g}" if isinstance(v, float) else
        f"{PARAM_SHORT.get(k, k).split(' (')[0]} = {v}" for k, v in t.params.items())


def _target(study):
    """Optuna's visualizations need the objective named in a multi-objective (pareto) study: mAA(10°), the first."""
    return (lambda t: t.values[0]) if len(study.directions) > 1 else None


def fig_history(study):
    """Optuna's optimization history (infeasible trials in their own trace), titled and labeled."""
    import optuna.visualization as ov
    fig = ov.plot_optimization_history(study, target=_target(study), target_name=METRIC)
    names = {METRIC: f"{METRIC} of a trial", "Best Value": "best within budget so far",
             "Infeasible Trial": INFEASIBLE}
    for tr in fig.data:
        tr.name = names.get(tr.name, tr.name)
        if tr.name == INFEASIBLE:  # Optuna leaves its grey points out of the legend: say what they are
            tr.showlegend = True
    fig.update_layout(title=f"Optimization history: validation {METRIC} per trial",
                      xaxis_title="trial number", yaxis_title=f"{METRIC} (validation)")
    return fig


def fig_importances(study):
    """Optuna's PED-ANOVA parameter importances for mAA(10°) (normalised to sum 1): how much each parameter decides
    whether a trial reaches the best 10% of mAA(10°): Optuna's default evaluator and what optuna-dashboard shows
    (not fANOVA's share of variance, which needs scikit-learn and would differ from the dashboard).
    Parameters are named as in the paper. With too few trials, or trials that all reach the same value, PED-ANOVA
    returns equal importances: the figure says so instead of Optuna's warning on stderr."""
    import warnings

    import optuna.visualization as ov
    from optuna.importance import PedAnovaImportanceEvaluator
    # pareto: PED-ANOVA ranks a given target low-is-better, so the target is -mAA(10°)
    target = (lambda t: -t.values[0]) if len(study.directions) > 1 else None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        fig = ov.plot_param_importances(study, evaluator=PedAnovaImportanceEvaluator(), target=target,
                                        target_name=METRIC)
    for tr in fig.data:
        if getattr(tr, "y", None) is not None:
            tr.y = [PARAM_SHORT.get(str(n), str(n)) for n in tr.y]
    fig.update_layout(title=f"Parameter importances for {METRIC} (PED-ANOVA, as in optuna-dashboard)",
                      xaxis_title="importance: how much the parameter decides reaching the best 10% of trials "
                                  "(sums to 1)", yaxis_title="parameter")
    if any("will be equal" in str(w.message) for w in caught):  # Optuna's words for "nothing to tell apart"
        fig.add_annotation(text="equal by construction: too few trials, or every trial reached the same "
                                f"{METRIC}", xref="paper", yref="paper", x=0.5, y=1.0, yanchor="bottom",
                           showarrow=False)
    return fig


def fig_contour(study):
    """mAA(10°) over eta (log axis) and r: Optuna's contour, axes labeled with units."""
    import optuna.visualization as ov
    fig = ov.plot_contour(study, params=["threshold", "ratio"], target=_target(study), target_name=METRIC)
    etas = [t.params["threshold"] for t in _complete(study) if "threshold" in t.params]
    for ax in ("xaxis", "yaxis"):
        axis = fig.layout[ax]
        name = axis.title.text if axis.title and axis.title.text else ""
        if name == "threshold":
            fig.update_layout({ax: dict(title=PARAM_LABELS["threshold"], **_log_axis(etas))})
        elif name in PARAM_LABELS:
            fig.update_layout({ax: dict(title=PARAM_LABELS[name])})
    for tr in fig.data:  # Optuna's dots, hidden from the legend: say what black and grey mean
        if tr.type == "scatter" and tr.name in ("Feasible Trial", "Infeasible Trial"):
            tr.name = FEASIBLE if tr.name == "Feasible Trial" else INFEASIBLE
            tr.showlegend = bool(tr.x is not None and len(tr.x))
    fig.update_layout(title=f"Validation {METRIC} over inlier threshold eta and ratio test r",
                      legend=dict(orientation="h", yanchor="top", y=-0.15, xanchor="left", x=0))
    return fig


def fig_cost(study):
    """mAA(10°) against the median estimator CPU time per pair; B as a vertical line."""
    import plotly.graph_objects as go
    trials = [t for t in _complete(study) if "ransac_seconds_median" in t.user_attrs]
    fig = go.Figure()
    for feas, name, color in ((True, FEASIBLE, "#1f77b4"), (False, INFEASIBLE, "#bbbbbb")):
        ts = [t for t in trials if is_feasible(t) == feas]
        if not ts:
            continue
        fig.add_trace(go.Scatter(
            x=[t.user_attrs["ransac_seconds_median"] for t in ts], y=[_value(t) for t in ts], mode="markers", name=name,
            marker=dict(color=color, size=8), text=[_hover_params(t) for t in ts],
            hovertemplate="%{text}<br>median %{x:.3f} s per pair<br>mAA(10°) %{y:.3f}<extra></extra>"))
    b = (study.user_attrs.get("budget") or {}).get("seconds_per_pair")
    if b:
        fig.add_vline(x=float(b), line_dash="dash", line_color="red", annotation_text=f"budget B = {b:g} s")
    fig.update_layout(title=f"Validation {METRIC} vs estimator CPU time per pair",
                      xaxis_title="median estimator CPU time per pair (s)", yaxis_title=f"{METRIC} (validation)")
    return fig


def fig_gamma(study):
    """mAA(10°) against the iteration cap Gamma (log axis, 1-2-5 ticks); Gamma_max of the budget marked.
    None when the study does not search Gamma."""
    import plotly.graph_objects as go
    trials = [t for t in _complete(study) if "max_iters" in t.params]
    if not trials:
        return None
    fig = go.Figure()
    for feas, name, color in ((True, FEASIBLE, "#1f77b4"), (False, INFEASIBLE, "#bbbbbb")):
        ts = [t for t in trials if is_feasible(t) == feas]
        if ts:
            fig.add_trace(go.Scatter(x=[t.params["max_iters"] for t in ts], y=[_value(t) for t in ts], mode="markers",
                                     name=name, marker=dict(color=color, size=8), text=[_hover_params(t) for t in ts],
                                     hovertemplate="%{text}<br>mAA(10°) %{y:.3f}<extra></extra>"))
    gammas = [t.params["max_iters"] for t in trials]
    gmax = (study.user_attrs.get("budget") or {}).get("gamma_max")
    if gmax:
        gammas.append(gmax)
        fig.add_vline(x=float(gmax), line_dash="dash", line_color="red")
        # the label placed by hand: on a log axis an annotation's x is log10 (add_vline's label is not: it landed
        # at 10^Gamma_max, off the figure)
        fig.add_annotation(x=math.log10(float(gmax)), xref="x", y=1.0, yref="y domain", xanchor="right",
                           yanchor="top", showarrow=False, text=f"Gamma_max = {_fmt_tick(float(gmax))} (budget)")
    fig.update_layout(title=f"Validation {METRIC} vs RANSAC iteration cap Gamma",
                      xaxis=dict(title="iteration cap Gamma (iterations, log scale)", **_log_axis(gammas)),
                      yaxis_title=f"{METRIC} (validation)")
    return fig


def fig_eta_curves(storage, study):
    """Best mAA(10°) per log-eta bin for every study of the same task in the storage."""
    import optuna
    import plotly.graph_objects as go
    task = study.user_attrs.get("task", "stereo")
    fig = go.Figure()
    n, all_x = 0, []
    for summ in optuna.get_all_study_summaries(storage, include_best_trial=False):
        if not summ.user_attrs.get("imtune") or summ.user_attrs.get("task", "stereo") != task:
            continue
        st = optuna.load_study(study_name=summ.study_name, storage=storage)
        pts = [(t.params["threshold"], _value(t)) for t in _complete(st) if "threshold" in t.params and is_feasible(t)]
        if len(pts) < 2:
            continue
        eta = np.array([p[0] for p in pts], float)
        val = np.array([p[1] for p in pts], float)
        edges = np.geomspace(eta.min() * 0.999, eta.max() * 1.001, min(12, len(pts)) + 1)
        xs, ys = [], []
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = (eta >= lo) & (eta < hi)
            if m.any():
                xs.append(float(np.sqrt(lo * hi)))
                ys.append(float(val[m].max()))
        width = 3 if summ.study_name == study.study_name else 1.5
        fig.add_trace(go.Scatter(x=xs, y=ys, mode="lines+markers", name=summ.study_name, line=dict(width=width)))
        all_x += xs
        n += 1
    fig.update_layout(title=f"Best {METRIC} vs inlier threshold eta, {task} studies (trials within budget)",
                      xaxis=dict(title="inlier threshold eta (px, log scale)", **_log_axis(all_x)),
                      yaxis_title=f"best {METRIC} per eta bin (validation)")
    return fig if n else None


def breakdown_sources(study, best, studies_dir=None) -> list[tuple[str, dict]]:
    """[(label, {scene: summary with "accuracy" and maybe "covisibility"})]: the frozen trial's (``best``)
    validation scenes, then the test scenes of test.json (per scene, averaged over the runs) when it is there."""
    from tuner.freeze import load_test_file, study_dir
    out = []
    if best is not None and best.user_attrs.get("scenes"):
        out.append((f"validation (trial {best.number})", best.user_attrs["scenes"]))
    if studies_dir is not None:
        t, _ = load_test_file(study_dir(studies_dir, study.study_name) / "test.json",  # unreadable: not drawn
                              study.study_name)
        if t and t.get("runs"):
            scenes = {}
            for name in t["runs"][0].get("scenes") or {}:
                per = [r["scenes"][name] for r in t["runs"] if name in (r.get("scenes") or {})]
                d = {}
                accs = [p_["accuracy"] for p_ in per if p_.get("accuracy")]
                if accs:
                    d["accuracy"] = np.mean(np.asarray(accs, float), axis=0).tolist()
                covs = [p_["covisibility"] for p_ in per if p_.get("covisibility")]
                if covs:
                    d["covisibility"] = {b: {"mAA10": float(np.mean([c[b]["mAA10"] for c in covs if b in c])),
                                             "pairs": covs[0][b].get("pairs")} for b in covs[0]}
                scenes[name] = d
            out.append((f"test (trial {t.get('trial')}, {_runs(len(t['runs']))})", scenes))
    return out


def fig_accuracy_threshold(sources, task: str = "stereo"):
    """Accuracy against the angular threshold (1..10°), one line per scene and source."""
    import plotly.graph_objects as go
    fig = go.Figure()
    for label, scenes in sources:
        dash = "solid" if label.startswith("validation") else "dash"
        for name, sm in scenes.items():
            acc = sm.get("accuracy")
            if not acc:
                continue
            fig.add_trace(go.Scatter(x=list(range(1, len(acc) + 1)), y=acc, mode="lines+markers",
                                     name=f"{name} - {label}", line=dict(dash=dash)))
    if not fig.data:
        return None
    fig.update_layout(title=f"Accuracy vs angular threshold, {task} pose, by scene (frozen trial)",
                      xaxis_title="angular threshold (°)",
                      yaxis_title="accuracy (fraction of pairs within the threshold)",
                      xaxis=dict(dtick=1), yaxis=dict(range=[0, 1.02]))
    return fig


def _has_covisibility(cov: dict | None) -> bool:
    """A breakdown with at least one pair of known co-visibility (scenes without ground-truth 3D points
    put every pair under "unknown")."""
    return bool(cov) and any((v or {}).get("pairs") for b, v in cov.items() if b != "unknown")


def fig_covisibility(sources):
    """mAA(10°) by co-visibility bin (pairs with co-visibility >= edge), one bar group per scene and source."""
    import plotly.graph_objects as go
    fig = go.Figure()
    for label, scenes in sources:
        for name, sm in scenes.items():
            cov = sm.get("covisibility")
            if not _has_covisibility(cov):
                continue
            bins = [b for b in cov if b != "unknown"]
            fig.add_trace(go.Bar(x=bins, y=[cov[b]["mAA10"] for b in bins], name=f"{name} - {label}",
                                 text=[f"{cov[b].get('pairs')} pairs" for b in bins],
                                 hovertemplate="co-visibility %{x}<br>mAA(10°) %{y:.3f}<br>%{text}<extra></extra>"))
    if not fig.data:
        return None
    fig.update_layout(title=f"Stereo {METRIC} by co-visibility, by scene (frozen trial)", barmode="group",
                      xaxis_title="co-visibility bin (pairs with co-visibility >= the bin's edge)",
                      yaxis_title=METRIC)
    return fig


def _covisibility_hint(study, sources) -> str:
    """Why there is no co-visibility figure, and the command that fixes it."""
    root = (study.user_attrs.get("data") or {}).get("root") or "DIR"
    name = study.study_name
    if not sources:
        return (f"no per-scene breakdown stored for the frozen trial (trials of older imtune versions): run "
                f"`tune test --study {name}`")
    lacking = sorted({sc for _, scenes in sources for sc, sm in scenes.items()
                      if not _has_covisibility(sm.get("covisibility"))})
    if lacking and any("covisibility" in sm for _, scenes in sources for sm in scenes.values()):
        return (f"no co-visibility for {', '.join(lacking)}: run `tune data build-gt --data {root}` "
                f"(3D points, hence co-visibility), then tune again or run `tune test --study {name}`")
    return (f"no co-visibility breakdown stored for the frozen trial (trials of older imtune versions): run "
            f"`tune test --study {name}`")


def frozen_trial(study):
    """The trial the study freezes: its recorded selection rule's pick (``tuner.select``; ``--select one-se`` or
    ``smooth`` can freeze another trial than the best), the best feasible trial where the rule is unknown."""
    from tuner.protocol import best_feasible
    from tuner.select import select_trial
    try:
        return select_trial(study, study.user_attrs.get("select"))[0]
    except ImtuneError:  # an unknown recorded rule (a newer imtune)
        return best_feasible(study)


def report_sections(storage, study_name: str, studies_dir: Path | str | None = None) -> list[Section]:
    """The report's sections, each a titled figure or a note saying why it is missing and how to fill it."""
    from tuner.study_identity import load_study
    study = load_study(storage, study_name)
    trials = _complete(study)
    if not trials:
        raise ImtuneError(f"study {study_name!r} has no completed trial to plot")
    task = study.user_attrs.get("task", "stereo")
    more = f"run more trials (the same `tune` command with --study {study_name} and a larger --n-trials)"
    sections: list[Section] = []

    def add(title, make, note=""):
        try:
            fig = make()
        except Exception as e:  # noqa: BLE001 - a section that cannot be drawn says why, the rest is written
            sections.append(Section(title, None, f"not available: {' '.join(str(e).split())[:200]}"))
            return
        sections.append(Section(fig.layout.title.text or title, fig) if fig is not None
                        else Section(title, None, note or "not enough data"))

    params = set().union(*(t.params for t in trials))
    add("Optimization history", lambda: fig_history(study))
    add("Parameter importances", lambda: fig_importances(study) if len(trials) >= 2 else None,
        f"needs at least 2 completed trials: {more}")
    if {"threshold", "ratio"} <= params:
        add(f"{METRIC} over eta and r", lambda: fig_contour(study))
    else:
        sections.append(Section(f"{METRIC} over eta and r", None, "eta and r are not both searched in this study"))
    from pipeline.tasks import TASKS
    if not TASKS.get(task).timed:  # a task that times no estimator of ours
        sections.append(Section(f"{METRIC} vs estimator CPU time per pair", None,
                                f"{task} study: no estimator of imtune's is timed (COLMAP runs its own RANSAC), "
                                "no estimator budget"))
    else:
        add(f"{METRIC} vs estimator CPU time per pair", lambda: fig_cost(study))
        add(f"{METRIC} vs iteration cap Gamma", lambda: fig_gamma(study),
            "Gamma is not searched in this study (pinned with --fix, or the estimator has no iteration cap)")
        if len(study.directions) > 1:  # a pareto study (tune --objective pareto): its accuracy-cost front
            from tuner.pareto import fig_front
            add(f"{METRIC} vs estimator CPU time per pair: Pareto front", lambda: fig_front(study))
    if "threshold" not in TASKS.get(task).uses:  # no number of trials brings an eta to a task that has none
        verifier = TASKS.get(task).verifier  # multiview: COLMAP
        sections.append(Section(f"{METRIC} vs eta across studies", None,
                                f"{task} study: the task does not search eta"
                                + (f" ({verifier} runs its own RANSAC)" if verifier else "")))
    else:
        add(f"{METRIC} vs eta across studies", lambda: fig_eta_curves(storage, study),
            f"needs studies with at least 2 trials within budget that search eta: {more}")
    best = frozen_trial(study)  # the trial test.json measured (its selection rule), not always the best one
    sources = breakdown_sources(study, best, studies_dir)
    add("Accuracy vs angular threshold, by scene", lambda: fig_accuracy_threshold(sources, task),
        f"no per-scene accuracy stored for the frozen trial (trials of older imtune versions): run "
        f"`tune test --study {study_name}`")
    # the section exists where the task's figures carry a co-visibility breakdown (pairs with co-visibility)
    if any("covisibility" in sm for _, scenes in sources for sm in scenes.values()) or \
            "covisibility" in (best.user_attrs if best is not None else {}):
        add(f"{METRIC} by co-visibility, by scene", lambda: fig_covisibility(sources),
            _covisibility_hint(study, sources))
    return sections


def _uncertainty_lines(study, studies_dir=None) -> list[str]:
    """HTML paragraphs: the frozen trial (its selection rule) with the 95% interval of its validation mAA(10°), how
    flat the optimum is, the warnings, and from test.json the test mAA(10°) with its interval and the paired
    comparison with the reference configuration."""

    from tuner.freeze import frozen_from_study, load_test_file, study_dir
    from tuner.select import comparison_text, flat_text, interval_units
    try:
        f = frozen_from_study(study)
    except Exception as e:  # noqa: BLE001 - the rest of the report still draws
        return [f"<p><i>{html.escape(f'frozen settings unavailable: {e}')}</i></p>"]
    v = f.get("validation") or {}
    ci = v.get("mAA10_ci")
    sel = f.get("selection") or {}
    ps = ", ".join(f"{PARAM_SHORT.get(k, k)} = {x:.4g}" if isinstance(x, float) else f"{PARAM_SHORT.get(k, k)} = {x}"
                   for k, x in (f.get("params") or {}).items())
    txt = (f"frozen ({sel.get('rule', 'best')} rule): trial {f['trial']}, validation {METRIC} = "
           + (f"{v.get('mAA10'):.3f}" if v.get("mAA10") is not None else "?")
           + (f" [95% interval {ci[0]:.3f}, {ci[1]:.3f}]" if ci else " (no interval stored)") + f"; {ps}")
    out = [f"<p><b>{html.escape(txt)}</b><br>{html.escape(sel.get('note', ''))}</p>",
           f"<p>{html.escape(flat_text(f.get('robustness')))}</p>"]
    out += [f"<p style='color:#b00'>warning: {html.escape(w)}</p>" for w in f.get("warnings") or []]
    t, why = load_test_file(study_dir(studies_dir, study.study_name) / "test.json" if studies_dir is not None else None,
                            study.study_name)
    if why:
        out.append(f"<p style='color:#b00'>{html.escape(f'test.json cannot be read ({why}): rerun `tune test --study {study.study_name}`')}</p>")
    if t is not None:
        m = t.get("mean") or {}
        tci = m.get("mAA10_ci")
        line = (f"test ({_runs(len(t.get('runs') or []))}, trial {t.get('trial')}): {METRIC} = "
                + (f"{m.get('mAA10'):.3f}" if m.get("mAA10") is not None else "?")
                + (f" [95% interval {tci[0]:.3f}, {tci[1]:.3f}, over {interval_units(t)} and runs]" if tci else "")
                + (f", sample std over runs {(t.get('std') or {}).get('mAA10', 0.0):.3f}"
                   if len(t.get("runs") or []) > 1 else ", one run: no spread over runs"))
        out.append(f"<p><b>{html.escape(line)}</b><br>{html.escape(comparison_text(t.get('reference')))}</p>")
        from tuner.replicates import replicated_block, replicated_text
        block = replicated_block(t)
        if block is not None and block["replicates"]:  # `tune --replicates K`: the tuned figure
            try:
                rep = replicated_text(block).splitlines()
            except (KeyError, TypeError, ValueError) as e:  # a hand-edited block: said, the report still drawn
                rep = [f"tuning replicates: the replicated block of test.json cannot be read ({e})"]
            out.append("<p><b>" + html.escape(rep[0]) + "</b><br>" + "<br>".join(html.escape(x) for x in rep[1:])
                       + "</p>")
    out += _ground_truth_lines(f, t)
    return out


def _ground_truth_lines(frozen: dict, test: dict | None) -> list[str]:
    """Where the validation and test scenes' poses come from (their own: a laser scan, a calibration, a pairs list;
    or imtune's SfM by `tune data build-gt`), as the study and test.json recorded it, with the tasks' notes on the
    scenes (pairs an SfM ground truth dropped, of those listed)."""
    from tuner.formatting import ground_truth_text
    out = []
    for role, d, notes in (("validation", frozen.get("data") or {}, (frozen.get("data") or {}).get("notes")),
                           ("test", (test or {}).get("data") or {}, (test or {}).get("notes"))):
        if role == "test" and test is None:
            continue
        origin = ground_truth_text(d.get("ground_truth")) or "not recorded (written before imtune recorded it)"
        out.append(f"<p>{html.escape(f'{role} ground truth: {origin}')}"
                   + "".join(f"<br><i>{html.escape(f'{role} {n}')}</i>" for n in notes or []) + "</p>")
    return out


def write_report(storage, study_name: str, out: Path | str, studies_dir: Path | str | None = None) -> Path:
    """Write the HTML report of one study; returns its path. ``studies_dir``: where test.json is read
    for the test-scene breakdowns."""
    import plotly.io as pio

    from tuner.formatting import gamma_max_text
    from tuner.freeze import study_dir
    from tuner.study import best_feasible, load_study, trial_counts
    sections = report_sections(storage, study_name, studies_dir)
    study = load_study(storage, study_name)
    best = best_feasible(study)
    counts = trial_counts(study)
    attrs = study.user_attrs
    b = attrs.get("budget") or {}
    from pipeline.tasks import TASKS
    task = attrs.get("task", "stereo")
    over = f" ({counts['infeasible']} over budget)"
    if task in TASKS and not TASKS.get(task).timed:  # COLMAP's RANSAC: no budget applies, none to state
        budget = f"{task} study: no estimator budget (no estimator of imtune's is timed)"
        over = ""
    else:
        budget = (f"budget B = {b.get('seconds_per_pair')} s per pair (median estimator CPU time), "
                  + gamma_max_text(b.get("gamma_max"), (attrs.get("search_space_resolved") or {}).get("fixed"),
                                   unit=" iterations"))
    head = [f"<h1>imtune study {html.escape(study_name)}</h1>",
            "<p>" + html.escape(f"trials: {counts['complete']} complete{over}, "
                                f"{counts['pruned']} pruned, {counts['fail']} failed; {budget}; "
                                f"data {attrs.get('data_fingerprint')}; code {attrs.get('code_version')}") + "</p>"]
    if best is not None:
        ps = ", ".join(f"{PARAM_SHORT.get(k, k)} = {v:.4g}" if isinstance(v, float) else f"{PARAM_SHORT.get(k, k)} = {v}"
                       for k, v in best.params.items())
        within = " within budget" if over else ""  # over: the trial counts name a budget (a timed task)
        head.append(f"<p><b>optimum (best{within}): trial {best.number}</b>, {METRIC} = {_value(best):.3f}; "
                    f"{html.escape(ps)}</p>")
        head += _uncertainty_lines(study, studies_dir)
    body, first = [], True
    for s in sections:
        if s.fig is not None:  # the figure carries its own title: no second heading above it
            body.append(pio.to_html(s.fig, full_html=False, include_plotlyjs=True if first else False))
            first = False
        else:
            body.append(f"<h2>{html.escape(s.title)}</h2>")
        if s.note:
            body.append(f"<p><i>{html.escape(s.note)}</i></p>")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>imtune " + html.escape(study_name) +
           "</title><style>body{font-family:sans-serif;max-width:1100px;margin:auto}</style></head><body>" +
           "\n".join(head + body) + "</body></html>")
    from pipeline.fileio import atomic_write
    atomic_write(out, doc)
    if studies_dir is not None and out.parent.resolve() == study_dir(studies_dir, study_name).resolve() \
            and (out.parent / "gallery.html").is_file():  # `tune viz --study` linked it: a redraw keeps the link
        from pipeline.viz.gallery import link_gallery
        link_gallery(out, "gallery.html")
    return out
