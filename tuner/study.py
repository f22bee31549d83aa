"""Studies: create or resume, calibrate the budget, optimise, then freeze and test — the `tune` command.

    from tuner.study import TuneSettings, tune
    out = tune(TuneSettings(base=build_config(args, ratio=1, threshold=1, max_iters=1), data_root=...))

Tasks: any registered ``pipeline.tasks`` task (``stereo``: eta, r, Gamma against a budget; ``multiview``: r,
and the strategy if the space lists it). A study searches only what its task uses (``Task.uses``; the rest of
the space is dropped), starts from the task's own search-space file when it names one (``Task.space_file``),
and is calibrated against the budget only when it searches Gamma up to ``calibrated``.

Study names default to ``<feature>-<num_features>-<ransac>-<task>`` (feature variants such as
upright or CLAHE are part of ``<feature>``). A study's user attributes record what it was created
with — search space, fixed pipeline settings, budget (B, Gamma_max and the calibration curve), data
fingerprint, code version — and rerunning the same command resumes it; rerunning with a different
search space, pipeline, budget or data is a one-line error (name a new study with ``--study``).

``n_trials`` is the study's target: a worker stops once the study holds that many finished (COMPLETE
or PRUNED) trials, so rerunning an interrupted study runs exactly the missing trials, and N workers on
one storage share the work and end with exactly the target (``tuner.workers``: each trial's place is
claimed before it runs; a dead worker's trial is failed and retried once by a live one). The first worker
to see the study complete freezes and tests; the others wait for its result and print it.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError

# re-exported: `tuner.study` is where scripts and tests have always found the study's parts
from tuner.preflight import (  # noqa: F401
    check_task_scene,
    load_study_space,
    open_validation,
    pinned_gamma_warning,
    preflight,
    test_scene_names,
)
from tuner.protocol import best_feasible  # noqa: F401  (re-exported: the study's pick)
from tuner.samplers import DEFAULT_PRUNER, PRUNERS, SAMPLERS, make_pruner, make_sampler, quiet_optuna  # noqa: F401
from tuner.study_identity import (  # noqa: F401
    AUC_OBJECTIVES,
    OBJECTIVES,
    PARETO_SPAN,
    PARETO_SUFFIX,
    SCHEMA,
    IncompatibleStudy,
    check_compatible,
    default_study_name,
    feature_label,
    load_study,
    study_identity,
    study_objective,
)
from tuner.version import code_version  # noqa: F401  (re-exported)
from tuner.warm_start import (  # noqa: F401
    WARM_START_BEST,
    check_warm_start_sources,
    project_params,
    start_at_defaults,
    warm_start,
)

DEFAULT_TRIALS = 50


@dataclass
class TuneSettings:
    """Everything one `tune` run needs. ``base`` is the fixed pipeline configuration (the searched
    fields are placeholders). Times in seconds; budgets are median estimator seconds per pair."""
    base: PipelineConfig
    data_root: Path
    #: the configuration an untuned run of the task uses (the searched fields at their defaults): a new study of a
    #: task with ``Task.start_at_defaults`` runs it first (None: no such first trial)
    untuned: PipelineConfig | None = None
    task: str = "stereo"
    study_name: str | None = None
    storage: str | None = None
    studies_dir: Path | None = None
    space_path: str | None = None
    fixes: list = field(default_factory=list)
    n_trials: int | None = None  # None: 50, or the whole grid with the grid sampler
    timeout: float | None = None
    seed: int | None = None
    sampler: str = "tpe"
    pruner: str = DEFAULT_PRUNER
    startup_trials: int | None = None
    budget: float = 0.5
    test_budget: float = 1.0
    val_scenes: list | None = None
    test_scenes: list | None = None
    min_covisibility: float | None = 0.1
    max_pairs: int | None = None
    chunk_pairs: int = 12
    cache_dir: str | None = None
    heartbeat: int | None = 10
    test_wait: float = 3600.0  # seconds a worker waits for the test phase another worker runs (0: do not wait)
    calibration_pairs: int = 8
    recalibrate: bool = False
    progress: bool = True
    test: bool = True
    test_runs: int = 3
    retest: bool = False
    multiview: object = None  # MultiviewConfig of task "multiview" (None: the protocol's bags)
    mapper: str | None = None  # task "reconstruction": "incremental" / "global" (None: the task's default)
    # task "reconstruction": a trial's mapping bound in seconds, "auto" (tuner.objective.auto_trial_timeout), None
    trial_timeout: float | str | None = None
    workers: int | None = None  # multiview: bag processes per trial (None: the task's default, all CPUs)
    jobs: int | None = None  # stereo: pair worker processes (None: every usable CPU); calibration uses as many
    warm_start: list = field(default_factory=list)  # studies (same storage) whose optimum + best trials go first
    gt_dir: str | None = None  # built ground truth (default $IMTUNE_GT, $IMTUNE_CACHE/gt, ~/.cache/imtune/gt)
    log: object = None  # callable(str) for status lines; None = stderr unless progress is off
    name_warnings: bool = False  # prefix the optimum's warnings with the study's name (runs of many studies)
    verbose: bool = False  # Optuna's own INFO log lines
    objective: str = "mAA10"  # "mAA10" | "pareto" (OBJECTIVES)
    pareto_span: float = PARETO_SPAN  # pareto: Gamma searched up to Gamma_max(span x B), the front crosses B
    confirm: int = 0  # tuner.confirm: the N best trials re-evaluated at more seeds before freezing (0: none)
    confirm_seeds: int = 2  # more seeds per confirmed candidate
    select: str | None = None  # tuner.select rule freezing the study (best | one-se | smooth; None: recorded/default)
    reference: str | None = None  # test runs compared with: None = paper defaults, "none", a config file or study
    ci_resamples: int = 2000  # bootstrap resamples of every mAA's 95% interval (0 = none)
    unused_options: tuple = ()  # typed options the task does not use (--budget of a multiview run): said, ignored
    terminate: str = "off"  # "auto": stop when more trials cannot beat the incumbent by its interval (tuner.terminate)

    def make_task(self, **extra):
        """The study's task with these settings' options (each task takes those it knows)."""
        from pipeline.tasks import make_task
        return make_task(self.task, min_covisibility=self.min_covisibility, max_pairs=self.max_pairs,
                         step_pairs=self.chunk_pairs, mv=self.multiview, workers=self.workers, jobs=self.jobs,
                         mapper=self.mapper,
                         trial_timeout=None if self.trial_timeout == "auto" else self.trial_timeout,
                         **{"ci_resamples": self.ci_resamples, **extra})

    def say(self, msg: str) -> None:
        if self.log is not None:
            self.log(msg)
        elif self.progress:
            print(msg, file=sys.stderr, flush=True)

    def warn(self, msg: str) -> None:
        """One warning line: through ``log`` when set, else on stderr even when progress is off (--quiet / --json)."""
        if self.log is not None or self.progress:
            self.say(f"warning: {msg}")
        else:
            print(f"warning: {msg}", file=sys.stderr, flush=True)


@dataclass
class StudyContext:
    study: object
    storage: object
    name: str
    space: object  # resolved SearchSpace
    vs: object  # ValidationSet
    objective: object
    attrs: dict
    cache: object
    created: bool


def study_name(s: TuneSettings, task_name: str | None = None) -> str:
    """The study's name: ``--study``, else ``<feature>-<num_features>-<ransac>-<task>`` (+ ``-global`` for the
    reconstruction task's global mapper, + ``-pareto`` / ``-auc10`` / ``-auc20`` by objective)."""
    return s.study_name or default_study_name(s.base, task_name or s.task) + (
        f"-{s.mapper}" if s.mapper and s.mapper != "incremental" else "") + (
        PARETO_SUFFIX if s.objective == "pareto" else f"-{s.objective}" if s.objective in AUC_OBJECTIVES else "")


