"""`tune evaluate`: one fixed configuration on the stereo and/or multiview task (JSON with --json, else tables)."""
from __future__ import annotations

import json
import math
import sys

from pipeline.errors import ImtuneError
from tuner.argtypes import count_int
from tuner.evaluate import evaluate_config
from tuner.formatting import render
from tuner.options import (  # --config (issue 13 item 8)
    OPTION_FIELDS,
    add_jobs_option,
    add_multiview_options,
    add_pipeline_options,
    build_config,
    config_over,
    explicit_options,
    multiview_config,
    resolve_data,
    task_choices,
    track_explicit,
)

IM_COLUMNS = ["scene", "pairs", "repeatability_3px", "matching_score_3px", "epipolar_matching_score"]


def register(sub) -> None:
    ap = sub.add_parser("evaluate", help="evaluate one fixed configuration")
    c = ap.add_argument_group("configuration file")
    c.add_argument("--config", default=None, metavar="FILE|STUDY",
                   help="start from this configuration: a frozen.yaml, a YAML / JSON with config: feature / matching / "
                        "geometry (feature: options: reach the extractor), an IMC benchmark method JSON, or a study "
                        "name (its frozen settings); the pipeline options typed on the command line override it")
    c.add_argument("--studies-dir", default=None, help="where --config STUDY lives (default $IMTUNE_STUDIES, else studies/)")
    add_pipeline_options(ap)
    ap.add_argument("--task", default="stereo", choices=task_choices(), help="a task (see `tune list`), or both")
    add_multiview_options(ap)
    r = ap.add_argument_group("reconstruction pipeline (--task reconstruction)")
    r.add_argument("--verifier", default=None, choices=["ours", "colmap"],
                   help="who verifies the tentative matches: ours (--ransac, eta, Gamma; default) or colmap (COLMAP's "
                        "two-view verification at pycolmap's defaults)")
    r.add_argument("--two-view", default=None, choices=["F", "colmap"],
                   help="what the database stores of a verified pair: F (default) or colmap (COLMAP's two-view "
                        "estimation on our inliers picks calibrated E, planar H or F)")
    r.add_argument("--shortlist", type=count_int, default=None,
                   help="partners per image matched above 30 images (default 20; 0: every pair)")
    r.add_argument("--recon-pipeline", default=None, choices=["imtune", "colmap", "imc2025-baseline"],
                   help="imtune (default), colmap: COLMAP out of the box (its SIFT, exhaustive matching, "
                        "verification, mapper), the reference `tune test` compares with, or imc2025-baseline: "
                        "the IMC 2025 baseline (ALIKED + LightGlue at --num-features, COLMAP's verification "
                        "and mapper)")
    ap.add_argument("--pairs", action="store_true", help="include every pair record in the JSON")
    ap.add_argument("--bag-records", action="store_true", help="include every multiview bag record in the JSON")
    ap.add_argument("--intermediate", action="store_true",
                    help="also repeatability and matching score at 1..10 px (depth maps) / epipolar matching score")
    add_ci_options(ap)
    add_jobs_option(ap)
    ap.set_defaults(func=run)
    track_explicit(ap)  # which options were typed: those, and only those, override --config's values


def _ci_kind(s: str) -> str:
    import argparse
    if s.lower() not in ("bootstrap", "none"):
        raise argparse.ArgumentTypeError(f"unknown interval {s!r} (bootstrap or none)")
    return s.lower()


def _resamples(s: str) -> int:
    import argparse
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
    from tuner.argtypes import MAX_RESAMPLES, MIN_RESAMPLES, MIN_RESAMPLES_WHY, RESAMPLES_WHY
    if v < MIN_RESAMPLES:
        raise argparse.ArgumentTypeError(f"must be >= {MIN_RESAMPLES} {MIN_RESAMPLES_WHY}, got {v} (use --ci none to "
                                         "skip)")
    if v > MAX_RESAMPLES:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_RESAMPLES:,} ({RESAMPLES_WHY}), got {v}")
    return v


def add_ci_options(ap) -> None:
    """``--ci bootstrap|none`` and ``--ci-resamples N``: the 95% intervals of every mAA (shared by the commands)."""
    g = ap.add_argument_group("confidence intervals")
    g.add_argument("--ci", type=_ci_kind, default="bootstrap",
                   help="95%% interval of every mAA: bootstrap over pairs stratified by scene (bags for "
                        "multiview), seeded; none = skip")
    g.add_argument("--ci-resamples", type=_resamples, default=None, help="bootstrap resamples (default 2000)")


