"""The Optuna commands: `tune [run]`, `tune calibrate`, `tune test`, `tune table`, `tune results`,
`tune plot`, `tune dashboard`, `tune studies`.

    tune --feature sift --ransac degensac              # = tune run ...: tune, freeze, test
    tune calibrate --feature sift --ransac magsac++    # Gamma_max(B) on this machine
    tune test --study sift-8000-degensac-stereo        # frozen settings on the test scenes, 3 runs
    tune table [--format csv|latex|json]               # optimal settings over all studies
    tune results                                       # test results: NF, NI and mAA(10) per estimator
    tune plot --study NAME                             # one HTML report
    tune --objective pareto ...                        # accuracy vs estimator CPU time: study <default>-pareto
    tune plot --pareto A-pareto B-pareto               # their Pareto fronts on one figure, with the budget B
    tune dashboard [--port 8080]                       # optuna-dashboard on 127.0.0.1

Every command takes ``--storage URL`` (default ``sqlite:///<studies dir>/optuna.db``) and
``--studies-dir DIR`` (default ``$IMTUNE_STUDIES``, else ``studies/`` in the project checkout, else
``./studies``); see :mod:`tuner.storage`.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.argtypes import nonnegative_float, nonnegative_int, positive_float, positive_int, ratio_float, scene_list
from tuner.commands.evaluate import add_ci_options, ci_resamples, with_ci
from tuner.formatting import render
from tuner.options import add_pipeline_options, build_config, resolve_data

FORMATS = ("markdown", "csv", "latex", "json")


def _storage_opts(ap, storage: bool = True) -> None:
    """--storage (the Optuna storage; not for commands that never open it) and --studies-dir."""
    g = ap.add_argument_group("storage")
    if storage:
        g.add_argument("--storage", default=None,
                       help="sqlite:///PATH, postgresql://USER:PASS@HOST:PORT/DB, mysql+pymysql://..., or journal:PATH "
                            "(default $IMTUNE_STORAGE, else sqlite:///<studies dir>/optuna.db)")
    g.add_argument("--studies-dir", default=None,
                   help="frozen settings, test results, reports, budgets.json (default $IMTUNE_STUDIES, else "
                        "studies/ in the project checkout)")


def _no_storage_for_calibrate(value: str):
    """`tune calibrate --storage ...`: said, not silently ignored (a calibration is no Optuna study)."""
    raise argparse.ArgumentTypeError("tune calibrate stores its calibration in <studies dir>/budgets.json, not in an "
                                     "Optuna storage: drop --storage (--studies-dir chooses the folder; a study "
                                     "run with that --studies-dir reuses it)")


def _check_strategy(args, base) -> None:
    """``--strategy X`` beside a search space that searches the strategy, or pins another one (in the file or by
    --fix): the study searched (or pinned) it and X was ignored, unsaid."""
    if args.strategy == "both":  # the default: nothing typed to lose
        return
    from pipeline.tasks import TASKS
    from tuner.space import SPACES_DIR, load_space
    task_file = TASKS.get(args.task).space_file
    path = args.space or (SPACES_DIR / task_file if task_file else None)
    space = load_space(path, feature=base.feature.name, estimator=base.geometry.ransac, fixes=args.fix,
                       matcher=base.matching.method)
    if "strategy" in space.params:
        raise ImtuneError(f"--strategy {args.strategy} does not apply: the search space {space.source} searches the "
                          f"strategy ({', '.join(space.params['strategy'].choices)}); drop --strategy, or pin it with "
                          f"--fix strategy={args.strategy}")
    if space.fixed.get("strategy") not in (None, args.strategy):
        raise ImtuneError(f"--strategy {args.strategy} does not apply: the strategy is pinned to "
                          f"{space.fixed['strategy']} (in {space.source} or by --fix); drop one of them")


#: `tune run` options of the stereo task's pairs and estimator budget (dest -> default)
STEREO_ONLY = {"max_pairs": None, "chunk_pairs": 12, "budget": 0.5, "test_budget": 1.0, "calibration_pairs": 8,
               "recalibrate": False, "covisibility": 0.1}


def _stereo_only_given(args) -> tuple:
    """The stereo options given to a multiview run (it reconstructs whole bags with COLMAP's own, untimed RANSAC:
    --max-pairs, --budget, ... were ignored, unsaid): the run says so with a --fix the task does not use."""
    from pipeline.tasks import TASKS, is_timed
    if is_timed(args.task) or args.task not in TASKS:  # a stereo-derived plug-in task uses them all; an unknown
        return ()  # task's own error comes next
    return tuple("--" + d.replace("_", "-") for d, v in STEREO_ONLY.items() if getattr(args, d, v) != v)


def resolve_reference(value: str | None, sdir):
    """``--reference``: the task's default (None), "paper", "colmap", "imc2025-baseline", "none", or a config file /
    study resolved to its Source."""
    from tuner.select import NAMED_REFERENCES, reference_spec
    kind = reference_spec(value)
    if kind in ("default", "paper", "none", *NAMED_REFERENCES):
        return None if kind == "default" else kind
    from pipeline.errors import ImtuneError
    from tuner.sources import resolve_source
    try:
        return resolve_source(kind, sdir)
    except ImtuneError as e:  # a misspelt name reads as a missing study: say what the named references are
        raise ImtuneError(f"--reference {e} (or give paper, {', '.join(NAMED_REFERENCES)} or none)") from None


def _select_opts(g) -> None:
    """``--select`` (which trial is frozen: tuner.select) and ``--reference`` (what test runs are compared with)."""
    from tuner.select import ALL_RULES, DEFAULT_RULE
    g.add_argument("--select", default=None, choices=list(ALL_RULES),
                   help=f"which feasible trial is frozen: best (highest validation mAA), one-se (the centre of the "
                        f"trials within one standard error of the best), smooth (best of the surface averaged over "
                        f"neighbouring trials), lower-bound (highest lower end of the validation 95%% interval), "
                        f"confirmed (highest mean over more seeds, after --confirm); "
                        f"see the docs' Tuning page (default: the study's rule, else {DEFAULT_RULE})")
    g.add_argument("--reference", default=None, metavar="FILE|STUDY|paper|colmap|imc2025-baseline|none",
                   help="configuration the test runs are compared with on the same pairs (paired bootstrap): a "
                        "config file or study, paper, colmap (COLMAP out of the box: the reconstruction task's "
                        "default), imc2025-baseline (the IMC 2025 baseline: ALIKED + LightGlue, COLMAP's "
                        "verification and mapper; reconstruction), none to skip (default: the paper defaults r 0.85 both, eta 0.5 px, "
                        "Gamma 50k with the study's feature and estimator)")


#: the options of `tune run` that `tune run -h` only names (`tune run --help-all` and the CLI reference describe
#: them): ablations of the pipeline, the multiview task's, the intervals', and the study's fine controls
RUN_LESS_USED = [
    "--no-low-threshold", "--upright", "--upright-plus", "--clahe", "--mr-size", "--max-side", "--feature-option",
    "--matcher", "--matcher-option", "--distance-threshold", "--fginn", "--prefilter", "--matches", "--confidence",
    "--covisibility", "--cache", "--warm-start", "--startup-trials", "--test-budget", "--chunk-pairs", "--heartbeat",
    "--test-wait",
    "--calibration-pairs", "--recalibrate", "--retest", "--verbose", "--reference", "--pareto-span", "--terminate",
    "--trial-timeout",
    "--bags", "--bag-min-points", "--bag-seed", "--mv-intrinsics", "--workers", "--keep-models", "--gt-dir", "--ci",
    "--ci-resamples",
]


def register(sub) -> None:
    from tuner.options import add_jobs_option, add_multiview_options, task_choices
    from tuner.samplers import DEFAULT_PRUNER, PRUNERS, SAMPLERS
    ap = sub.add_parser("run", help="tune on the validation scenes, freeze the optimum, run the test scenes "
                                    "(the default command)")
    from pipeline.data import STRECHA_MAX_PAIRS
    from tuner.argtypes import SEED_MAX
    add_pipeline_options(ap, tuning=True, seed_help=f"seed of the sampler (each worker derives its own from it and its "
                                                    f"first trial) and of the seeded estimators, 0 to {SEED_MAX} "
                                                    f"(default: none: an unseeded sampler, estimator seed 0)")
    ap.set_defaults(seed=None)
    _storage_opts(ap)
    t = ap.add_argument_group("study")
    t.add_argument("--study", default=None, help="study name (default <feature>-<num_features>-<ransac>-<task>)")
    t.add_argument("--task", default="stereo", choices=[t for t in task_choices() if t != "both"],
                   help="the task tuned (see `tune list`)")
    t.add_argument("--space", default=None, help="search-space YAML replacing the default of the estimator family "
                                                 "(default: search_spaces/<family>.yaml, with its per-feature overrides)")
    t.add_argument("--fix", action="append", default=[], metavar="NAME=VALUE",
                   help="pin a parameter (ratio, threshold, max_iters, strategy); repeatable")
    t.add_argument("--n-trials", type=positive_int, default=None,
                   help="finished trials (complete + pruned) the study should hold; a rerun runs the missing ones "
                        "(default 50; the whole grid with --sampler grid)")
    t.add_argument("--timeout", type=nonnegative_float, default=None,
                   help="stop this worker's search after this many seconds of trials, then freeze and test as usual "
                        "(default: 300 for a stereo study, the main job's bound; none for multiview and "
                        "reconstruction; 0 = no limit)")
    t.add_argument("--trial-timeout", type=_trial_timeout_arg, default=None, metavar="SECONDS|auto",
                   help="reconstruction: a trial whose mapping (all its validation datasets) runs longer than this "
                        "is stopped and recorded as pruned, with the reason; auto: 10 x the defaults trial's "
                        "mapping seconds, at least 60 (default: no bound; test runs and the reference are never "
                        "bounded)")
    t.add_argument("--terminate", default="off", choices=["off", "auto"],
                   help="auto: stop the study early when more trials cannot beat the incumbent by more than its "
                        "validation interval (Optuna's terminator: a GP regret bound, after min(20, n_trials / 2) "
                        "trials); off (default): run every trial")
    t.add_argument("--confirm", type=int, default=None, metavar="N",
                   help="before freezing, evaluate the N best trials (and the task's defaults, when the study started "
                        "from them) at --confirm-seeds more seeds on the validation data and freeze the highest mean "
                        "(--select confirmed); against the winner's curse where runs are noisy (default: 3 for the "
                        "reconstruction task, else 0: none)")
    t.add_argument("--confirm-seeds", type=int, default=2, metavar="S",
                   help="more seeds per confirmed candidate (default 2)")
    t.add_argument("--replicates", type=positive_int, default=1, metavar="K",
                   help="K independent tunings of this configuration (studies NAME, NAME-r2, ...; each its own sampler "
                        "and estimator seed derived from --seed, all sharing the cache), each frozen and tested on "
                        "the same pairs (reconstruction: datasets); the test figure is their mean with an interval "
                        "holding the tuning variance (default 1: the tuning variance is not measured); a rerun "
                        "resumes them")
    t.add_argument("--sampler", default="tpe", choices=list(SAMPLERS), help=f"{' | '.join(SAMPLERS)} (default tpe)")
    t.add_argument("--pruner", default=DEFAULT_PRUNER, choices=list(PRUNERS),
                   help=f"{' | '.join(PRUNERS)}: Optuna's median, successive-halving or Hyperband pruner over the "
                        f"chunks of pairs, or none (default {DEFAULT_PRUNER}; see Tuning in the docs)")
    t.add_argument("--warm-start", action="append", default=[], metavar="STUDY",
                   help="first trials: the frozen optimum and the 3 best feasible trials of STUDY (same storage), "
                        "projected into this study's space (clipped to its ranges, Gamma to its Gamma_max); "
                        "repeatable; only a study without trials")
    t.add_argument("--startup-trials", type=positive_int, default=None,
                   help="random trials before TPE models (default: n_trials / 5, between 3 and 10)")
    t.add_argument("--budget", type=positive_float, default=0.5,
                   help="B: median estimator CPU seconds per pair allowed on validation (default 0.5)")
    t.add_argument("--test-budget", type=positive_float, default=1.0,
                   help="estimator seconds per pair allowed on test (default 1.0)")
    t.add_argument("--test-scenes", type=scene_list, default=None, help="comma-separated test scenes (default: the data set's test split)")
    t.add_argument("--max-pairs", type=positive_int, default=None,
                   help=f"use at most N pairs per scene (evenly spread; quick runs) (default: every pair; "
                        f"{STRECHA_MAX_PAIRS} on the built-in Strecha split)")
    t.add_argument("--chunk-pairs", type=positive_int, default=12,
                   help="pairs per pruning step (an intermediate value after each chunk)")
    t.add_argument("--heartbeat", type=nonnegative_int, default=10,
                   help="seconds between heartbeats of a running trial (RDB storages; 0 = off); a trial silent "
                        "for 3 heartbeats is failed and retried once")
    t.add_argument("--test-wait", type=nonnegative_float, default=3600.0, metavar="SECONDS",
                   help="many workers: how long a worker waits for the test phase another worker runs, then prints "
                        "its result (0: print where it runs and exit at once) (default 3600)")
    t.add_argument("--calibration-pairs", type=positive_int, default=8, help="pairs timed by the automatic calibration")
    t.add_argument("--recalibrate", action="store_true", help="measure Gamma_max again even if stored")
    t.add_argument("--no-test", action="store_true", help="do not run the test scenes at the end")
    t.add_argument("--test-runs", type=positive_int, default=3,
                   help="test runs of the frozen settings, each with its own estimator seed, averaged (default 3)")
    t.add_argument("--retest", action="store_true", help="rerun the test even if test.json matches the frozen settings")
    t.add_argument("--verbose", action="store_true", help="Optuna's per-trial log lines")
    _select_opts(t)
    t.add_argument("--objective", default="mAA10", choices=["mAA10", "auc10", "auc20", "pareto"],
                   help="mAA10 (default, the paper's protocol): maximize mAA(10°) within the budget B; auc10 / auc20: "
                        "maximize the pose AUC@10° / @20° (SuperGlue/LightGlue's) instead, study named "
                        "<default>-auc10 / -auc20; pareto: a two-objective study (maximize "
                        "mAA(10°), minimize median estimator seconds per pair; no pruning), named <default>-pareto; "
                        "`tune plot` draws its front, freeze takes its best trial within B")
    t.add_argument("--pareto-span", type=positive_float, default=None,
                   help="pareto: search Gamma up to Gamma_max(span x B), so that the front reaches past B (default 4)")
    add_multiview_options(ap)
    add_ci_options(ap)
    add_jobs_option(t)
    from tuner.cli import RESUME_NOTE
    ap.set_defaults(func=run, on_interrupt=RESUME_NOTE)
    from tuner.options import track_explicit
    track_explicit(ap)  # which pipeline options were typed: the others take the task's defaults (apply_task_defaults)
    if hasattr(ap, "set_less_used"):  # `tune run -h`: what most people set; `tune run --help-all`: everything
        ap.set_less_used(RUN_LESS_USED)

    c = sub.add_parser("calibrate", help="measure estimator CPU seconds per pair vs max-iters; store Gamma_max(B)")
    add_pipeline_options(c, tuning=True)
    _storage_opts(c, storage=False)  # a calibration lives in <studies dir>/budgets.json, never in the storage
    c.add_argument("--storage", dest="refused_storage", type=_no_storage_for_calibrate, help=argparse.SUPPRESS)
    c.add_argument("--budget", type=positive_float, action="append", default=None,
                   help="B: median estimator CPU seconds per pair (repeatable) (default: 0.5 and 1.0)")
    c.add_argument("--pairs", type=positive_int, default=16, help="validation pairs timed per cap (default 16)")
    c.add_argument("--max-pairs", type=positive_int, default=None,
                   help="pairs per scene considered (default: every pair)")
    c.add_argument("--space", default=None, help="search space whose 'calibration' section gives r and eta (default: "
                                                 "the estimator family's in search_spaces/)")
    c.add_argument("--calibration-ratio", type=ratio_float, default=None,
                   help="ratio test r of the timed matches (default: the search space's 'calibration' section)")
    c.add_argument("--calibration-threshold", type=positive_float, default=None,
                   help="eta (px) used while timing (default: the search space's 'calibration' section)")
    c.add_argument("--force", action="store_true", help="measure again even if stored")
    c.add_argument("--task", default="stereo", choices=[t for t in task_choices() if t != "both"],
                   help="the task whose pairs are timed")
    add_jobs_option(c)
    c.set_defaults(func=run_calibrate, on_interrupt="a calibration is stored only when it finishes; rerun the command")

    te = sub.add_parser("test", help="run a study's frozen settings on the test scenes (3 runs, averaged)")
    te.add_argument("--study", required=True, help="the study whose frozen settings are tested")
    _storage_opts(te)
    te.add_argument("--data", default=None, help="data folder (default: the study's, else the usual precedence)")
    te.add_argument("--scenes", type=scene_list, default=None, help="comma-separated test scenes (default: the study's test split)")
    te.add_argument("--runs", type=positive_int, default=3,
                    help="test runs, each with its own estimator seed, averaged")
    te.add_argument("--max-pairs", type=positive_int, default=None,
                    help="at most N pairs per scene (evenly spread; default: the study's --max-pairs, else every pair)")
    te.add_argument("--test-budget", type=positive_float, default=None,
                    help="median estimator CPU seconds per pair allowed on test (default: the study's --test-budget, "
                         "1.0 unless set)")
    te.add_argument("--cache", default=None, help="cache folder (else $IMTUNE_CACHE or ~/.cache/imtune)")
    te.add_argument("--reuse", action="store_true", help="return test.json as is when it matches the frozen settings")
    te.add_argument("--workers", type=positive_int, default=None,
                    help="multiview studies: bags in parallel (default: available CPUs)")
    te.add_argument("--json", action="store_true", help="print the test result (test.json's object)")
    te.add_argument("--quiet", action="store_true", help="no progress bars")
    _select_opts(te)
    add_ci_options(te)
    add_jobs_option(te)
    # a test run has no trials and does not resume: test.json is written (atomically) when all its runs are done
    te.set_defaults(func=run_test_cmd, on_interrupt="a test run is written only when it finishes (test.json keeps the "
                                                    "last finished one); rerun the command")

    for name, helptext, fn in (("table", "optimal-settings table over all studies in the storage", run_table),
                               ("results", "test-results table (NF, NI and mAA(10) per estimator, rank)", run_results)):
        p = sub.add_parser(name, help=helptext)
        _storage_opts(p)
        p.add_argument("--format", default="markdown", help="markdown | csv | latex | json")
        p.add_argument("--task", default="all" if name == "table" else "stereo",
                       help="a task (see `tune list`), or all" if name == "table" else "a task (see `tune list`)")
        p.add_argument("--objective", default=None, choices=["mAA10", "auc10", "auc20"],
                       help="only the studies that maximised this (needed when the storage holds studies of several "
                            "objectives: they are never ranked as one)")
        p.set_defaults(func=fn)

    pl = sub.add_parser("plot", help="one HTML report of a study, or the Pareto fronts of several (plotly)")
    pl.add_argument("--study", default=None, help="the study whose report is drawn")
    pl.add_argument("--pareto", nargs="+", default=None, metavar="STUDY",
                    help="overlay the accuracy-cost Pareto fronts of these studies (one per estimator) on one "
                         "figure, with the budget B")
    _storage_opts(pl)
    pl.add_argument("--out", default=None, help="HTML file (default <studies dir>/<study>/report.html; with "
                                                "--pareto <studies dir>/pareto.html)")
    pl.set_defaults(func=run_plot)

    d = sub.add_parser("dashboard", help="serve optuna-dashboard on the storage (127.0.0.1)")
    _storage_opts(d)
    d.add_argument("--port", type=int, default=8080, help="port of the dashboard's web server (default 8080)")
    d.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    d.set_defaults(func=run_dashboard)

    ex = sub.add_parser("export", help="print a study's frozen settings for COLMAP, pycolmap, OpenCV, PoseLib, hloc or "
                                       "as JSON")
    ex.add_argument("--study", required=True, help="the study (its frozen.yaml in the studies dir)")
    ex.add_argument("--format", default="json", help="colmap | pycolmap | opencv | poselib | hloc | json")
    _storage_opts(ex, storage=False)
    ex.set_defaults(func=run_export)
    ls = sub.add_parser("studies", help="list the studies in a storage")
    _storage_opts(ls)
    ls.add_argument("--json", action="store_true", help="print a JSON list, one object per study, with the whole "
                                                        "ground-truth phrases")
    ls.set_defaults(func=run_studies)


def _studies_dir(args) -> Path:
    from tuner.storage import default_studies_dir
    return Path(args.studies_dir).expanduser().resolve() if args.studies_dir else default_studies_dir()


def _scenes(value):
    if not value:
        return None
    return [n.strip() for n in value.split(",") if n.strip()]


def _jsonable(o):
    from tuner.freeze import _plain
    return _plain(o)


# -- tune run ---------------------------------------------------------------------------------------

def _max_pairs(args, data_root):
    """``--max-pairs``, else on the built-in Strecha split (no --scenes / --test-scenes, no splits.yaml) its
    pairs-per-scene cap :data:`pipeline.data.STRECHA_MAX_PAIRS` (six scenes, 1,034 pairs: every pair would make the
    main job several times longer), else None (every pair). A multiview run takes no pairs cap."""
    if args.max_pairs is not None or args.scenes or args.test_scenes:
        return args.max_pairs
    from pipeline.tasks import is_timed
    if not is_timed(args.task):
        return None
    from pipeline.data import default_max_pairs
    return default_max_pairs(data_root)


def _trial_timeout_arg(s: str) -> float | str:
    """``--trial-timeout``: seconds > 0 or ``auto``."""
    return "auto" if s == "auto" else positive_float(s)


def _trial_timeout(args) -> float | str | None:
    """``--trial-timeout``: a task that takes it (reconstruction), else a one-line error naming the option."""
    v = getattr(args, "trial_timeout", None)
    if v is None:
        return None
    from pipeline.errors import ImtuneError
    from pipeline.tasks import TASKS, task_class
    if args.task in TASKS and not task_class(args.task).takes("trial_timeout"):
        raise ImtuneError(f"--trial-timeout bounds a reconstruction trial's mapping; the {args.task} task has none "
                          "(add --task reconstruction, or drop --trial-timeout)")
    return v


def _timeout(args) -> float | None:
    """``--timeout`` (0 = no limit), else the task's ``search_seconds`` (stereo: a bound that keeps the main job's
    wall time stable whatever trials the sampler draws; None for tasks whose one evaluation takes minutes)."""
    if args.timeout is not None:
        return args.timeout or None
    from pipeline.tasks import TASKS
    return TASKS.get(args.task).search_seconds if args.task in TASKS else None


def settings_from_args(args):
    """TuneSettings from the `tune run` options."""
    from tuner.study import TuneSettings
    from tuner.study_identity import PARETO_SPAN
    select = _select(args)  # before the data: a contradiction in the options is said first
    if args.startup_trials is not None and args.sampler in ("random", "grid"):  # it was ignored, unsaid
        raise ImtuneError(f"--startup-trials {args.startup_trials} applies to the tpe and cmaes samplers (random trials "
                          f"before they model): --sampler {args.sampler} has none; drop --startup-trials")
    if args.pareto_span is not None and args.objective != "pareto":  # it was ignored, unsaid
        raise ImtuneError(f"--pareto-span {args.pareto_span:g} applies to a pareto study only: add --objective pareto, "
                          "or drop --pareto-span")
    if getattr(args, "terminate", "off") == "auto":
        from tuner.terminate import make_terminator
        make_terminator("auto", 50, args.objective)  # a pareto study: one line now, before any calibration
    pinned = [f for f in args.fix if f.partition("=")[0].strip() in ("ratio", "strategy")]
    if getattr(args, "matches", None) and pinned:  # was "--fix ratio is given twice (ratio=0.7 and ratio=1.0)"
        raise ImtuneError(f"--fix {pinned[0].strip()} does not apply with --matches custom:DIR: imported matches skip the "
                          "matcher (ratio and strategy are fixed at r=1 both); drop it")
    from tuner.options import apply_task_defaults
    apply_task_defaults(args, [args.task])  # the reconstruction task's own defaults (COLMAP's SIFT)
    base = build_config(args, ratio=1.0, threshold=0.5, max_iters=1000,
                        seed=args.seed if args.seed is not None else 0)
    from tuner.options import untuned_values
    untuned = build_config(args, **untuned_values(args.task), seed=args.seed if args.seed is not None else 0)
    _check_strategy(args, base)
    from tuner.options import check_multiview_only, multiview_config
    check_multiview_only(args, [args.task])
    quiet = bool(args.quiet or args.json)
    mv = multiview_config(args, seed=args.seed if args.seed is not None else 0)
    data_root = resolve_data(args.data, download=True, quiet=quiet)
    return TuneSettings(
        base=base, untuned=untuned, data_root=data_root, task=args.task, study_name=args.study,
        storage=args.storage, studies_dir=_studies_dir(args), space_path=args.space,
        # imported (custom) matches skip the matcher: the ratio test and strategy are then not searched
        fixes=list(args.fix) + (["ratio=1.0", "strategy=both"] if getattr(args, "matches", None) else []),
        n_trials=args.n_trials, timeout=_timeout(args), seed=args.seed, sampler=args.sampler, pruner=args.pruner,
        startup_trials=args.startup_trials, budget=args.budget, test_budget=args.test_budget,
        val_scenes=_scenes(args.scenes), test_scenes=_scenes(args.test_scenes), min_covisibility=args.covisibility,
        max_pairs=_max_pairs(args, data_root), chunk_pairs=args.chunk_pairs, cache_dir=args.cache,
        heartbeat=args.heartbeat if args.heartbeat and args.heartbeat > 0 else None,
        test_wait=args.test_wait,
        calibration_pairs=args.calibration_pairs, recalibrate=args.recalibrate, progress=not quiet,
        test=not args.no_test, test_runs=args.test_runs, retest=args.retest, multiview=mv, workers=args.workers,
        mapper=getattr(args, "mapper", None), trial_timeout=_trial_timeout(args), jobs=args.jobs,
        warm_start=list(args.warm_start),
        gt_dir=args.gt_dir, objective=args.objective,
        pareto_span=PARETO_SPAN if args.pareto_span is None else args.pareto_span, select=select,
        confirm=args.confirm, confirm_seeds=args.confirm_seeds,
        reference=resolve_reference(args.reference, _studies_dir(args)), ci_resamples=ci_resamples(args),
        unused_options=_stereo_only_given(args), terminate=getattr(args, "terminate", "off"))


def _select(args) -> str | None:
    """--select, made "confirmed" by --confirm N (N > 0); one-line exit 2 for a contradiction or a bad count."""
    from pipeline.tasks import task_class
    from tuner.confirm import check
    from tuner.select import CONFIRMED
    if args.confirm is None:  # the task's default (tuner.confirm), unless another rule was asked for
        given = args.select not in (None, CONFIRMED)
        args.confirm = 0 if given else task_class(args.task).confirm_default
    check(args.confirm, args.confirm_seeds)
    if args.confirm and args.select not in (None, CONFIRMED):
        raise ImtuneError(f"--confirm {args.confirm} with --select {args.select}: confirmation freezes by the "
                          "confirmed mean; drop one of them")
    if args.select == CONFIRMED and not args.confirm:
        raise ImtuneError("--select confirmed needs --confirm N (how many of the best trials to confirm)")
    return CONFIRMED if args.confirm else args.select


def run(args) -> int:
    from tuner.study import tune
    s = settings_from_args(args)
    s.verbose = bool(args.verbose)
    k = int(getattr(args, "replicates", 1) or 1)
    if k > 1:  # tuner.replicates: K studies, each tuned, frozen and tested; their figure with the tuning variance
        from tuner.replicates import tune_replicates
        out = tune_replicates(s, k)
        if args.json:
            print(json.dumps(_jsonable(out), indent=2))
        else:
            print_replicated(out)
        return 0
    out = tune(s)
    if args.json:
        print(json.dumps(_jsonable(out), indent=2))
    else:
        print_outcome(out)
        if out.get("test"):
            from pipeline.metrics.replicates import NOT_MEASURED
            from pipeline.tasks import task_class
            from tuner.formatting import fit_text
            unit = task_class(out["test"].get("task") or "stereo").unit
            what = NOT_MEASURED if unit == "pairs" else (
                f"the tuning variance was not measured (1 replicate): the interval covers the test {unit}' runs only")
            print(fit_text(f"tuning: 1 replicate: {what}; the verdict against the reference is about this "
                           "frozen setting, not about tuning at another seed (--replicates 3 measures it)"))
    return 0


def print_replicated(out: dict) -> None:
    """Each replicate's outcome, then the replicated figure (tuner.replicates.replicated_text)."""
    from tuner.replicates import replicated_text
    for i, o in enumerate(out["replicates"], 1):
        print(f"== replicate {i}/{len(out['replicates'])}")
        print_outcome(o)
        print()
    if out.get("replicated"):
        print(replicated_text(out["replicated"]))
    else:
        print("replicated figure: not computed (a replicate was not tested: --no-test, or trials still running in "
              "other workers); rerun the command to finish and test them")