def setup_study(s: TuneSettings) -> StudyContext:
    """Open the storage, load the validation data, create or resume the study (checking that it was
    created with the same settings), calibrate the budget if the study is new, build the objective."""
    import optuna

    from pipeline.cache import H5Cache
    from pipeline.geometry import get_estimator
    from pipeline.tasks.pool import resolve_jobs
    from tuner.budget import calibrate
    from tuner.objective import Objective
    from tuner.space import SearchSpace
    from tuner.storage import check_studies_dir, default_studies_dir, open_storage
    quiet_optuna(s.verbose)
    if s.sampler not in SAMPLERS:
        raise ImtuneError(f"unknown sampler {s.sampler!r} (choose from {', '.join(SAMPLERS)})")
    make_pruner(s.pruner)
    pareto = s.objective == "pareto"
    if s.objective not in OBJECTIVES:
        raise ImtuneError(f"unknown objective {s.objective!r} (choose from {', '.join(OBJECTIVES)})")
    if pareto and s.sampler == "cmaes":
        raise ImtuneError("sampler cmaes is single-objective in Optuna: use --sampler tpe (multi-objective TPE), "
                          "random or grid with --objective pareto")
    if pareto and not (math.isfinite(s.pareto_span) and s.pareto_span >= 1):
        raise ImtuneError(f"--pareto-span must be a number >= 1, got {s.pareto_span}")
    if not (s.budget > 0 and s.test_budget > 0):
        raise ImtuneError("budgets must be > 0 seconds per pair")
    if s.n_trials is not None and s.n_trials < 1:
        raise ImtuneError(f"--n-trials must be >= 1, got {s.n_trials}")
    task = s.make_task()  # unknown task -> one line listing the tasks
    if s.objective in AUC_OBJECTIVES:
        if s.objective not in task.summary_keys:
            raise ImtuneError(f"task {task.name} reports no pose AUC: --objective {s.objective} needs --task stereo; "
                              "use --objective mAA10")
        task.objective = s.objective  # the figure every trial returns and reports (tuner.objective.Objective)
    if pareto and not task.timed:
        raise ImtuneError(f"task {task.name} times no estimator of imtune's: it cannot run a pareto study "
                          "(accuracy against estimator CPU time); use --objective mAA10")
    get_estimator(s.base.geometry.ransac)  # unknown / unavailable estimator: one line, now
    s.studies_dir = Path(s.studies_dir) if s.studies_dir else default_studies_dir()
    check_studies_dir(s.studies_dir)  # budgets.json, frozen.yaml, reports: read-only or a file in the way -> now
    space = load_study_space(s, task)
    name = study_name(s, task.name)
    from tuner.freeze import check_study_outputs
    check_study_outputs(s.studies_dir, name)  # frozen.yaml, test.json: a file or folder in the way -> now
    storage = open_storage(s.storage, heartbeat=s.heartbeat, studies_dir=s.studies_dir)
    check_warm_start_sources(storage, name, s.warm_start)  # before the study is created: a typo leaves no empty study
    cache = H5Cache(s.cache_dir)
    vs = open_validation(s, task)
    pinned = pinned_gamma_warning(s, space, vs.fingerprint)  # before any calibration or trial
    if pinned:
        s.warn(pinned)
    base = dataclasses.replace(s.base, geometry=dataclasses.replace(s.base.geometry, seed=int(s.seed or 0)))
    mine = study_identity(s, task, space, vs, base)
    study = None
    try:
        study = optuna.load_study(study_name=name, storage=storage)
    except KeyError:
        pass
    stored = dict(study.user_attrs) if study is not None else {}
    if study is not None and len(study.directions) != (2 if pareto else 1):
        raise ImtuneError(f"study {name!r} exists as a {'pareto' if len(study.directions) > 1 else 'mAA10'} study: "
                          f"rerun with --objective {'pareto' if len(study.directions) > 1 else 'mAA10'} "
                          "or name a new study with --study")
    if study is not None and stored.get("imtune") is None and len(study.trials) > 0:
        raise ImtuneError(f"study {name!r} exists in the storage but was not created by imtune; name another with --study")
    created = not stored.get("imtune")
    if not created and not pareto and study_objective(stored) != s.objective:
        raise ImtuneError(f"study {name!r} maximises {study_objective(stored)}: rerun with --objective "
                          f"{study_objective(stored)} or name a new study with --study")
    if not created:
        check_compatible(name, stored, mine)
        if stored.get("sampler") and stored["sampler"] != s.sampler:  # allowed (a sampler changes no measurement),
            # but the study's attribute keeps the creator's: each trial records its own (Objective.sampler)
            s.warn(f"study {name!r} was created with sampler {stored['sampler']}; this worker samples with "
                   f"{s.sampler} (each trial's 'sampler' attribute says which drew it)")
    test_names = preflight(s, task, stored)  # fail fast, before any calibration: nothing after tuning may stop it
    held_in = [n for n in test_names if n in vs.scene_names]
    if held_in:
        s.warn(f"test scene {', '.join(held_in)} is also a validation scene: its test numbers are not held out "
               "(tuned on the scene they measure); choose other --test-scenes for a fair test")
    for note in vs.notes:
        s.warn(f"validation {note}")
    from tuner.select import reference_task_note
    if s.test and reference_task_note(s.reference, task.name):
        s.warn(reference_task_note(s.reference, task.name))
    s.say(f"validation: {', '.join(vs.scene_names)} ({vs.n_pairs} pairs) from {s.data_root}")
    vs.prepare(base, cache, progress=s.progress)
    if created:
        cal = None
        if space.needs_calibration:
            cal = calibrate(base.geometry.ransac, base, vs.scenes, cache, vs.fingerprint,
                            budgets=(s.budget, s.budget * s.pareto_span) if pareto else (s.budget,),
                            ratio=space.calibration["ratio"],
                            threshold=space.calibration["threshold"], max_pairs=s.calibration_pairs,
                            studies_dir=s.studies_dir, force=s.recalibrate, progress=s.progress, seed=int(s.seed or 0),
                            jobs=resolve_jobs(s.jobs))  # timed with as many estimators running as a trial runs
            gmax = cal.gamma_max(s.budget)
            s.say(f"budget: {s.budget:g} s per pair -> Gamma_max = {gmax} for {base.geometry.ransac} "
                  f"(calibrated on {cal.pairs} pairs, {len(cal.curve)} caps)")
        else:
            gmax = None
        # pareto: Gamma reaches past Gamma_max(B) so that the front shows what time beyond B buys
        resolved = space.resolve(cal.gamma_max(s.budget * s.pareto_span) if pareto and cal else gmax)
        mine["budget"].update(gamma_max=gmax, gamma_max_test=cal.gamma_max(s.test_budget) if cal and cal.covers(s.test_budget) else None,
                              calibration=cal.to_dict() if cal else None)
        if pareto:
            mine["objective"] = {"name": "pareto", "values": ["mAA10", "median estimator CPU seconds per pair"],
                                 "directions": ["maximize", "minimize"], "pareto_span": float(s.pareto_span)}
            mine["budget"]["gamma_max_front"] = cal.gamma_max(s.budget * s.pareto_span) if cal else None
        if s.objective in AUC_OBJECTIVES:
            mine["objective"] = {"name": s.objective, "values": [s.objective], "directions": ["maximize"]}
        mine["search_space_resolved"] = resolved.spec()
        mine["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        mine["sampler"] = s.sampler
        study = optuna.create_study(study_name=name, storage=storage, load_if_exists=True,
                                    directions=["maximize", "minimize"] if pareto else ["maximize"])
        again = study.user_attrs
        if not again.get("imtune"):
            # this process creates the study: an earlier study's frozen.yaml / test.json in its folder (the storage
            # emptied or replaced) would be overwritten by this one's without a word -- kept aside, and said
            from tuner.freeze import set_aside_earlier_outputs
            kept = set_aside_earlier_outputs(s.studies_dir, name)
            if kept is not None:
                s.warn(f"study {name!r} is new in this storage, but its folder held the results of an earlier study of "
                       f"that name: moved to {kept} (kept, not overwritten)")
            for k, v in mine.items():
                if k != "imtune":
                    study.set_user_attr(k, v)
            study.set_user_attr("imtune", SCHEMA)  # last: marks the attributes complete
        else:
            check_compatible(name, again, mine)
        stored = dict(study.user_attrs)
    resolved = SearchSpace.from_spec(stored["search_space_resolved"], source=stored.get("search_space_source", ""))
    resolved.calibration = space.calibration
    # every trial of a study uses the estimator seed the study was created with
    base = dataclasses.replace(base, geometry=dataclasses.replace(base.geometry, seed=int(stored.get("seed", 0))))
    from tuner.objective import PARETO, SINGLE
    objective = Objective(task, base, resolved, vs, cache, budget=float(stored["budget"]["seconds_per_pair"]),
                          objectives=PARETO if pareto else SINGLE)
    objective.auto_trial_timeout = s.trial_timeout == "auto"
    return StudyContext(study=study, storage=storage, name=name, space=resolved, vs=vs, objective=objective,
                        attrs=stored, cache=cache, created=created)


def trial_counts(study) -> dict:
    from optuna.trial import TrialState

    from tuner.protocol import trial_within_budget
    counts = {st.name.lower(): 0 for st in TrialState}
    infeasible = 0
    for t in study.get_trials(deepcopy=False):
        counts[t.state.name.lower()] += 1
        if t.state == TrialState.COMPLETE and not trial_within_budget(t):
            infeasible += 1
    counts["infeasible"] = infeasible
    return counts


def trial_target(s: TuneSettings, space) -> int:
    """How many finished (COMPLETE or PRUNED) trials a worker runs the study to: ``s.n_trials``, else
    :data:`DEFAULT_TRIALS` (the grid sampler: the grid's size), at most the grid's size with the grid sampler.
    ``space``: the study's resolved search space."""
    n_target = s.n_trials or (space.grid_size() if s.sampler == "grid" else DEFAULT_TRIALS)
    if s.sampler == "grid":
        n_target = min(n_target, space.grid_size())
    return n_target


def optimize(ctx: StudyContext, s: TuneSettings) -> dict:
    """Run trials until the study holds ``s.n_trials`` finished trials (or ``s.timeout``)."""
    import optuna
    from optuna.trial import TrialState

    from tuner.storage import fail_stale_trials
    study = ctx.study
    n_target = trial_target(s, ctx.space)
    from tuner.seeding import worker_seeded
    startup = s.startup_trials or max(3, min(10, (n_target or 50) // 5))
    # each worker's sampler seed derives from --seed and its first trial number: the same --seed in two
    # workers or a resume never replays the same parameters (issue 14 item 9; see tuner.seeding)
    sampler = worker_seeded(lambda seed: make_sampler(s.sampler, seed, ctx.space, startup), s.seed)
    # Optuna prunes single-objective studies only (Trial.report / should_prune raise on multi-objective ones)
    pruner = make_pruner("none" if getattr(ctx.objective, "pareto", False) else s.pruner)
    study = optuna.load_study(study_name=ctx.name, storage=ctx.storage, sampler=sampler, pruner=pruner)
    ctx.study = study
    from tuner.storage import track_created_trials
    created = track_created_trials(study._storage)  # before the first trial: a Ctrl-C before the objective runs
    ctx.objective.sampler = s.sampler  # recorded in each trial: a resume may use another sampler than the creator

    def finished(st) -> int:
        return len(st.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED)))

    from tuner.terminate import make_terminator, should_terminate
    terminator = make_terminator(s.terminate, n_target, s.objective, seed=s.seed)  # an unknown mode: before any bar
    fail_stale_trials(study)  # trials of killed workers: FAIL, parameters re-enqueued once
    warm_start(study, ctx.storage, ctx.space, s.warm_start, say=s.say)  # a new study only
    from pipeline.tasks import task_class
    if task_class(s.task).start_at_defaults and s.untuned is not None:  # a new study without warm start only
        start_at_defaults(study, ctx.space, s.untuned, s.sampler, say=s.say)
    figure = s.objective if s.objective in AUC_OBJECTIVES else task_class(s.task).objective  # the progress bar's
    done0 = finished(study)
    bar = None
    if s.progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=n_target, initial=min(done0, n_target), desc=f"{ctx.name}", unit="trial",
                   dynamic_ncols=True)
        _set_postfix(bar, study, figure)

    stop = [False]

    def callback(st, trial):
        done = finished(st)
        if bar is not None:
            bar.n = min(done, n_target)
            _set_postfix(bar, st, figure)
            bar.refresh()
        if done < n_target and terminator is not None and trial.state == TrialState.COMPLETE \
                and should_terminate(terminator, st, say=s.say):
            stop[0] = True

    t0 = time.perf_counter()
    reason = "target"
    try:
        stopped = terminator is not None and done0 < n_target and should_terminate(terminator, study, say=s.say)
        if done0 < n_target and not stopped:  # a terminated study resumed: no trial more
            from tuner.workers import run_to_target
            # the study-wide target, exact across workers: each trial's place claimed before it runs
            reason = run_to_target(study, ctx.objective, n_target, timeout=s.timeout, callbacks=(callback,),
                                   should_stop=lambda: stop[0], on_wait=s.say)
        elif stopped:
            reason = "stopped"
    except BaseException as e:
        from tuner.storage import fail_interrupted_trials, interrupt_in_chain
        if isinstance(e, KeyboardInterrupt) or interrupt_in_chain(e) is not None:
            fail_interrupted_trials(study, ctx.objective.trials_run[-1:], created)  # this process's
        raise
    finally:
        if bar is not None:
            bar.close()
    return {"trials_run": list(ctx.objective.trials_run), "seconds": time.perf_counter() - t0,
            "target": n_target, "stopped": reason}