def ci_resamples(args) -> int:
    """The resample count the options ask for (0: no intervals)."""
    n = getattr(args, "ci_resamples", None)
    if getattr(args, "ci", "bootstrap") == "none":
        if n is not None:  # it was ignored, unsaid
            raise ImtuneError(f"--ci-resamples {n} does not apply with --ci none (no intervals): drop one of them")
        return 0
    return int(n or 2000)


def with_ci(v, ci) -> str | None:
    """A readable ``value [lo, hi]`` (3 decimals, as every mAA is shown); the value alone without an interval."""
    if v is None:
        return None
    return f"{float(v):.3f} [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else f"{float(v):.3f}"


def task_rows(section: dict, columns) -> tuple[list[dict], list[str]]:
    """Rows of one task's section: one per scene (and per group of a breakdown such as bag sizes, when the
    summaries carry ``by_size``), then a mean row when there are several scenes."""
    rows = []
    grouped = any("by_size" in s for s in section["scenes"].values())
    cols = ["scene"] + (["bag_size"] if grouped else []) + list(columns)

    def row(scene, s, size=None):
        r = dict(scene=scene, **{k: s.get(k) for k in columns})
        for k in columns:  # mAA with its interval, where computed: "value [lo, hi]"
            if s.get(f"{k}_ci"):
                r[k] = with_ci(s.get(k), s[f"{k}_ci"])
        if grouped:
            r["bag_size"] = size if size is not None else "all"
        return r
    for name, s in section["scenes"].items():
        for size, ss in (s.get("by_size") or {}).items():
            rows.append(row(name, ss, size))
        rows.append(row(name, s))
    if len(section["scenes"]) > 1 or grouped:
        rows.append(row(f"mean of {len(section['scenes'])} scene(s)", section))
    return rows, cols