def print_outcome(out: dict) -> None:
    c = out["counts"]
    print(f"study {out['study']}  ({out['storage']})")
    over = f" ({c['infeasible']} over budget)" if out.get("timed", True) else ""  # a multiview study has no budget
    print(f"trials: {c['complete']} complete{over}, {c['pruned']} pruned, "
          f"{c['fail']} failed; this worker ran {len(out['worker']['trials_run'])}")
    if out["worker"].get("time_limit"):
        w = out["worker"]
        print(f"search: stopped at its time limit of {w['time_limit']:g} s (--timeout; 0 = none) before the target "
              f"of {w['target']} trials; rerun the command to run the rest")
    f = out.get("frozen")
    if f:
        print(f"frozen: {out['frozen_path']}  (trial #{f['trial']})")
        print(frozen_table(f))
    ph = out.get("test_phase") or {}
    if ph and not ph.get("this_worker"):  # many workers: the one test phase ran (or runs) in another worker
        from tuner.formatting import fit_text
        where = f"worker {ph.get('host')} pid {ph.get('pid')}"
        print(fit_text(f"test phase: run by {where} (its test.json: {ph.get('test_json')})" if ph.get("state") == "done"
                       else f"test phase: still running in {where}; its result goes to the study (`tune results`) "
                            "and to test.json on that machine"))
    t = out.get("test")
    if t:
        print()
        print(test_table(t))


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def frozen_table(f: dict) -> str:
    """The frozen settings: tuned and fixed parameters, the budget, the validation figures."""
    from tuner.freeze import task_of
    task = task_of(f)
    rows = []
    for k, v in f["params"].items():
        rows.append({"parameter": k, "value": _fmt(v), "": "tuned"})
    for k, v in f.get("fixed", {}).items():
        rows.append({"parameter": k, "value": _fmt(v), "": "fixed"})
    v = f.get("validation", {})
    b = f.get("budget", {})
    if "max_iters" in f["params"] or task.budget_seconds(v) is not None:
        from tuner.formatting import gamma_max_text
        gmax = b.get("gamma_max")
        used = ""  # the frozen trial's budget statistic: the mean beside a budget read as over it when it is not
        if v.get("ransac_seconds_median") is not None:
            used = f"; frozen trial: median {v['ransac_seconds_median']:.3g} s/pair (the budget statistic)"
            if v.get("ransac_seconds") is not None:
                used += f", mean {v['ransac_seconds']:.3g}"
        rows.append({"parameter": "budget", "value": f"{b.get('seconds_per_pair')} s/pair",
                     "": gamma_max_text(gmax, f.get("fixed")) + used})
    from tuner.formatting import format_value  # each figure at its column's precision, as every table shows it
    others = ", ".join(f"{k} {format_value(k, v.get(k))}" for k in task.columns
                       if k not in ("mAA10",) and v.get(k) is not None)
    obj = v.get(task.objective)
    rows.append({"parameter": f"validation {task.objective}",
                 "value": with_ci(obj, v.get(f"{task.objective}_ci")) if obj is not None else _fmt(obj),
                 "": f"{task.name}: {others}"})
    from tuner.formatting import TERMINAL_WIDTH, wrapped_cell_rows
    room = TERMINAL_WIDTH - 10 - sum(max(len(str(r[c])) for r in rows + [{c: c}]) for c in ("parameter", "value"))
    rows = wrapped_cell_rows(rows, "", max(30, room))  # the notes continue on rows of their own: 100 columns
    return render(rows, "markdown", ["parameter", "value", ""]) + _frozen_notes(f)


