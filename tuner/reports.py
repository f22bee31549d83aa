"""Tables over every imtune study in a storage (the paper's tables).

    from tuner.reports import collect_studies, settings_rows, results_rows
    studies = collect_studies(storage)        # [StudyInfo, ...]
    render(*settings_rows(studies))           # optimal settings: one row per feature (+ count)
    render(*results_rows(studies))            # test results: NF, NI and mAA(10) per estimator, rank

Optimal settings (``tune table``), as the paper's "optimal hyper-parameters" tables: for each feature and
feature count, the ratio test r for stereo (``r``) and multiview (``r_multiview``, the frozen r of the
``tune --task multiview`` studies, the best by validation multiview mAA(10) when there are several), then
for each estimator the frozen inlier threshold eta (px) and iteration cap Gamma, and the time budget B
they were tuned under (seconds per pair, median estimator CPU time). Each estimator study tunes its own r;
``r`` is that of the study with the best validation mAA(10) (named in ``r from``), the paper's single r
per feature. ``--format latex`` is a booktabs table with a caption; ``--format json`` gives every
study's values.

Test results (``tune results``): NF (features per image), then per estimator NI (inliers per pair)
and mAA(10) on the test scenes (mean of the test runs), and the rank of each feature by its best
mAA(10) over estimators (1 = best).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.protocol import trial_value  # a pareto study's trials have two values: mAA10 first


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


def study_test(name: str, attrs: dict, studies_dir: Path | str | None = None, warn=None) -> dict | None:
    """A study's test summary: its attribute ``test``, else ``<studies_dir>/<study>/test.json``'s; None if it has
    none. ``warn(line)``: told of a test.json that cannot be read."""
    from tuner.freeze import load_test_file, study_dir, test_summary
    test = attrs.get("test")
    if test is None and studies_dir is not None:
        p = study_dir(studies_dir, name) / "test.json"
        d, why = load_test_file(p, name)
        try:
            test = test_summary(d) if d is not None else None
        except (ValueError, KeyError, AttributeError, TypeError):
            why = "not a test result"
        if why and warn is not None:  # the study's test results vanished from the tables, unsaid
            warn(f"{p} cannot be read ({why}): study {name} is shown without test results; "
                 f"rerun `tune test --study {name}` to rewrite it")
    return test


def collect_studies(storage, task: str | None = None, studies_dir: Path | str | None = None,
                    warn=None, objective: str | None = None) -> list[StudyInfo]:
    """Every imtune study in the storage (others are skipped), with the trial it freezes (``best``: its selection
    rule's pick, by default the best feasible trial) and test
    summary (study attribute ``test``, else ``<studies_dir>/<study>/test.json``). ``warn(line)``: told of a
    test.json that cannot be read. Studies of one objective only (:func:`one_objective`)."""
    import optuna
    from optuna.trial import TrialState

    out = []
    for summ in optuna.get_all_study_summaries(storage, include_best_trial=False):
        attrs = summ.user_attrs
        if not attrs.get("imtune"):
            continue
        if task and attrs.get("task", "stereo") != task:
            continue
        study = optuna.load_study(study_name=summ.study_name, storage=storage)
        test = study_test(summ.study_name, attrs, studies_dir, warn)
        out.append(StudyInfo(name=summ.study_name, task=attrs.get("task", "stereo"), feature=attrs.get("feature", "?"),
                             num_features=int(attrs.get("num_features") or 0), ransac=attrs.get("ransac", "?"),
                             attrs=attrs, best=_frozen_trial(study),
                             n_complete=len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))),
                             test=test))
    return one_objective(out, objective)


def one_objective(studies: list[StudyInfo], objective: str | None) -> list[StudyInfo]:
    """The studies that maximised ``objective`` (a pareto study counts as mAA10, its first value); with None, all of
    them when they share one objective. Studies that maximised different figures are never put in one table:
    ImtuneError naming the objectives and the option that chooses one."""
    from tuner.study_identity import study_objective

    def obj(s: StudyInfo) -> str:
        o = study_objective(s.attrs)
        return "mAA10" if o == "pareto" else o
    if objective:
        return [s for s in studies if obj(s) == objective]
    counts: dict[str, int] = {}
    for s in studies:
        counts[obj(s)] = counts.get(obj(s), 0) + 1
    if len(counts) > 1:
        raise ImtuneError("the storage holds studies of different objectives ("
                          + ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
                          + "), never ranked as one: add --objective " + " or ".join(sorted(counts)))
    return studies


def _frozen_trial(study):
    """The trial the study freezes: its selection rule (``tuner.select``; the default rule: the best feasible)."""
    from tuner.select import select_trial
    try:
        return select_trial(study, study.user_attrs.get("select"))[0]
    except ImtuneError:  # an unknown recorded rule (a newer imtune): the best feasible
        from tuner.protocol import best_feasible
        return best_feasible(study)


def row_feature(s: StudyInfo) -> str:
    """The feature column of a study's row: its feature label plus what it pins that the protocol tunes or fixes
    otherwise: a matching strategy other than 'both' ("sift+uni"), parameters pinned with --fix ("+eta3px",
    "+Gamma1000", "+r0.8") and a RANSAC confidence other than 0.999999 ("+conf0.99"). Such a study (a `tune
    findings` variant beside the main study) is another method and gets its own row: grouped by feature alone, the
    best-validated of them gave the 'sift' row its eta, Gamma and test mAA(10), unsaid."""
    from pipeline.config import GeometryConfig
    a = s.attrs or {}
    pipe = a.get("pipeline") or {}
    space = a.get("search_space_resolved") or {}
    searched = set(space.get("params") or {})
    fixed = dict(space.get("fixed") or {})
    tags = []
    strategy = fixed.pop("strategy", None) or (pipe.get("matching") or {}).get("strategy")
    if strategy and strategy != "both" and "strategy" not in searched:
        tags.append(str(strategy))
    names = {"threshold": ("eta", "px"), "max_iters": ("Gamma", ""), "ratio": ("r", "")}
    order = ("ratio", "threshold", "max_iters")  # r, eta, Gamma as the paper lists them; then the rest
    for k, v in sorted(fixed.items(), key=lambda kv: (order.index(kv[0]) if kv[0] in order else 3, kv[0])):
        sym, unit = names.get(k, (k, ""))
        val = f"{int(v)}" if k == "max_iters" and isinstance(v, (int, float)) else \
            (f"{v:g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v))
        tags.append(f"{sym}{val}{unit}")
    conf = (pipe.get("geometry") or {}).get("confidence")
    if isinstance(conf, (int, float)) and conf != GeometryConfig.confidence:
        tags.append(f"conf{conf:g}")
    return s.feature + "".join(f"+{t}" for t in tags)


def _groups(studies: list[StudyInfo]):
    groups: dict[tuple, list[StudyInfo]] = {}
    for s in studies:
        groups.setdefault((row_feature(s), s.num_features), []).append(s)
    return dict(sorted(groups.items(), key=lambda kv: (kv[0][1], kv[0][0])))


def _val_pairs(s: StudyInfo) -> float:
    """Validation pairs (or bags) a study was tuned on (0 when not recorded)."""
    v = (s.attrs.get("data") or {}).get("pairs")
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else 0.0


def _by_estimator(group: list[StudyInfo]) -> dict[str, StudyInfo]:
    """One study per estimator of a (feature, count) group: where several studies share the estimator (a second
    --study name, a findings study beside the main one), the one tuned on the most validation pairs (a
    `tune findings --quick` study's 12 pairs per scene against the main job's 55: values of different pair sets
    are not comparable, and the fuller set is the protocol's), then the best validation value of the trial it
    freezes (studies without one last; then by name). It was the last study listed in the storage, so the row
    could show the eta and Gamma of an unfinished study next to the r of another ("eta -" beside a tuned eta)."""
    out: dict[str, StudyInfo] = {}
    for st in sorted(group, key=lambda x: x.name):
        cur = out.get(st.ransac)
        if cur is None or _study_rank(st) > _study_rank(cur):
            out[st.ransac] = st
    return out


def _study_rank(st: StudyInfo) -> tuple:
    """Which of several studies a table shows: one with a frozen trial, then the most validation pairs, then the
    best validation value."""
    v = trial_value(st.best) if st.best is not None else None
    return (v is not None, _val_pairs(st) if v is not None else 0.0, v if v is not None else 0.0)


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
    from tuner.protocol import LEAVES
    lf = LEAVES.get(name)
    sec = lf.section if lf is not None else "geometry"
    if sec == "mapper" and "mapper" not in (s.attrs.get("pipeline") or {}):  # at its defaults, not written
        from pipeline.config import MapperConfig
        return getattr(MapperConfig(), lf.field) if lf is not None else None
    return (s.attrs.get("pipeline") or {}).get(sec, {}).get(name)


def _uses_iterations(estimator: str) -> bool:
    """Whether the estimator has an iteration cap Gamma (False for the 8-point fit); unknown here
    (an estimator not installed on this machine): True, the study's value is shown."""
    try:
        from pipeline.geometry import get_estimator
        return bool(getattr(get_estimator(estimator), "uses_iterations", True))
    except Exception:  # noqa: BLE001 - a table of another machine's studies still prints
        return True


def _num(v, digits: int):
    return round(float(v), digits) if isinstance(v, (int, float)) and not isinstance(v, bool) else v


def _budget(s: StudyInfo):
    return (s.attrs.get("budget") or {}).get("seconds_per_pair")


def _settings_caption(studies: list[StudyInfo], multiview: list[StudyInfo], per_est_budget: bool) -> tuple[str, str]:
    """(plain caption, LaTeX caption) of the optimal-settings table: where the values come from."""
    from tuner.formatting import latex_escape
    scenes = sorted({", ".join((s.attrs.get("data") or {}).get("val_scenes") or []) for s in studies + multiview} - {""})
    where = f"validation scenes {scenes[0]}" if len(scenes) == 1 else "the validation scenes of each study"
    budgets = sorted({_budget(s) for s in studies if _budget(s) is not None})
    if not studies:
        text = (f"Optimal ratio test r for multiview reconstruction (COLMAP, which runs its own RANSAC) on the "
                f"{where}.")
        return text, latex_escape(text).replace("ratio test r", "ratio test $r$")
    if budgets and not per_est_budget:
        b_txt = f"B = {budgets[0]:g} s per pair"
    else:
        b_txt = "B of each study (columns B, s per pair)"
    plain = (f"Optimal settings on the {where}: ratio test r (stereo: from the estimator study with the best "
             f"validation mAA(10°); multiview: COLMAP), inlier threshold eta (px) and maximum iterations Gamma "
             f"of each estimator under the time budget {b_txt} (median estimator CPU time).")
    tex = (f"Optimal settings on the {latex_escape(where)}: ratio test $r$ (stereo: from the estimator study with "
           f"the best validation mAA($10^\\circ$); multiview: COLMAP), inlier threshold $\\eta$ (px) and maximum "
           f"iterations $\\Gamma$ of each estimator under the time budget "
           + (f"$B = {budgets[0]:g}$\\,s per pair" if budgets and not per_est_budget
              else "$B$ of each study (columns $B$, s per pair)")
           + " (median estimator CPU time).")
    return plain, tex


GROUND_TRUTH_NOT_RECORDED = "not recorded (written before imtune recorded it)"


def _truth(origins) -> str:
    """One line of recorded ground-truth origins (scene -> :meth:`pipeline.data.scene.Scene.truth_origin`), or that an
    older record does not say."""
    from tuner.formatting import ground_truth_text
    return ground_truth_text(origins) or GROUND_TRUTH_NOT_RECORDED


def _val_truth(s: StudyInfo) -> str:
    """Where a study's validation scenes' poses come from, as the study recorded it."""
    return _truth((s.attrs.get("data") or {}).get("ground_truth"))


def _test_truth(s: StudyInfo) -> str:
    """Where a study's test scenes' poses come from, as its test (test.json, the study's test summary) recorded it."""
    return _truth((s.test or {}).get("ground_truth"))


def _val_set(s: StudyInfo) -> str:
    """What a study was tuned on: its validation scenes and pairs (e.g. ``fountain-P11 (55 pairs)``)."""
    d = s.attrs.get("data") or {}
    scenes = ", ".join(str(x) for x in (d.get("val_scenes") or [])) or "?"
    return scenes + (f" ({_val_pairs(s):g} pairs)" if _val_pairs(s) else "")


def settings_rows(studies: list[StudyInfo], fmt: str = "markdown",
                  multiview: list[StudyInfo] | None = None,
                  multiview_column: bool = True, warn=None) -> tuple[list[dict], list[str]]:
    """(rows, columns) of the optimal-settings table (the paper's "optimal hyper-parameters" tables):
    per feature and feature count (``features``) the ratio test ``r`` (stereo; from the estimator study
    with the best validation mAA(10), named in ``r from``) and ``r_multiview``, then per estimator the
    inlier threshold ``eta <est>`` (px) and iteration cap ``Gamma <est>``, and the budget ``B`` (s per
    pair; one ``B <est>`` column per estimator when the studies differ). ``columns`` is a
    :class:`tuner.formatting.Columns` with the caption of the LaTeX form; ``multiview`` studies fill
    ``r_multiview`` (an empty column without them, as the paper's table has it, unless ``multiview_column`` is
    False: a table asked for one task only). Where the validation poses come from (the study's recorded
    ``data.ground_truth``, "not recorded" for an older study) ends the caption when every row's study says the same,
    else is a ``val ground truth`` column (always one in ``json``). ``warn(line)``: told when the stereo studies shown were tuned on
    different validation sets (scenes or pairs)."""
    from tuner.formatting import Columns
    multiview = list(multiview or [])
    ests = _estimators(studies)
    mv_groups = _groups(multiview)
    groups = _groups(studies)
    sets: dict[str, list[str]] = {}
    for st in (x for g in groups.values() for x in _by_estimator(g).values() if x.best is not None):
        sets.setdefault(_val_set(st), []).append(st.name)
    if len(sets) > 1 and warn is not None:  # one table of settings tuned on different pairs, unsaid
        warn("the settings shown were tuned on different validation sets (" + "; ".join(
            f"{k}: {', '.join(v[:3])}{' ...' if len(v) > 3 else ''}" for k, v in sets.items())
            + "): their validation values are not comparable (--format json names each row's studies)")
    keys = sorted(set(groups) | set(mv_groups), key=lambda k: (k[1], k[0]))
    per_est_budget = len({_budget(s) for s in studies}) > 1
    iters = {e: _uses_iterations(e) for e in ests}
    rows = []
    for feat, nf in keys:
        group = groups.get((feat, nf), [])
        row = {"feature": feat, "features": nf}
        by_est = _by_estimator(group)
        scored = [s for s in by_est.values() if s.best is not None]  # r from a study the row shows
        top = max(scored, key=_study_rank) if scored else None
        row["r"] = _num(_param(top, "ratio"), 3) if top else None
        mv_scored = [s for s in mv_groups.get((feat, nf), []) if s.best is not None]
        mv_top = max(mv_scored, key=_study_rank) if mv_scored else None
        row["r_multiview"] = _num(_param(mv_top, "ratio"), 3) if mv_top else None
        for e in ests:
            s = by_est.get(e)
            row[f"eta {e}"] = _num(_param(s, "threshold"), 4) if s else None
            g = _param(s, "max_iters") if s and iters[e] else None
            row[f"Gamma {e}"] = int(g) if isinstance(g, (int, float)) and not isinstance(g, bool) else g
            if per_est_budget:
                row[f"B {e}"] = _budget(s) if s else None
        if not per_est_budget:
            bs = {_budget(s) for s in group} - {None}
            row["B"] = bs.pop() if len(bs) == 1 else None
        row["r from"] = top.ransac if top else None
        truth_of = top or mv_top
        row["val ground truth"] = _val_truth(truth_of) if truth_of else None
        row["mAA10 val"] = _num(trial_value(top.best), 4) if top else None
        row["mAA10 mv val"] = _num(trial_value(mv_top.best), 4) if mv_top else None
        for key, st in (("mAA10 val", top), ("mAA10 mv val", mv_top)):  # the optimum's 95% interval
            ci = (st.best.user_attrs.get("mAA10_ci") if st is not None else None)
            if fmt == "json":
                row[f"{key} ci"] = [round(float(x), 4) for x in ci] if ci else None
            elif ci and row[key] is not None:
                row[key] = _with_ci(row[key], ci)
        if fmt == "json":
            row["studies"] = {s.ransac: {"study": s.name, "trial": s.best.number if s.best else None,
                                         "value": trial_value(s.best) if s.best else None,
                                         "params": dict(s.best.params) if s.best else None,
                                         "gamma_max": (s.attrs.get("budget") or {}).get("gamma_max"),
                                         "budget": _budget(s),
                                         "complete_trials": s.n_complete}
                              for s in by_est.values()}
            row["multiview_studies"] = {s.ransac: {"study": s.name, "trial": s.best.number if s.best else None,
                                                   "value": trial_value(s.best) if s.best else None,
                                                   "params": dict(s.best.params) if s.best else None,
                                                   "complete_trials": s.n_complete}
                                        for s in mv_groups.get((feat, nf), [])}
        rows.append(row)
    names = ["feature", "features"] + (["r"] if studies else []) + \
        (["r_multiview"] if multiview or multiview_column else [])
    for e in ests:
        names += [f"eta {e}", f"Gamma {e}"] + ([f"B {e}"] if per_est_budget else [])
    if studies and not per_est_budget:
        names.append("B")
    if studies:
        names += ["r from", "mAA10 val"]
    if multiview:
        names.append("mAA10 mv val")
    # where the validation poses come from: the caption when every row's study says the same, else a column
    truths = {r["val ground truth"] for r in rows if r["val ground truth"] is not None}
    if len(truths) > 1 or fmt == "json":
        names.append("val ground truth")
    if fmt == "json":
        names += (["mAA10 val ci"] if studies else []) + (["mAA10 mv val ci"] if multiview else [])
        names += ["studies"] + (["multiview_studies"] if multiview else [])
    plain, tex = _settings_caption(studies, multiview, per_est_budget)
    from tuner.formatting import latex_escape
    truth = (f" Validation ground truth: {truths.pop()}." if len(truths) == 1 else
             " Validation ground truth of each row's study: column 'val ground truth'." if truths else "")
    plain, tex = plain + truth, tex + latex_escape(truth)
    labels = {"r": "$r$ stereo", "r from": "$r$ from", "r_multiview": "$r$ multiview", "B": "$B$ (s)",
              "mAA10 val": "val.\\ mAA($10^\\circ$)", "mAA10 mv val": "val.\\ multiview mAA($10^\\circ$)"}
    for e in ests:
        labels[f"eta {e}"] = "$\\eta$ " + _tex(e)
        labels[f"Gamma {e}"] = "$\\Gamma$ " + _tex(e)
        labels[f"B {e}"] = "$B$ " + _tex(e) + " (s)"
    return rows, Columns(names, caption=plain, labels=labels, latex_caption=tex)


def _tex(s) -> str:
    from tuner.formatting import latex_escape
    return latex_escape(s)


def _test_pair_runs(s: StudyInfo, studies_dir, warn=None) -> list[list[dict]] | None:
    """Per-run stereo pair records of a study's test runs, from ``<studies_dir>/<study>/test.json``: each run's
    ``pair_errors`` ([scene, pair, err] triples) or ``pair_records`` (dicts). None where not stored; ``warn(line)``
    is told when the file is there but cannot be read (the study's interval and ties then come from its summary)."""
    if studies_dir is None:
        return None
    from tuner.freeze import load_test_file, study_dir
    p = study_dir(studies_dir, s.name) / "test.json"
    d, why = load_test_file(p, s.name)
    if d is not None:
        try:
            return _pair_runs(d)
        except (ValueError, AttributeError, TypeError, KeyError) as e:
            why = f"its pair errors: {str(e).splitlines()[0][:80] if isinstance(e, ValueError) else 'malformed'}"
    if why and warn is not None:  # the interval silently came from the summary and ties became unpaired
        warn(f"{p} cannot be read ({why}): study {s.name}'s test interval and rank ties come from its stored "
             f"summary (unpaired); rerun `tune test --study {s.name}` to rewrite it")
    return None


def _pair_error(e) -> float:
    """A stored pair error in degrees: a number >= 0, or None / "inf" / Infinity for a failed pair (+inf)."""
    err = float("inf") if e is None else float(e)
    if math.isnan(err) or err < 0:
        raise ValueError(f"a pair error of {e!r} degrees")
    return err


def _pair_runs(d: dict) -> list[list[dict]] | None:
    """Each test run's records: stereo pair records, or multiview bag records (``bag_errors``: scene, bag size,
    bag, pair errors and, written since December 2026, the bag's images)."""
    out = []
    for r in d.get("runs") or []:
        if r.get("pair_errors") is not None:
            out.append([{"scene": sc, "pair": pr, "err": _pair_error(e)} for sc, pr, e in r["pair_errors"]])
        elif r.get("pair_records") is not None:
            out.append([{"scene": x["scene"], "pair": x["pair"], "err": _pair_error(x["err"])}
                        for x in r["pair_records"]])
        elif r.get("bag_errors") is not None:
            from tuner.select import _as_bags
            bags = _as_bags(r["bag_errors"])
            for b in bags:
                b["errors"] = [_pair_error(e) for e in b["errors"]]
            out.append(bags)
        else:
            return None
    return out or None


def _with_ci(m, ci) -> str | None:
    if m is None:
        return None
    # 3 decimals, as tuner.formatting shows every mAA
    return f"{float(m):.3f} [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else f"{float(m):.3f}"


def results_rows(studies: list[StudyInfo], fmt: str = "markdown", studies_dir: Path | str | None = None,
                 n_resamples: int = 2000, seed: int = 0, warn=None) -> tuple[list[dict], list[str]]:
    """(rows, columns) of the test-results table, ranked by each feature's best mAA(10), with ties.

    Each mAA(10) is shown as ``value [lo, hi]`` (95% interval) where one is known: from the test runs' pair
    errors in ``<studies_dir>/<study>/test.json`` (:func:`pipeline.metrics.uncertainty.combine_runs_interval`:
    pairs resampled within scenes, widened by the run-to-run variation), else the test summary's
    ``mAA10_ci``. Ranks: each feature (by its best estimator's study) is compared with the first (best) feature of
    the rank above it; it shares that rank when the difference is not significant — by the paired bootstrap on the common test
    pairs (:func:`~pipeline.metrics.uncertainty.rank_with_ties`) where both have pair errors, for multiview studies on
    the test bags (:func:`~pipeline.metrics.uncertainty.paired_bags`) where every row's test holds the same bags
    (scene, size and images), else when their intervals overlap
    (:func:`~pipeline.metrics.uncertainty.rank_by_intervals`, unpaired and conservative; the column says why).
    The ``ties`` column says which rule shared a rank, or that no interval was available. Where the test poses come
    from (test.json's ``data.ground_truth`` of each row's best study, "not recorded" for an older one) ends the
    caption when every row says the same, else is a ``ground truth`` column (always one in ``json``). ``--format json``
    adds ``mAA10_ci <est>`` lists and ``studies``. ``warn(line)``: told of a test.json that cannot be read."""
    from pipeline.metrics.uncertainty import (
        bags_differ,
        combine_bag_runs_interval,
        combine_runs_interval,
        is_bag_records,
        rank_by_intervals,
        rank_with_ties,
    )
    from pipeline.tasks import task_class  # what each study's task declares (its unit, what verifies its matches)
    tested = [s for s in studies if s.test]
    # replicated studies (`tune --replicates K`, tuner.replicates): the first study stands for all K (its figure the
    # mean over replicates, its interval the replicated one); the others are not rows of their own
    from tuner.replicates import load_replicated
    replicated = {s.name: load_replicated(studies_dir, s.name) for s in tested} if studies_dir is not None else {}
    replicated = {k: v for k, v in replicated.items() if v and v.get("unit", "pairs") == "pairs"}  # mAA tables
    members = {r["study"] for v in replicated.values() for r in v["replicates"][1:]}
    tested = [s for s in tested if s.name not in members]
    ests = _estimators(tested)
    shown = [st for group in _groups(tested).values() for st in _by_estimator(group).values()]
    sets: dict[str, list[str]] = {}
    for st in shown:
        sets.setdefault(_test_set(st), []).append(st.name)
    several = len(sets) > 1
    if several and warn is not None:  # one table ranked numbers measured on different pairs, unsaid
        warn("the studies shown were tested on different test sets (" + "; ".join(
            f"{k}: {', '.join(v[:3])}{' ...' if len(v) > 3 else ''}" for k, v in sets.items())
            + "): mAA(10) of different test sets are not comparable; the 'test set' column says which each row's "
              "best study measured (rerun `tune test --study NAME --scenes ...` to align them)")
    rows = []
    for (feat, nf), group in _groups(tested).items():
        row = {"feature": feat, "features": nf}
        nfs = [s.test.get("NF") for s in group if s.test.get("NF") is not None]
        row["NF"] = round(float(sum(nfs) / len(nfs)), 1) if nfs else None
        by_est = _by_estimator(group)
        best = None
        for e in ests:
            s = by_est.get(e)
            ni = s.test.get("NI") if s else None
            m = s.test.get("mAA10") if s else None
            runs = _test_pair_runs(s, studies_dir, warn) if s and m is not None else None
            ci = s.test.get("mAA10_ci") if s else None
            if runs:
                combine = combine_bag_runs_interval if is_bag_records(runs[0]) else combine_runs_interval
                ci = combine(runs, taus=(10,), n_resamples=n_resamples, seed=seed)["mAA10_ci"]
            rep = replicated.get(s.name) if s else None
            per_rep = [runs] if runs else None  # the test runs of each replicate (one for a single tuning)
            if rep is not None and m is not None:  # the replicated figure; the ranks compare replicates x pairs
                m, ci = rep["mAA10"], rep["mAA10_ci"]
                per_rep = [list(runs or [])]
                for r in rep["replicates"][1:]:
                    other = next((x for x in studies if x.name == r["study"]), None)
                    extra = _test_pair_runs(other, studies_dir, warn) if other is not None else None
                    per_rep.append(list(extra or []))
                runs = [run for group in per_rep for run in group] or runs
            row[f"NI {e}"] = round(float(ni), 1) if ni is not None else None
            auc = s.test.get("auc10") if s else None  # pose AUC@10 beside mAA10 (tests before it have none)
            row[f"auc10 {e}"] = round(float(auc), 4) if isinstance(auc, (int, float)) else None
            if fmt == "json":
                row[f"mAA10 {e}"] = round(float(m), 4) if m is not None else None
                row[f"mAA10_ci {e}"] = [round(float(v), 4) for v in ci] if ci else None
            else:
                row[f"mAA10 {e}"] = _with_ci(m, ci)
                if rep is not None and m is not None:
                    row[f"mAA10 {e}"] += f" (K={rep['K']})"
            if m is not None and (best is None or m > best[0]):
                best = (m, e, runs, ci, per_rep)
        row["best"] = best[1] if best else None
        if several:
            row["test set"] = _test_set(by_est[best[1]]) if best else None
        row["ground truth"] = _test_truth(by_est[best[1]]) if best else None  # the test poses of its best study
        row["_best"] = best
        if fmt == "json":
            row["studies"] = {s.ransac: {"study": s.name, **s.test} for s in by_est.values()}
        rows.append(row)
    scored = [i for i, r in enumerate(rows) if r["_best"] is not None]
    name = {i: f"{rows[i]['feature']} ({rows[i]['features']})" for i in range(len(rows))}
    recs = {i: [{**x, "run": k} for k, run in enumerate(rows[i]["_best"][2] or []) for x in run] for i in scored}
    kinds = {is_bag_records(recs[i]) for i in scored if recs[i]}
    unpaired = None  # why the ranks cannot pair: then they share where the 95% intervals overlap
    if not scored or not all(recs[i] for i in scored):
        units = {task_class(st.task).unit_one for st in shown}
        unpaired = f"no {units.pop() if len(units) == 1 else 'pair'} errors in test.json"
    elif len(kinds) > 1:
        unpaired = "stereo pairs beside multiview bags"
    elif kinds == {True}:  # multiview: paired only on the same bags (scene, size, images) for every row
        for i in scored[1:]:
            why = bags_differ(recs[scored[0]], recs[i])
            if why:
                unpaired = f"{name[i]} and {name[scored[0]]}: {why}"
                break
    tuned_rows = any(rows[i]["_best"][4] and len(rows[i]["_best"][4]) > 1 for i in scored)
    if unpaired is None and tuned_rows and kinds == {False}:  # replicated rows: the tuned comparison of replicates
        from pipeline.metrics.replicates import replicated_records_comparison, replicated_records_value
        ranked = rank_with_ties([(str(i), rows[i]["_best"][4]) for i in scored], n_resamples=n_resamples, seed=seed,
                                compare=replicated_records_comparison, value=replicated_records_value)
        rule = (f"tuned comparison over replicates x test pairs (t test, variance components), Bonferroni over the "
                f"{max(1, len(scored) * (len(scored) - 1) // 2)} pairs of methods; a row tuned once (K = 1) has no "
                "tuned verdict and shares the rank")
    elif unpaired is None:  # the same pairs (bags) everywhere: paired tests
        ranked = rank_with_ties([(str(i), recs[i]) for i in scored], n_resamples=n_resamples, seed=seed)
        rule = (f"paired bootstrap and sign-flip test on the test {'bags' if kinds == {True} else 'pairs'}, "
                f"Bonferroni over the {max(1, len(scored) * (len(scored) - 1) // 2)} pairs of methods")
    else:
        ranked = rank_by_intervals([{"name": str(i), "mAA10": rows[i]["_best"][0], "mAA10_ci": rows[i]["_best"][3]}
                                    for i in scored])
        rule = f"95% intervals overlap (unpaired: {unpaired})"
        if warn is not None and kinds == {True} and "differ" in unpaired:
            warn(f"the multiview ranks are not paired: {unpaired}; they share a rank where the 95% intervals "
                 "overlap (conservative)")
    order, leader = [], None  # leader: the first row of the current rank, which every row sharing it is compared with
    for r in ranked:
        i = int(r["name"])
        rows[i]["rank"] = r["rank"]
        if r["shared"]:
            rows[i]["ties"] = f"rank shared with {name[leader]}: not significantly different ({rule})"
        elif "no common" in r.get("note", ""):
            rows[i]["ties"] = (f"not compared with {name[leader]}: no common test "
                               f"{'bags' if kinds == {True} else 'pairs'}")
        elif rows[i]["_best"][3] is None and rule.startswith("95%"):
            rows[i]["ties"] = "no interval: ranked by value alone"
        else:
            rows[i]["ties"] = ""
        if not r["shared"]:
            leader = i
        order.append(i)
    for rank, i in enumerate([i for i in range(len(rows)) if i not in order], len(order) + 1):
        rows[i]["rank"], rows[i]["ties"] = rank, "no test mAA"
        order.append(i)
    rows = [rows[i] for i in order]
    for r in rows:
        r.pop("_best")
    cols = ["rank", "feature", "features", "NF"]
    for e in ests:
        cols += [f"NI {e}", f"mAA10 {e}"] + ([f"mAA10_ci {e}"] if fmt == "json" else []) + [f"auc10 {e}"]
    truths = {r["ground truth"] for r in rows if r["ground truth"] is not None}
    cols += ["best"] + (["test set"] if several else []) + (["ground truth"] if len(truths) > 1 or fmt == "json"
                                                            else []) + ["ties"]
    # NF / NI that no row has (a multiview test records neither): left out, not a column of '-'
    cols = [c for c in cols if not (c == "NF" or c.startswith(("NI ", "auc10 "))) or any(r.get(c) is not None for r in rows)]
    if fmt == "json":
        cols.append("studies")
    from tuner.formatting import Columns
    verifiers = {task_class(st.task).verifier for st in shown}
    if shown and len(verifiers) == 1 and None not in verifiers and len(ests) == 1:
        # the task verifies the matches itself (multiview: COLMAP, its own RANSAC): the study's estimator name would
        # head a column of it
        v = verifiers.pop()
        ren = {f"mAA10 {ests[0]}": f"mAA10 {v}", f"mAA10_ci {ests[0]}": f"mAA10_ci {v}"}
        # ... and a 'best' column would name that estimator in every row, as if it had won
        rows = [{ren.get(k, k): v for k, v in r.items() if k != "best"} for r in rows]
        cols = [ren.get(c, c) for c in cols if c != "best"]
    caption = _results_caption(shown, sets, several, truths)
    shown_reps = [n for n in replicated if any(st.name == n for st in shown)]
    if fmt != "json" and shown_reps:  # a table without replicated rows keeps its caption as it was
        from pipeline.metrics.replicates import NOT_MEASURED
        note = ("mAA10 (K=k): the mean over k tuning replicates (`tune --replicates k`), its 95% interval holds the "
                "tuning variance; ranks pair on every replicate's test runs" if shown_reps else "")
        if len(shown_reps) < len(shown):
            note += ("; " if note else "") + f"a figure without (K=k) is one tuning: {NOT_MEASURED}"
        caption = f"{caption} {note[0].upper()}{note[1:]}." if caption else f"{note[0].upper()}{note[1:]}."
    return rows, Columns(cols, caption=caption)


def _results_caption(shown: list[StudyInfo], sets: dict, several: bool, truths: set | None = None) -> str:
    """What the results table shows: test numbers, on which scenes and pairs, over how many runs, with which
    interval (the settings table says its numbers are the validation scenes'; this one said nothing)."""
    from pipeline.tasks import task_class
    where = f"the test scenes {next(iter(sets))}" if len(sets) == 1 and not several else \
        "each study's test scenes (column 'test set')"
    runs = sorted({int(s.test["runs"]) for s in shown if isinstance((s.test or {}).get("runs"), (int, float))})
    n = (f"mean of {runs[0]} run{'s' if runs[0] != 1 else ''}" if len(runs) == 1 else
         f"mean of each study's test runs ({runs[0]}-{runs[-1]})" if runs else "mean of the test runs")
    # what the figures are: as the tasks shown declare them (studies of several tasks: the stereo task's columns)
    from pipeline.tasks.stereo import StereoTask
    whats = {task_class(s.task).test_figures for s in shown}
    what = whats.pop() if len(whats) == 1 else StereoTask.test_figures
    truths = set(truths or ())
    truth = (f" Test ground truth: {truths.pop()}." if len(truths) == 1 else
             " Test ground truth of each row's best study: column 'ground truth'." if truths else "")
    return (f"Test results on {where}, {n}: {what}; rank by each feature's best mAA(10°), shared with the "
            f"rank's first row where the difference to it is not significant (column 'ties').{truth}")


def _test_set(s: StudyInfo) -> str:
    """What a study's test numbers were measured on: its test scenes and pairs (e.g. ``Herz-Jesus-P8, entry-P10
    (73 pairs)``); two studies are comparable only on the same."""
    t = s.test or {}
    pairs = t.get("pairs")
    scenes = ", ".join(sorted(str(x) for x in (t.get("scenes") or []))) or "?"
    return scenes + (f" ({float(pairs):g} pairs)" if isinstance(pairs, (int, float)) else "")


def render_table(rows, cols, fmt: str) -> str:
    from tuner.formatting import render
    if fmt not in ("markdown", "csv", "latex", "json"):
        raise ImtuneError(f"unknown format {fmt!r} (choose markdown, csv, latex or json)")
    return render(rows, fmt, cols)