def _set_postfix(bar, study, figure: str = "mAA10") -> None:
    b = best_feasible(study)
    c = trial_counts(study)
    parts = []
    if b is not None:
        from tuner.protocol import trial_value
        parts.append(f"best {figure}={trial_value(b):.4f} (#{b.number})")  # the task's figure (score: IMC)
    if c["pruned"]:
        parts.append(f"pruned={c['pruned']}")
    if c["infeasible"]:
        parts.append(f"infeasible={c['infeasible']}")
    bar.set_postfix_str(", ".join(parts))


def tune(s: TuneSettings) -> dict:
    """The whole protocol: study (create or resume) -> trials -> freeze -> test. Returns a JSON-able
    dict: study, storage (masked), counts, frozen settings, test results (None if skipped)."""
    from optuna.trial import TrialState

    from tuner.storage import storage_label
    ctx = setup_study(s)
    s.say(f"study {ctx.name} in {storage_label(s.storage, s.studies_dir)} "
          f"({'created' if ctx.created else 'resumed'}; sampler {s.sampler}, target "
          f"{s.n_trials or ('the grid' if s.sampler == 'grid' else DEFAULT_TRIALS)} trials)")
    if ctx.objective.pareto:
        s.say("objective pareto: maximize mAA(10°), minimize median estimator seconds per pair; no pruning "
              "(Optuna prunes single-objective studies only); frozen: the best trial within B on the front")
    run = optimize(ctx, s)
    # the search stopped at --timeout before the trial target: said, and recorded (the frozen optimum is that of fewer
    # trials than asked; a rerun of the command runs the missing ones)
    run["time_limit"] = s.timeout if run.get("stopped") == "timeout" else None
    out = {"study": ctx.name, "storage": storage_label(s.storage, s.studies_dir), "worker": run,
           "counts": trial_counts(ctx.study), "timed": bool(getattr(ctx.objective.task, "timed", True)),
           "frozen": None, "frozen_path": None, "test": None, "warnings": []}
    if best_feasible(ctx.study) is None:
        from tuner.protocol import no_feasible_message
        raise ImtuneError(f"{no_feasible_message(ctx.study, ctx.attrs['budget']['seconds_per_pair'])}; run more "
                          "trials, or a larger --budget")
    others = ctx.study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    if not s.test or (others and run["stopped"] == "timeout"):
        _freeze_into(out, ctx, s)
        if s.test:  # this worker's --timeout ended it before the study was complete
            s.say(f"{len(others)} trial(s) still running in other workers: skipping the test run "
                  f"(the worker that completes the study runs it; or `tune test --study {ctx.name}`)")
        return out
    _test_phase(out, ctx, s)
    from tuner.freeze import earlier_test_line
    if out["test"] and earlier_test_line(out["test"]):
        s.warn(earlier_test_line(out["test"]))
    return out