def _frozen_notes(f: dict) -> str:
    """The selection rule and how flat the optimum is, one line each (the frozen file's warnings were already
    printed once on stderr by `tune` and are kept in frozen.yaml under ``warnings``)."""
    from tuner.select import flat_text
    lines = []
    from tuner.formatting import ground_truth_text
    origin = ground_truth_text((f.get("data") or {}).get("ground_truth"))
    if origin:  # where the validation figures' poses come from (a study created before this was recorded: none)
        lines.append(f"validation ground truth: {origin}")
    sel = f.get("selection") or {}
    if sel:
        lines.append(f"selection: {sel.get('rule')} (best trial #{sel.get('best_trial')}"
                     + (f", value {sel['best_value']:.3f}" if sel.get("best_value") is not None else "")
                     + f"): {sel.get('note', '')}")
    if "robustness" in f:
        lines.append(flat_text(f.get("robustness")))
        flat = f.get("robustness") or {}
        if sel.get("rule") == "best" and flat.get("of") and flat.get("trials", 0) > flat["of"] / 2:
            # most trials tie with the best: which one wins is noise, and a noise pick can fail on the test scenes
            lines.append(f"the optimum is flat ({flat['trials']} of {flat['of']} trials tie with the best within its "
                         f"interval): `tune test --study {f.get('study')} --select one-se` freezes the trial at the "
                         "centre of the tied ones instead (the selection rules: How sure a number is, in the docs)")
    from tuner.formatting import fit_text
    return ("\n" + "\n".join(fit_text(x) for x in lines)) if lines else ""


