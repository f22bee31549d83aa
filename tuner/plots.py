"""One self-contained HTML report per study (plotly; works offline — plotly.js is embedded once).

    from tuner.plots import write_report
    path = write_report(storage, "sift-8000-degensac-stereo", "studies/sift-8000-degensac-stereo/report.html")

Sections: optimisation history (infeasible trials marked), parameter importances, the (eta, r)
contour of mAA(10), mAA(10) against the median estimator seconds per pair (with the budget B), and the
mAA(10)-against-eta curves of every study of the same task in the storage (best mAA(10) per eta bin:
the paper's inlier-threshold figure).
"""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError


def _complete(study):
    from optuna.trial import TrialState
    return study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))


def _feasible(t) -> bool:
    return all(v <= 0 for v in t.constraints.values())


def fig_cost(study):
    """mAA(10) against the median estimator seconds per pair; B as a vertical line."""
    import plotly.graph_objects as go
    trials = [t for t in _complete(study) if "ransac_seconds_median" in t.user_attrs]
    fig = go.Figure()
    for feas, name, color in ((True, "feasible", "#1f77b4"), (False, "infeasible (over budget)", "#bbbbbb")):
        ts = [t for t in trials if _feasible(t) == feas]
        if not ts:
            continue
        fig.add_trace(go.Scatter(
            x=[t.user_attrs["ransac_seconds_median"] for t in ts], y=[t.value for t in ts], mode="markers", name=name,
            marker=dict(color=color, size=8),
            text=[f"#{t.number} " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                               for k, v in t.params.items()) for t in ts],
            hovertemplate="%{text}<br>median %{x:.3f} s/pair<br>mAA10 %{y:.4f}<extra></extra>"))
    b = (study.user_attrs.get("budget") or {}).get("seconds_per_pair")
    if b:
        fig.add_vline(x=float(b), line_dash="dash", line_color="red", annotation_text=f"B = {b:g} s")
    fig.update_layout(title="mAA(10) vs estimator seconds per pair (median over validation pairs)",
                      xaxis_title="estimator seconds per pair (median)", yaxis_title="mAA(10)")
    return fig


def fig_eta_curves(storage, study):
    """Best mAA(10) per log-eta bin for every study of the same task in the storage."""
    import optuna
    import plotly.graph_objects as go
    task = study.user_attrs.get("task", "stereo")
    fig = go.Figure()
    n = 0
    for summ in optuna.get_all_study_summaries(storage, include_best_trial=False):
        if not summ.user_attrs.get("imtune") or summ.user_attrs.get("task", "stereo") != task:
            continue
        st = optuna.load_study(study_name=summ.study_name, storage=storage)
        pts = [(t.params["threshold"], t.value) for t in _complete(st) if "threshold" in t.params and _feasible(t)]
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
        n += 1
    fig.update_layout(title=f"mAA(10) vs inlier threshold eta across {task} studies (best per eta bin, feasible trials)",
                      xaxis_title="eta (px)", yaxis_title="mAA(10)", xaxis_type="log")
    return fig if n else None


def write_report(storage, study_name: str, out: Path | str) -> Path:
    """Write the HTML report of one study; returns its path."""
    import optuna.visualization as ov
    import plotly.io as pio
    from tuner.study import best_feasible, load_study, trial_counts
    study = load_study(storage, study_name)
    trials = _complete(study)
    if not trials:
        raise ImtuneError(f"study {study_name!r} has no completed trial to plot")
    sections: list[tuple[str, object, str]] = []

    def add(title, make, note=""):
        try:
            fig = make()
        except Exception as e:  # noqa: BLE001 - a section that cannot be drawn says why, the rest is written
            sections.append((title, None, f"not available: {' '.join(str(e).split())[:200]}"))
            return
        sections.append((title, fig, "") if fig is not None else (title, None, note or "not enough data"))

    params = set().union(*(t.params for t in trials))
    add("Optimisation history", lambda: ov.plot_optimization_history(study, target_name="mAA(10)"))
    add("Parameter importances",
        lambda: ov.plot_param_importances(study, target_name="mAA(10)") if len(trials) >= 2 else None,
        "" if len(trials) >= 2 else "needs at least 2 completed trials")
    if {"threshold", "ratio"} <= params:
        add("(eta, r) contour of mAA(10)",
            lambda: ov.plot_contour(study, params=["threshold", "ratio"], target_name="mAA(10)"))
    else:
        sections.append(("(eta, r) contour of mAA(10)", None, "eta and r are not both searched in this study"))
    add("mAA(10) vs estimator seconds per pair", lambda: fig_cost(study))
    add("mAA(10) vs eta across studies", lambda: fig_eta_curves(storage, study),
        "needs studies with at least 2 feasible trials that search eta")
    best = best_feasible(study)
    counts = trial_counts(study)
    attrs = study.user_attrs
    head = [f"<h1>imtune study {html.escape(study_name)}</h1>",
            "<p>" + html.escape(f"trials: {counts['complete']} complete ({counts['infeasible']} infeasible), "
                                f"{counts['pruned']} pruned, {counts['fail']} failed; "
                                f"budget {attrs.get('budget', {}).get('seconds_per_pair')} s per pair, "
                                f"Gamma_max {attrs.get('budget', {}).get('gamma_max')}; "
                                f"data {attrs.get('data_fingerprint')}; code {attrs.get('code_version')}") + "</p>"]
    if best is not None:
        ps = ", ".join(f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {v}" for k, v in best.params.items())
        head.append(f"<p><b>best feasible trial #{best.number}</b>: mAA(10) = {best.value:.4f}; {html.escape(ps)}</p>")
    body, first = [], True
    for title, fig, note in sections:
        body.append(f"<h2>{html.escape(title)}</h2>")
        if fig is not None:
            body.append(pio.to_html(fig, full_html=False, include_plotlyjs=True if first else False))
            first = False
        if note:
            body.append(f"<p><i>{html.escape(note)}</i></p>")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>imtune " + html.escape(study_name) +
           "</title><style>body{font-family:sans-serif;max-width:1100px;margin:auto}</style></head><body>" +
           "\n".join(head + body) + "</body></html>")
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(doc)
    tmp.replace(out)
    return out