def _jsonable(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None if math.isnan(o) else ("inf" if o > 0 else "-inf")
    if isinstance(o, dict):
        return {k: _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    return o


def config_of(args):
    """The configuration `tune evaluate` runs and a line saying where it came from: ``--config``'s (a file or a
    study, ``tuner.sources.resolve_source``) with the pipeline options typed on the command line on top (a
    frozen study's task too, unless --task is typed); without ``--config``, the options alone (line None)."""
    if not getattr(args, "config", None):
        return build_config(args), None
    from tuner.sources import resolve_source, studies_dir
    src = resolve_source(args.config, studies_dir(getattr(args, "studies_dir", None)))
    conf, used = config_over(src.conf, args, where=f"--config {args.config}")
    if src.frozen and "task" in explicit_options(args):  # --task over a study of another task: said, as tune test
        from pipeline.tasks import task_list
        from tuner.select import reference_task_note
        for t in task_list(args.task):
            note = reference_task_note(src, t, flag="--config", use="evaluation")
            if note:
                print(f"warning: {note}", file=sys.stderr, flush=True)
    if src.frozen and src.frozen.get("task") and "task" not in explicit_options(args):
        from pipeline.tasks import TASKS
        try:  # the file's task: an unknown one was "unknown task 'foo'" with no word of where it came from
            TASKS.get(src.frozen["task"] if isinstance(src.frozen["task"], str) else repr(src.frozen["task"]))
        except ImtuneError as e:
            raise ImtuneError(f"--config {args.config}: task: {e}") from None
        args.task = src.frozen["task"]
    pairs_note = ""
    if src.frozen and "covisibility" not in explicit_options(args):
        # the study's pairs: its co-visibility floor, not this command's default 0.1 (a study tuned at 0.3 was
        # evaluated on more, harder pairs than it reports, unsaid); as tune viz does
        cov = (src.frozen.get("data") or {}).get("min_covisibility")  # checked by tuner.freeze.FROZEN_SHAPE
        if cov is not None:
            args.covisibility = float(cov)
            args.covisibility_of_study = True
            pairs_note = f"; pairs with co-visibility >= {float(cov):g} (the study's)"
    return conf, (f"config {args.config} ({src.label})"
                  + (f"; overridden on the command line: {', '.join(used)}" if used else "") + pairs_note)


def _warn_estimator_options(args, tasks: list[str]) -> None:
    """One warning line for estimator options typed when no stereo task runs: the multiview task's COLMAP runs its
    own RANSAC, so --threshold / --max-iters / --confidence / --ransac were ignored, unsaid."""
    from pipeline.tasks import is_timed
    if any(is_timed(t) for t in tasks):  # stereo, or a plugin task built on it
        return
    typed = [o for o in ("ransac", "threshold", "max_iters", "confidence", "covisibility")
             if o in explicit_options(args)]
    if typed:
        flags = ", ".join("--" + o.replace("_", "-") for o in typed)
        print(f"warning: {flags}: the {' and '.join(tasks)} task does not use {'it' if len(typed) == 1 else 'them'} "
              "(COLMAP reconstructs each bag whole, with its own RANSAC); ignored", file=sys.stderr, flush=True)


def run(args) -> int:
    for flag, on in (("--pairs", args.pairs), ("--bag-records", args.bag_records)):
        if on and not args.json:  # the records go into the JSON only: without --json it was ignored, unsaid
            raise ImtuneError(f"{flag} adds records to the JSON output only: add --json (or drop {flag})")
    from pipeline.tasks import task_list
    from tuner.options import apply_task_defaults, check_multiview_only
    if not getattr(args, "config", None):
        apply_task_defaults(args, task_list(args.task))  # the reconstruction task's own defaults (COLMAP's SIFT)
    conf, source = config_of(args)
    check_multiview_only(args, task_list(args.task))
    recon = {k: getattr(args, d) for k, d in (("verifier", "verifier"), ("two_view", "two_view"),
                                               ("shortlist", "shortlist"), ("pipeline", "recon_pipeline"))
             if getattr(args, d, None) is not None}
    if recon and "reconstruction" not in task_list(args.task):
        flag = {"pipeline": "--recon-pipeline"}.get(next(iter(recon)), "--" + next(iter(recon)).replace("_", "-"))
        raise ImtuneError(f"{flag} is an option of the reconstruction task: add --task reconstruction, or drop it")
    data = resolve_data(args.data)
    out = evaluate_config(conf, data, args.scenes, cache_dir=args.cache, task_options=recon or None,
                          min_covisibility=args.covisibility, progress=not (args.quiet or args.json),
                          with_pairs=args.pairs, task=args.task, multiview=multiview_config(args), workers=args.workers,
                          mapper=args.mapper, submission=args.submission,
                          gt_dir=args.gt_dir, with_bags=args.bag_records, keep_models=args.keep_models,
                          intermediate=args.intermediate, ci_resamples=ci_resamples(args), jobs=args.jobs)
    if source:
        out["config_source"] = {"config": args.config, "overridden": sorted(explicit_options(args) & set(OPTION_FIELDS))}
        if getattr(args, "covisibility_of_study", False):  # the study's pairs, not the command's default
            out["config_source"]["min_covisibility"] = args.covisibility
    for section in out.values():  # the tasks' notes (bag sizes above a scene's images): on stderr, kept in the JSON
        for note in (section.get("notes") or []) if isinstance(section, dict) else []:
            print(f"warning: {note}", file=sys.stderr, flush=True)
    _warn_estimator_options(args, task_list(args.task))  # with the notes: a run stopped by bad input says that alone
    if args.json:
        print(json.dumps(_jsonable(out), indent=2))
    else:
        if source:
            print(source)
        c = conf
        from pipeline.tasks import TASKS, is_timed
        # multiview alone: COLMAP verifies the matches with its own RANSAC, the estimator's eta and Gamma play no part
        geo = (f"{c.geometry.ransac} eta={c.geometry.threshold}px Gamma={c.geometry.max_iters}"
               if any(is_timed(t) for t in task_list(args.task)) else "COLMAP's own RANSAC")
        match = (f"{c.matching.method} c>{c.matching.min_confidence:g}" if c.matching.learned
                 else f"r={c.matching.ratio} {c.matching.strategy}")
        ran = (out.get("reconstruction") or {}).get("baseline_config")
        if ran:  # --recon-pipeline imc2025-baseline: its own features and matcher, not the options above
            print(f"IMC 2025 baseline: aliked ({ran['feature']['num_features']}) | lightglue "
                  f"c>{ran['matching']['min_confidence']:g}, adaptive off | COLMAP's verification and mapper | "
                  f"data {data}")
        else:
            print(f"{c.feature.name} ({c.feature.num_features}) | {match} | {geo} | data {data}")
        from tuner.formatting import ground_truth_text
        print(f"ground truth: {ground_truth_text(out.get('ground_truth'))}")
        for name in TASKS.names():
            if name in out:
                task = TASKS.get(name)
                rows, cols = task_rows(out[name], task.columns)
                ci = (out[name].get("ci") or {})
                note = task.note + (f"; [95% interval: {ci['method']}, {ci['resamples']} resamples]" if ci else "")
                print(f"{name}: {note}" if note else name)
                from tuner.formatting import render_fitted  # split by columns to fit a terminal, scene in each
                print(render_fitted(rows, cols))
        if "intermediate" in out:
            im = out["intermediate"]
            rows = [dict(scene=n, **{k: s.get(k) for k in IM_COLUMNS[1:]}) for n, s in im["scenes"].items()]
            rows.append(dict(scene="mean", **{k: im.get(k) for k in IM_COLUMNS[1:]}))
            print("intermediate: tentative matches before RANSAC; repeatability / matching score need depth maps")
            print(render(rows, "markdown", IM_COLUMNS))
    return 0