def test_table(t: dict) -> str:
    """The test runs: per scene and the mean over scenes of the task's columns."""
    from tuner.freeze import task_of
    task = task_of(t)
    m = t["mean"]
    parts = [m, *(m.get("scenes") or {}).values()]  # a column no run recorded (multiview's seconds) is left out
    cols = ["scene"] + [c for c in task.columns if any(p.get(c) is not None for p in parts)]
    def row(scene, s):  # mAA with its 95% interval: "value [lo, hi]"
        return dict(scene=scene, **{k: with_ci(s.get(k), s[f"{k}_ci"]) if s.get(f"{k}_ci") and s.get(k) is not None
                                    else s.get(k) for k in cols[1:]})
    rows = [row(name, s) for name, s in m.get("scenes", {}).items()]
    if len(rows) > 1:
        rows.append(row(f"mean of {len(rows)} scenes", m))
    b = t.get("budget", {})
    std = t.get("std", {}).get(task.objective, 0.0)
    n_runs = len(t.get("runs", []))
    # one run has no spread over runs: "std 0" read as a perfectly stable result
    spread = (f"{task.objective} sample std over the runs {_fmt(std)}" if n_runs > 1 else
              "one run: no spread over runs")
    head = f"{task.name} test ({n_runs} run{'s' if n_runs != 1 else ''}, mean; {spread}"
    if task.budget_seconds(m) is not None:
        head += (f"; within the {b.get('test_seconds_per_pair')} s/pair test budget: "
                 f"{'yes' if b.get('within_budget') else 'no'}")
    tail = []
    if "ransac_seconds" in cols or "match_seconds" in cols:  # the unit, and which statistic the budget reads
        med = m.get("ransac_seconds_median")
        tail.append("match_seconds, ransac_seconds: seconds per pair, mean over the pairs"
                    + (f" (the budget is on the median estimator CPU time: {med:.3g} s/pair)"
                       if isinstance(med, (int, float)) else ""))
    if t.get("interval"):
        from tuner.select import interval_units
        units = interval_units(t)
        tail.append(f"intervals: 95%, over {units} and runs ({t['interval'].get('resamples')} resamples; how: "
                    "test.json 'interval')")
    if "reference" in t:
        from tuner.select import comparison_text
        tail.append(comparison_text(t.get("reference")))
    if t.get("submission"):  # reconstruction: the frozen settings' first run, every test dataset
        tail.append(f"submission.csv (run 1 of the frozen settings): {t['submission']}")
    from tuner.formatting import ground_truth_text
    origin = ground_truth_text((t.get("data") or {}).get("ground_truth"))
    tail.append(f"ground truth: {origin}" if origin else "ground truth: not recorded (a test.json written before imtune "
                "recorded it: rerun `tune test` to record it)")
    from tuner.formatting import fit_text, render_fitted
    # split by columns where the table would be wider than a terminal (each part keeps the scene column)
    return (fit_text(head + ")") + "\n" + render_fitted(rows, cols)
            + "".join("\n" + fit_text(x) for x in tail))


