"""Tables over every imtune study in a storage (the paper's tables).

    from tuner.reports import collect_studies, settings_rows, results_rows
    studies = collect_studies(storage)        # [StudyInfo, ...]
    render(*settings_rows(studies))           # optimal settings: one row per feature (+ count)
    render(*results_rows(studies))            # test results: NF, NI and mAA(10) per estimator, rank

Optimal settings (``tune table``): for each feature and feature count, the frozen inlier threshold
eta of each estimator's study and the ratio test r. Each estimator study tunes its own r; the ``r``
column is that of the study with the best validation mAA(10) (named in ``r from``), the paper's
single r per feature; ``--format json`` gives every study's values. ``r_multiview`` is the frozen r of the
multiview studies (``tune --task multiview``) of the same feature and count (the best by validation
multiview mAA(10) when there are several).

Test results (``tune results``): NF (features per image), then per estimator NI (inliers per pair)
and mAA(10) on the test scenes (mean of the test runs), and the rank of each feature by its best
mAA(10) over estimators (1 = best).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import ImtuneError


@dataclass
class StudyInfo:
    name: str
    task: str
    feature: str
    num_features: int
    ransac: str
    attrs: dict
    best: object  # FrozenTrial or None (best feasible)
    n_complete: int
    test: dict | None


def collect_studies(storage, task: str | None = None, studies_dir: Path | str | None = None) -> list[StudyInfo]:
    """Every imtune study in the storage (others are skipped), with its best feasible trial and test
    summary (study attribute ``test``, else ``<studies_dir>/<study>/test.json``)."""
    import optuna
    from optuna.trial import TrialState

    from tuner.freeze import study_dir, test_summary
    from tuner.study import best_feasible
    out = []
    for summ in optuna.get_all_study_summaries(storage, include_best_trial=False):
        attrs = summ.user_attrs
        if not attrs.get("imtune"):
            continue
        if task and attrs.get("task", "stereo") != task:
            continue
        study = optuna.load_study(study_name=summ.study_name, storage=storage)
        test = attrs.get("test")
        if test is None and studies_dir is not None:
            p = study_dir(studies_dir, summ.study_name) / "test.json"
            if p.is_file():
                try:
                    test = test_summary(json.loads(p.read_text()))
                except (OSError, ValueError, KeyError):
                    test = None
        out.append(StudyInfo(name=summ.study_name, task=attrs.get("task", "stereo"), feature=attrs.get("feature", "?"),
                             num_features=int(attrs.get("num_features") or 0), ransac=attrs.get("ransac", "?"),
                             attrs=attrs, best=best_feasible(study),
                             n_complete=len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))),
                             test=test))
    return out


def _groups(studies: list[StudyInfo]):
    groups: dict[tuple, list[StudyInfo]] = {}
    for s in studies:
        groups.setdefault((s.feature, s.num_features), []).append(s)
    return dict(sorted(groups.items(), key=lambda kv: (kv[0][1], kv[0][0])))


def _estimators(studies: list[StudyInfo]) -> list[str]:
    return sorted({s.ransac for s in studies})


def _param(s: StudyInfo, name: str):
    if s.best is None:
        return None
    if name in s.best.params:
        return s.best.params[name]
    fixed = (s.attrs.get("search_space_resolved") or {}).get("fixed", {})
    if name in fixed:
        return fixed[name]
    sec = "matching" if name in ("ratio", "strategy") else "geometry"
    return (s.attrs.get("pipeline") or {}).get(sec, {}).get(name)


def settings_rows(studies: list[StudyInfo], fmt: str = "markdown",
                  multiview: list[StudyInfo] | None = None) -> tuple[list[dict], list[str]]:
    """(rows, columns) of the optimal-settings table; ``multiview`` studies fill ``r_multiview``."""
    ests = _estimators(studies)
    mv_groups = _groups(list(multiview or []))
    keys = sorted(set(_groups(studies)) | set(mv_groups), key=lambda k: (k[1], k[0]))
    groups = _groups(studies)
    rows = []
    for feat, nf in keys:
        group = groups.get((feat, nf), [])
        row = {"feature": feat, "features": nf}
        by_est = {s.ransac: s for s in group}
        for e in ests:
            s = by_est.get(e)
            v = _param(s, "threshold") if s else None
            row[f"eta {e}"] = round(float(v), 3) if isinstance(v, (int, float)) else v
        scored = [s for s in group if s.best is not None]
        if scored:
            top = max(scored, key=lambda s: s.best.value)
            r = _param(top, "ratio")
            row["r"] = round(float(r), 3) if isinstance(r, (int, float)) else r
            row["r from"] = top.ransac
            row["mAA10 val"] = round(float(top.best.value), 4)
        else:
            row.update({"r": None, "r from": None, "mAA10 val": None})
        mv_scored = [s for s in mv_groups.get((feat, nf), []) if s.best is not None]
        mv_top = max(mv_scored, key=lambda s: s.best.value) if mv_scored else None
        r = _param(mv_top, "ratio") if mv_top else None
        row["r_multiview"] = round(float(r), 3) if isinstance(r, (int, float)) else r
        row["mAA10 mv val"] = round(float(mv_top.best.value), 4) if mv_top else None
        if fmt == "json":
            row["studies"] = {s.ransac: {"study": s.name, "trial": s.best.number if s.best else None,
                                         "value": s.best.value if s.best else None,
                                         "params": dict(s.best.params) if s.best else None,
                                         "gamma_max": (s.attrs.get("budget") or {}).get("gamma_max"),
                                         "budget": (s.attrs.get("budget") or {}).get("seconds_per_pair"),
                                         "complete_trials": s.n_complete}
                              for s in group}
            row["multiview_studies"] = {s.ransac: {"study": s.name, "trial": s.best.number if s.best else None,
                                                   "value": s.best.value if s.best else None,
                                                   "params": dict(s.best.params) if s.best else None,
                                                   "complete_trials": s.n_complete}
                                        for s in mv_groups.get((feat, nf), [])}
        rows.append(row)
    cols = ["feature", "features"] + [f"eta {e}" for e in ests] + ["r", "r from", "mAA10 val"]
    if multiview:
        cols += ["r_multiview", "mAA10 mv val"]
    if fmt == "json":
        cols += ["studies"] + (["multiview_studies"] if multiview else [])
    return rows, cols


def results_rows(studies: list[StudyInfo], fmt: str = "markdown") -> tuple[list[dict], list[str]]:
    """(rows, columns) of the test-results table, ranked by each feature's best mAA(10)."""
    tested = [s for s in studies if s.test]
    ests = _estimators(tested)
    rows = []
    for (feat, nf), group in _groups(tested).items():
        row = {"feature": feat, "features": nf}
        nfs = [s.test.get("NF") for s in group if s.test.get("NF") is not None]
        row["NF"] = round(float(sum(nfs) / len(nfs)), 1) if nfs else None
        by_est = {s.ransac: s for s in group}
        best = None
        for e in ests:
            s = by_est.get(e)
            ni = s.test.get("NI") if s else None
            m = s.test.get("mAA10") if s else None
            row[f"NI {e}"] = round(float(ni), 1) if ni is not None else None
            row[f"mAA10 {e}"] = round(float(m), 4) if m is not None else None
            if m is not None and (best is None or m > best[0]):
                best = (m, e)
        row["best"] = best[1] if best else None
        row["_score"] = best[0] if best else -1.0
        if fmt == "json":
            row["studies"] = {s.ransac: {"study": s.name, **s.test} for s in group}
        rows.append(row)
    order = sorted(range(len(rows)), key=lambda i: -rows[i]["_score"])
    for rank, i in enumerate(order, 1):
        rows[i]["rank"] = rank
    rows = [rows[i] for i in order]
    for r in rows:
        r.pop("_score")
    cols = ["rank", "feature", "features", "NF"]
    for e in ests:
        cols += [f"NI {e}", f"mAA10 {e}"]
    cols.append("best")
    if fmt == "json":
        cols.append("studies")
    return rows, cols


def render_table(rows, cols, fmt: str) -> str:
    from tuner.formatting import render
    if fmt not in ("markdown", "csv", "latex", "json"):
        raise ImtuneError(f"unknown format {fmt!r} (choose markdown, csv, latex or json)")
    return render(rows, fmt, cols)
