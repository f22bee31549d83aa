"""One self-contained HTML report per study (plotly; works offline — plotly.js is embedded once).

    from tuner.plots import write_report
    path = write_report(storage, "sift-8000-degensac-stereo", "studies/sift-8000-degensac-stereo/report.html")

Sections: optimisation history (infeasible trials marked), parameter importances, the (eta, r)
contour of mAA(10), mAA(10) against the median estimator seconds per pair (with the budget B), and the
mAA(10)-against-eta curves of every study of the same task in the storage (best mAA(10) per eta bin:
the paper's inlier-threshold figure), and the breakdowns of the frozen (best feasible) trial by scene:
accuracy against the angular threshold (1..10 deg; stereo pairs, or multiview pairs of the bags) and
mAA(10) by co-visibility bin (stereo) — from the trial's user attributes (validation scenes) and, once
`tune test` has run, from ``<studies dir>/<study>/test.json`` (test scenes, mean over the runs).
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


def breakdown_sources(study, best, studies_dir=None) -> list[tuple[str, dict]]:
    """[(label, {scene: summary with "accuracy" and maybe "covisibility"})]: the best trial's validation
    scenes, then the test scenes of test.json (per scene, averaged over the runs) when it is there."""
    import json

    from tuner.freeze import study_dir
    out = []
    if best is not None and best.user_attrs.get("scenes"):
        out.append((f"validation (trial #{best.number})", best.user_attrs["scenes"]))
    if studies_dir is not None:
        p = study_dir(studies_dir, study.study_name) / "test.json"
        try:
            t = json.loads(p.read_text()) if p.is_file() else None
        except (OSError, ValueError):
            t = None
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
            out.append((f"test (trial #{t.get('trial')}, {len(t['runs'])} runs)", scenes))
    return out


def fig_accuracy_threshold(sources, task: str = "stereo"):
    """Accuracy against the angular threshold (1..10 deg), one line per scene and source."""
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
    fig.update_layout(title=f"{task} pose accuracy vs angular threshold, by scene (frozen trial)",
                      xaxis_title="threshold (deg)", yaxis_title="accuracy (fraction of pairs within)",
                      xaxis=dict(dtick=1), yaxis=dict(range=[0, 1.02]))
    return fig


def fig_covisibility(sources):
    """mAA(10) by co-visibility bin (pairs with co-visibility >= edge), one bar group per scene and source."""
    import plotly.graph_objects as go
    fig = go.Figure()
    for label, scenes in sources:
        for name, sm in scenes.items():
            cov = sm.get("covisibility")
            if not cov:
                continue
            bins = [b for b in cov if b != "unknown"]
            fig.add_trace(go.Bar(x=bins, y=[cov[b]["mAA10"] for b in bins], name=f"{name} - {label}",
                                 text=[f"{cov[b].get('pairs')} pairs" for b in bins],
                                 hovertemplate="co-visibility %{x}<br>mAA10 %{y:.4f}<br>%{text}<extra></extra>"))
    if not fig.data:
        return None
    fig.update_layout(title="stereo mAA(10) by co-visibility bin, by scene (frozen trial)", barmode="group",
                      xaxis_title="co-visibility bin (pairs with co-visibility >= edge)", yaxis_title="mAA(10)")
    return fig


def write_report(storage, study_name: str, out: Path | str, studies_dir: Path | str | None = None) -> Path:
    """Write the HTML report of one study; returns its path. ``studies_dir``: where test.json is read
    for the test-scene breakdowns."""
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
    if study.user_attrs.get("task", "stereo") == "multiview":
        sections.append(("mAA(10) vs estimator seconds per pair", None,
                         "multiview study: COLMAP runs its own RANSAC, no estimator budget"))
    else:
        add("mAA(10) vs estimator seconds per pair", lambda: fig_cost(study))
    add("mAA(10) vs eta across studies", lambda: fig_eta_curves(storage, study),
        "needs studies with at least 2 feasible trials that search eta")
    best = best_feasible(study)
    task = study.user_attrs.get("task", "stereo")
    sources = breakdown_sources(study, best, studies_dir)
    add("Accuracy vs angular threshold (1..10 deg), by scene", lambda: fig_accuracy_threshold(sources, task),
        "no per-scene accuracy stored for the frozen trial (trials of older imtune versions; rerun `tune test`)")
    if task == "stereo":
        add("mAA(10) by co-visibility bin, by scene", lambda: fig_covisibility(sources),
            "no co-visibility breakdown for the frozen trial (scenes without co-visibility, or trials of older "
            "imtune versions; rerun `tune test`)")
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