# -- tune calibrate ---------------------------------------------------------------------------------

def run_calibrate(args) -> int:
    from pipeline.cache import H5Cache
    from pipeline.tasks import make_task
    from tuner.budget import calibrate
    from tuner.evaluate import load_scenes
    from tuner.objective import ValidationSet
    from tuner.samplers import quiet_optuna
    from tuner.space import load_space
    quiet_optuna()
    from tuner.storage import check_studies_dir
    check_studies_dir(_studies_dir(args))  # budgets.json goes there: read-only or a file in the way -> now
    conf = build_config(args, ratio=1.0, threshold=0.5, max_iters=1000)
    from pipeline.geometry import get_estimator
    est = get_estimator(conf.geometry.ransac)
    space = load_space(args.space, feature=conf.feature.name, estimator=conf.geometry.ransac)
    ratio = args.calibration_ratio if args.calibration_ratio is not None else space.calibration["ratio"]
    threshold = args.calibration_threshold if args.calibration_threshold is not None else space.calibration["threshold"]
    from tuner.space import _check_value
    ratio = _check_value("ratio", ratio, "--calibration-ratio")
    threshold = _check_value("threshold", threshold, "--calibration-threshold")
    budgets = tuple(args.budget or (0.5, 1.0))
    root = resolve_data(args.data)
    quiet = bool(args.quiet or args.json)
    task = make_task(args.task, min_covisibility=args.covisibility, max_pairs=args.max_pairs)
    from pipeline.tasks.pool import resolve_jobs
    vs = ValidationSet.from_scenes(load_scenes(root, args.scenes, split="val"), task)
    cache = H5Cache(args.cache)
    cal = calibrate(conf.geometry.ransac, conf, vs.scenes, cache, vs.fingerprint, budgets=budgets, ratio=ratio,
                    threshold=threshold, max_pairs=args.pairs, studies_dir=_studies_dir(args), force=args.force,
                    progress=not quiet, seed=int(args.seed or 0),
                    jobs=resolve_jobs(args.jobs))  # as many estimators at once as a study's trial runs
    caps = {f"{b:g}": cal.gamma_max(b) for b in budgets}
    if args.json:
        print(json.dumps(_jsonable({"calibration": cal.to_dict(), "gamma_max": caps,
                                    "uses_iterations": bool(getattr(est, "uses_iterations", True))}), indent=2))
        return 0
    print(f"{cal.estimator} on {cal.pairs} validation pairs of {', '.join(vs.scene_names)} "
          f"({conf.feature.name} {conf.feature.num_features}, r={cal.ratio:g}, eta={cal.threshold:g} px; "
          f"host {cal.host}; measured {cal.created}); estimator CPU time per pair (what the budget bounds), "
          "wall time beside it")
    wall = {int(w[0]): w[1] for w in cal.wall_curve}
    rows = [{"max_iters": g, "median CPU s/pair": m, "p90 CPU s/pair": p, "median wall s/pair": wall.get(int(g))}
            for g, m, p, *_ in cal.curve]
    print(render(rows, "markdown", ["max_iters", "median CPU s/pair", "p90 CPU s/pair", "median wall s/pair"]))
    for b, g in caps.items():
        print(f"Gamma_max({b} s) = {g} (median CPU s per pair)")
    return 0