def _freeze_into(out: dict, ctx: StudyContext, s: TuneSettings) -> dict:
    """Freeze the study (``<studies dir>/<study>/frozen.yaml``), say the optimum's warnings; returns the frozen dict."""
    from tuner.freeze import freeze
    if s.confirm:  # tuner.confirm: the best trials at more seeds; the "confirmed" rule freezes the best mean
        from tuner.confirm import confirm_candidates
        s.say(f"confirming the {s.confirm} best trials at {s.confirm_seeds} more seeds each")
        confirm_candidates(ctx, s.confirm, s.confirm_seeds, say=s.say)
    frozen, path = freeze(ctx.study, s.studies_dir, select=s.select)
    out["frozen"], out["frozen_path"] = frozen, str(path)
    from tuner.diagnostics import optimum_warnings  # on a bound, Gamma_max at the ceiling, every trial 0
    out["warnings"] = list(frozen["warnings"]) if "warnings" in frozen else optimum_warnings(ctx.study, frozen)
    for w in out["warnings"]:
        s.warn(f"{ctx.name}: {w}" if s.name_warnings else w)
    return frozen


def _test_phase(out: dict, ctx: StudyContext, s: TuneSettings) -> None:
    """The study's one test phase (``tuner.workers.TestPhase``): this worker freezes and tests if it is the first
    to claim it, else it waits (at most ``s.test_wait`` seconds) for the worker that does and takes its frozen
    settings and result; a phase whose owner stopped renewing its lease is taken over."""
    import datetime as _dt2

    from tuner.freeze import run_test_for_study
    from tuner.storage import DEFAULT_HEARTBEAT_S, classify, default_storage_url, scrub
    from tuner.workers import FROZEN_ATTR, TestPhase, phase_key, slim_test_result
    key = phase_key(ctx.study, {"scenes": s.test_scenes, "runs": s.test_runs, "max_pairs": s.max_pairs,
                                "reference": s.reference, "select": s.select, "ci": s.ci_resamples})
    server = classify(s.storage or default_storage_url(s.studies_dir))[0] == "rdb"
    phase = TestPhase(ctx.study, key, lease=3.0 * (s.heartbeat or DEFAULT_HEARTBEAT_S), settle=1.0 if server else 0.25)
    began = _dt2.datetime.now(_dt2.timezone.utc)
    deadline = time.monotonic() + max(0.0, float(s.test_wait))
    said = False
    while True:
        rec = phase.record()
        state = (rec or {}).get("state")
        redo = s.retest and state == "done" and str(rec.get("finished") or "") < began.isoformat(timespec="seconds")
        if state == "done" and not redo:
            if not _phase_here(rec, s):
                _take_phase_result(out, ctx, rec)
                return
            break  # a rerun where the phase ran: frozen and tested again as before (the test.json is reused)
        if state == "failed":
            raise ImtuneError(f"the test phase of study {ctx.name} failed in worker {rec.get('host')} pid "
                              f"{rec.get('pid')}: {rec.get('error')}; fix that and rerun, or run "
                              f"`tune test --study {ctx.name}`")
        if rec is None or phase.stale(rec) or redo:
            if rec is not None and phase.stale(rec):
                s.warn(f"the test phase's worker ({rec.get('host')} pid {rec.get('pid')}) stopped renewing its lease: "
                       "taking it over")
            if phase.claim(rec):
                break
            continue  # another worker claimed it at the same moment: wait for it
        if not said:
            s.say(f"the test phase runs in worker {rec.get('host')} pid {rec.get('pid')}: waiting for its result "
                  f"(at most {s.test_wait:g} s)")
            said = True
        status, _ = phase.wait(deadline - time.monotonic())
        if status == "timeout":
            out["frozen"] = ctx.study.user_attrs.get(FROZEN_ATTR)
            out["test_phase"] = {"state": "running elsewhere", "host": rec.get("host"), "pid": rec.get("pid"),
                                 "this_worker": False}
            return
    if state != "done":
        phase.start_renewing()
    try:
        frozen = _freeze_into(out, ctx, s)
        ctx.study.set_user_attr(FROZEN_ATTR, frozen)  # what the waiting workers print
        out["test"] = run_test_for_study(ctx.study, frozen, s.studies_dir, data_root=s.data_root,
                                         scenes=s.test_scenes, cache=ctx.cache, runs=s.test_runs,
                                         max_pairs=s.max_pairs, progress=s.progress, reuse=not s.retest, jobs=s.jobs,
                                         workers=s.workers, reference=s.reference, ci_resamples=s.ci_resamples,
                                         gt_dir=s.gt_dir)
    except KeyboardInterrupt:
        phase.finish("abandoned")  # a waiting worker takes it over at once
        raise
    except Exception as e:
        try:
            phase.finish("failed", error=scrub(str(e).splitlines()[0] if str(e) else type(e).__name__, s.storage))
        except Exception:  # noqa: BLE001 - the storage itself may be what failed: that error is reported
            pass
        raise
    test_json = str(Path(out["frozen_path"]).parent / "test.json")
    done = dict(frozen_trial=frozen["trial"], frozen_path=out["frozen_path"], test_json=test_json)
    try:  # the whole result, as test.json holds it (its per-pair errors: what findings and replicates read)
        phase.finish("done", **done, test=out["test"])
    except Exception:  # noqa: BLE001 - too large for the storage's attribute column (MySQL TEXT: 64 KiB)
        phase.finish("done", **done, test=slim_test_result(out["test"]))
    out["test_phase"] = {"state": "done", "this_worker": True, "test_json": test_json}


def _phase_here(rec: dict, s: TuneSettings) -> bool:
    """Whether a finished test phase ran on this host into this studies folder (a rerun of the same command)."""
    import socket
    path = str(rec.get("frozen_path") or "")
    return rec.get("host") == socket.gethostname() and path.startswith(str(Path(s.studies_dir).resolve()) + "/")


def _take_phase_result(out: dict, ctx: StudyContext, rec: dict) -> None:
    """Another worker's finished test phase: its frozen settings and test result (as its test.json holds it; without
    the per-pair errors where the storage could not hold them)."""
    from tuner.workers import FROZEN_ATTR
    out["frozen"] = ctx.study.user_attrs.get(FROZEN_ATTR)
    out["frozen_path"] = f"{rec.get('host')}:{rec.get('frozen_path')}"
    out["test"] = rec.get("test")
    out["warnings"] = list((out["frozen"] or {}).get("warnings") or [])
    out["test_phase"] = {"state": "done", "this_worker": False, "host": rec.get("host"), "pid": rec.get("pid"),
                         "test_json": rec.get("test_json")}