# -- tune test --------------------------------------------------------------------------------------

def _check_test_workers(args, task) -> None:
    """``tune test --workers N`` (multiview bag processes) of a study of another task, or ``--max-pairs`` /
    ``--test-budget`` of a multiview study: each was ignored, unsaid."""
    from pipeline.tasks import TASKS, task_class
    task = task if isinstance(task, str) else "stereo"
    cls = task_class(task)  # what the study's task takes (a task not loaded here: the defaults)
    if args.workers is not None and not cls.takes("workers"):
        takers = " / ".join(n for n in TASKS.names() if TASKS.get(n).takes("workers"))
        raise ImtuneError(f"--workers is an option of the {takers} task (its parallel processes), and study "
                          f"{args.study} is a {task} study: drop --workers (--jobs sets its pair processes)")
    # as tune run says of an untimed task (TuneSettings.unused_options)
    given = [f for f, v, used in (("--max-pairs", args.max_pairs, cls.takes("max_pairs")),
                                  ("--test-budget", args.test_budget, cls.timed)) if v is not None and not used]
    if given:
        _warn(f"{', '.join(given)}: the {task} task does not use {'it' if len(given) == 1 else 'them'} "
              f"({cls.why_untimed}); ignored")


def run_test_cmd(args) -> int:
    import optuna

    from pipeline.cache import H5Cache
    from tuner.freeze import freeze, load_frozen, run_test, run_test_for_study, study_data_root
    from tuner.samplers import quiet_optuna
    from tuner.storage import open_storage
    quiet_optuna()
    sdir = _studies_dir(args)
    from tuner.freeze import check_study_outputs
    check_study_outputs(sdir, args.study)  # test.json (and frozen.yaml) go there: a file or folder in the way -> now
    study, no_storage = None, None
    try:  # a test never creates a storage: without one, the study's frozen file alone is enough
        storage = open_storage(args.storage, heartbeat=None, studies_dir=sdir, must_exist=True)
        study = optuna.load_study(study_name=args.study, storage=storage)
    except KeyError:
        pass
    except ImtuneError as e:
        no_storage = e
    from tuner.freeze import study_dir
    frozen_file = study_dir(sdir, args.study) / "frozen.yaml"
    if study is None and no_storage is not None and not frozen_file.is_file():
        raise ImtuneError(f"no study {args.study!r}: no frozen settings at {frozen_file}, and {no_storage}")
    from tuner.storage import storage_absent
    if no_storage is not None and not storage_absent(args.storage, sdir):  # there, but unreadable: said, not hidden
        _warn(f"{no_storage} -- testing the frozen settings {frozen_file} alone (the result is not recorded in the "
              "storage)")
    quiet = bool(args.quiet or args.json)
    root = resolve_data(args.data) if args.data else None
    kw = dict(scenes=_scenes(args.scenes), cache=H5Cache(args.cache), runs=args.runs, max_pairs=args.max_pairs,
              test_budget=args.test_budget, progress=not quiet, reuse=args.reuse, workers=args.workers, jobs=args.jobs,
              reference=resolve_reference(args.reference, _studies_dir(args)), ci_resamples=ci_resamples(args))
    if study is not None:
        _check_test_workers(args, study.user_attrs.get("task"))
        frozen, path = freeze(study, sdir, select=args.select,
                              warn=lambda w: print(f"warning: {w}", file=sys.stderr, flush=True))
        result = run_test_for_study(study, frozen, sdir, data_root=root, **kw)
    else:
        frozen = load_frozen(sdir, args.study)  # no such study in this storage: the frozen file alone
        _check_test_workers(args, frozen.get("task"))
        result = run_test(frozen, study_data_root(frozen, root), sdir, **kw)
    for note in result.get("notes") or []:
        print(f"warning: test {note}", file=sys.stderr, flush=True)
    from tuner.select import reference_task_note
    if reference_task_note(kw["reference"], frozen.get("task") or "stereo"):
        _warn(reference_task_note(kw["reference"], frozen.get("task") or "stereo"))
    from tuner.freeze import earlier_test_line
    if earlier_test_line(result):
        _warn(earlier_test_line(result))
    held_in = [n for n in (_scenes(args.scenes) or []) if n in ((frozen.get("data") or {}).get("val_scenes") or [])]
    if held_in:  # as `tune run` warns for --test-scenes
        print(f"warning: test scene {', '.join(held_in)} is also a validation scene of study {args.study}: its test "
              "numbers are not held out (tuned on the scene they measure)", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(_jsonable(result), indent=2))
    else:
        print(f"study {args.study}: frozen trial #{frozen['trial']} -> {study_dir(sdir, args.study) / 'test.json'}")
        print(test_table(result))
    return 0


# -- tables, plot, dashboard, studies ----------------------------------------------------------------

def _warn(line: str) -> None:
    print(f"warning: {line}", file=sys.stderr, flush=True)


def _collect(args):
    from tuner.reports import collect_studies
    from tuner.samplers import quiet_optuna
    from tuner.storage import open_storage
    quiet_optuna()
    if args.format not in FORMATS:
        raise ImtuneError(f"unknown format {args.format!r} (choose {', '.join(FORMATS)})")
    sdir = _studies_dir(args)
    storage = open_storage(args.storage, heartbeat=None, studies_dir=sdir, must_exist=True)
    return collect_studies(storage, task=args.task, studies_dir=sdir, warn=_warn,
                           objective=getattr(args, "objective", None))


def run_table(args) -> int:
    """Stereo studies give eta and r; multiview studies the r_multiview column (`--task multiview`:
    that column alone)."""
    from tuner.reports import render_table, settings_rows
    task = args.task
    if task not in (None, "both", "all"):
        _check_task(task)  # unknown -> one line listing the tasks, before the storage is read
    args.task = None
    studies = _collect(args)
    args.task = task
    from pipeline.tasks import TASKS
    if task not in (None, "both", "all"):
        studies = [s for s in studies if s.task == task]
    # the estimator settings (eta, Gamma, B) come from the studies whose task tunes them; the others (COLMAP's
    # multiview task) contribute their own ratio-test column
    known = [s for s in studies if s.task in TASKS]
    geo = [s for s in known if "threshold" in TASKS.get(s.task).uses]
    other = [s for s in known if s not in geo]
    if not geo and not other:
        raise ImtuneError(f"no imtune {task} studies in the storage")
    # `--task stereo` asks for the stereo settings alone: no empty multiview column
    rows, cols = settings_rows(geo, args.format, multiview=other, multiview_column=task in (None, "both", "all"),
                               warn=_warn)
    print(render_table(rows, cols, args.format))
    return 0


def _check_task(task: str) -> None:
    """``--task`` of table / results names a registered task: one line listing them otherwise (a typo used to read
    as "no tested bogus study in the storage")."""
    from pipeline.tasks import TASKS
    try:
        TASKS.get(task)
    except ImtuneError as e:
        raise ImtuneError(f"--task: {e}") from None


def run_results(args) -> int:
    from tuner.reports import render_table, results_rows
    _check_task(args.task)
    studies = _collect(args)
    rows, cols = results_rows(studies, args.format, studies_dir=_studies_dir(args), warn=_warn)
    if not rows:
        raise ImtuneError(f"no tested {args.task} study in the storage (run `tune test --study NAME`)")
    print(render_table(rows, cols, args.format))
    return 0


def run_plot(args) -> int:
    from tuner.freeze import study_dir
    from tuner.plots import write_report
    from tuner.samplers import quiet_optuna
    from tuner.storage import open_storage
    quiet_optuna()
    sdir = _studies_dir(args)
    if not args.study and not args.pareto:
        raise ImtuneError("tune plot: name a study (--study NAME) or the studies whose fronts to overlay "
                          "(--pareto NAME [NAME ...])")
    if args.study and args.pareto:
        raise ImtuneError("tune plot: --study and --pareto draw different pages; give one of them")
    storage = open_storage(args.storage, heartbeat=None, studies_dir=sdir, must_exist=True)
    out = Path(args.out) if args.out else (sdir / "pareto.html" if args.pareto else
                                           study_dir(sdir, args.study) / "report.html")
    from pipeline.fileio import check_writable_folder
    if out.is_dir():  # before drawing (a folder or a file in the way was an internal error, FileExistsError)
        if args.out:
            raise ImtuneError(f"--out {out} is a folder: give the HTML file to write, e.g. {out / 'report.html'}")
        raise ImtuneError(f"{out} is a folder where tune plot writes its page: move it away, or give --out FILE.html")
    if args.out:
        if out.suffix.lower() not in (".html", ".htm"):  # p.png got an HTML page under a picture's name
            raise ImtuneError(f"--out {out}: tune plot writes an interactive HTML page (plotly); name it .html, "
                              f"e.g. {out.with_suffix('.html')} (a picture: the page's camera button saves a PNG)")
    check_writable_folder(out.parent, "--out folder" if args.out else "studies folder" if args.pareto else
                          "study folder", "give --out a file in a folder you can write" if args.out else
                          "move what is in the way, or give --out FILE.html")
    if args.pareto:
        from tuner.pareto import write_overlay
        print(str(write_overlay(storage, args.pareto, out)))
        return 0
    from tuner.study_identity import load_study
    if not load_study(storage, args.study).user_attrs.get("imtune"):  # its values were drawn and labelled as mAA(10)
        raise ImtuneError(f"study {args.study!r} was not created by imtune: no report of it to draw (optuna-dashboard "
                          "shows any study: tune dashboard)")
    path = write_report(storage, args.study, out, studies_dir=sdir)
    print(str(path))
    return 0


def run_dashboard(args) -> int:
    from tuner.dashboard import serve
    serve(args.storage, host=args.host, port=args.port, studies_dir=_studies_dir(args))
    return 0


def run_export(args) -> int:
    from tuner.export import export_study
    print(export_study(_studies_dir(args), args.study, args.format), end="")
    return 0


def run_studies(args) -> int:
    import optuna

    from tuner.formatting import ground_truth_short
    from tuner.protocol import best_feasible, trial_value
    from tuner.reports import study_test
    from tuner.samplers import quiet_optuna
    from tuner.storage import open_storage
    from tuner.study import trial_counts
    quiet_optuna()
    storage = open_storage(args.storage, heartbeat=None, studies_dir=_studies_dir(args), must_exist=True)
    rows, foreign = [], []
    for summ in optuna.get_all_study_summaries(storage, include_best_trial=False):
        st = optuna.load_study(study_name=summ.study_name, storage=storage)
        c = trial_counts(st)
        b = best_feasible(st) if st.user_attrs.get("imtune") else None
        if not st.user_attrs.get("imtune"):  # another program's study (a shared PostgreSQL): its value is no mAA10
            foreign.append(summ.study_name)
        from tuner.plots import frozen_trial
        rule = st.user_attrs.get("select") or "best"
        fz = frozen_trial(st) if st.user_attrs.get("imtune") else None  # --select one-se / smooth freeze another
        from pipeline.tasks import is_timed
        timed = is_timed(st.user_attrs.get("task", "stereo"))  # a multiview study has no budget to be over
        from tuner.study_identity import study_objective
        row = {"study": summ.study_name,
               "objective": study_objective(st.user_attrs) if st.user_attrs.get("imtune") else None,
               "complete": c["complete"], "pruned": c["pruned"],
               "infeasible": c["infeasible"] if timed else None, "running": c["running"], "failed": c["fail"],
               # the best trial by the study's objective; its mAA10 (an auc10/auc20 study's value is in "best value")
               "best mAA10": (trial_value(b) if study_objective(st.user_attrs) in ("mAA10", "pareto")
                              else b.user_attrs.get("mAA10")) if b else None,
               "best value": trial_value(b) if b else None, "best trial": b.number if b else None,
               "frozen trial": fz.number if fz else None, "frozen by": rule if fz else None}
        if st.user_attrs.get("imtune"):  # where the poses its numbers are measured against come from
            test = study_test(summ.study_name, st.user_attrs, _studies_dir(args), warn=_warn)
            row["ground_truth"] = {"validation": (st.user_attrs.get("data") or {}).get("ground_truth"),
                                   "test": test.get("ground_truth") if test else None}
            # the table's short cell; "test" only for a tested study
            row["_cell"] = f"val {ground_truth_short(row['ground_truth']['validation'])}" + (
                f"; test {ground_truth_short(row['ground_truth']['test'])}" if test else "")
        rows.append(row)
    if args.json:
        print(json.dumps(_jsonable([{k: v for k, v in r.items() if k != "_cell"} for r in rows]), indent=2))
    elif rows:
        cols = [k for k in rows[0] if k not in ("ground_truth", "_cell")
                and (k != "infeasible" or any(r["infeasible"] is not None for r in rows))]
        if any("_cell" in r for r in rows):
            cols.append("ground truth")
        from tuner.formatting import render_fitted  # split by columns to fit a terminal, the study in each part
        print(render_fitted([{**r, "ground truth": r.get("_cell")} for r in rows], cols))
    else:
        print("no studies", file=sys.stderr)
    if foreign and not args.json:
        _warn(f"{', '.join(foreign)}: not created by imtune (no mAA10 to show)")
    return 0
