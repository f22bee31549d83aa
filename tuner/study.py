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
one storage share the work (trials still running in other workers when the target is reached are
finished and kept: at most N - 1 beyond the target).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError
from tuner.protocol import best_feasible  # noqa: F401  (re-exported: the study's pick)
from tuner.version import code_version  # noqa: F401  (re-exported)

SAMPLERS = ("tpe", "random", "cmaes", "grid")
PRUNERS = ("median", "sha", "hyperband", "none")
DEFAULT_PRUNER = "hyperband"  # the fastest to the same frozen optimum in benchmarks/study_wall_time.py (README)
# mAA10: maximise mAA(10 deg) within the budget B; pareto: a two-objective study (maximise mAA(10 deg), minimise
# the median estimator seconds per pair) whose Pareto front tuner.pareto draws and reads the best within B off
OBJECTIVES = ("mAA10", "auc10", "auc20", "pareto")
# auc10 / auc20: maximise the pose AUC (pipeline.metrics.auc) instead; the study records it (user attribute
# "objective"), its default name ends in -auc10 / -auc20, and a study without the attribute maximised mAA10
AUC_OBJECTIVES = ("auc10", "auc20")
PARETO_SUFFIX = "-pareto"
PARETO_SPAN = 4.0
SCHEMA = 1
DEFAULT_TRIALS = 50


def feature_label(conf: PipelineConfig) -> str:
    """The ``<feature>`` part of a study name: the name plus any non-default variant."""
    f = conf.feature
    name = f.name
    if name.startswith("custom:"):  # imported features: the folder's name, not its path
        name = "custom_" + (Path(name[len("custom:"):]).name or "features")
    tags = [name]
    if f.upright_plus:
        tags.append("upright++")
    elif f.upright:
        tags.append("upright")
    if f.clahe != "none":
        tags.append(f"clahe_{f.clahe}")
    if not f.low_threshold:
        tags.append("defthr")
    if f.mr_size is not None:
        tags.append(f"mr{f.mr_size:g}")
    if f.max_side != 1024:
        tags.append(f"side{f.max_side}")
    for k, v in f.options or ():  # extractor options (--feature-option): sift+edge_threshold5
        tags.append(f"{k}{v:g}" if isinstance(v, float) else f"{k}{v}")
    m = conf.matching
    if m.method != "exact":
        tags.append(m.method)
    if m.fginn:
        tags.append("fginn")
    if getattr(m, "prefilter", "none") not in ("none", None):
        tags.append(str(m.prefilter))
    if getattr(m, "custom_matches", None):
        tags.append("custom_matches")
    return "_".join(tags[:1]) + ("+" + "+".join(tags[1:]) if len(tags) > 1 else "")


def default_study_name(conf: PipelineConfig, task: str = "stereo") -> str:
    return f"{feature_label(conf)}-{conf.feature.num_features}-{conf.geometry.ransac}-{task}"


@dataclass
class TuneSettings:
    """Everything one `tune` run needs. ``base`` is the fixed pipeline configuration (the searched
    fields are placeholders). Times in seconds; budgets are median estimator seconds per pair."""
    base: PipelineConfig
    data_root: Path
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
    calibration_pairs: int = 8
    recalibrate: bool = False
    progress: bool = True
    test: bool = True
    test_runs: int = 3
    retest: bool = False
    multiview: object = None  # MultiviewConfig of task "multiview" (None: the protocol's bags)
    workers: int | None = None  # multiview: bag processes per trial (None: the task's default, all CPUs)
    jobs: int | None = None  # stereo: pair worker processes (None: every usable CPU); calibration uses as many
    warm_start: list = field(default_factory=list)  # studies (same storage) whose optimum + best trials go first
    gt_dir: str | None = None  # built ground truth (default $IMTUNE_GT, $IMTUNE_CACHE/gt, ~/.cache/imtune/gt)
    log: object = None  # callable(str) for status lines; None = stderr unless progress is off
    name_warnings: bool = False  # prefix the optimum's warnings with the study's name (runs of many studies)
    verbose: bool = False  # Optuna's own INFO log lines
    objective: str = "mAA10"  # "mAA10" | "pareto" (OBJECTIVES)
    pareto_span: float = PARETO_SPAN  # pareto: Gamma searched up to Gamma_max(span x B), the front crosses B
    select: str | None = None  # tuner.select rule freezing the study (best | one-se | smooth; None: recorded/default)
    reference: str | None = None  # test runs compared with: None = paper defaults, "none", a config file or study
    ci_resamples: int = 2000  # bootstrap resamples of every mAA's 95% interval (0 = none)
    unused_options: tuple = ()  # typed options the task does not use (--budget of a multiview run): said, ignored

    def make_task(self, **extra):
        """The study's task with these settings' options (each task takes those it knows)."""
        from pipeline.tasks import make_task
        return make_task(self.task, min_covisibility=self.min_covisibility, max_pairs=self.max_pairs,
                         step_pairs=self.chunk_pairs, mv=self.multiview, workers=self.workers, jobs=self.jobs,
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


def _quiet_optuna(verbose: bool = False):
    import optuna
    if verbose:
        optuna.logging.set_verbosity(optuna.logging.INFO)
        return
    # ERROR: a trial failing (Ctrl-C, a bug) is reported once, as the CLI's one-line error, not as
    # Optuna's warning with a traceback; `tune --verbose` restores Optuna's per-trial INFO lines
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    warnings.filterwarnings("ignore", category=FutureWarning, module="optuna")


def make_sampler(name: str, seed: int | None, space, startup_trials: int | None = None):
    """TPE (multivariate, constant liar for parallel workers), random, CMA-ES or grid."""
    import optuna
    if name not in SAMPLERS:
        raise ImtuneError(f"unknown sampler {name!r} (choose from {', '.join(SAMPLERS)})")
    if name == "tpe":
        return optuna.samplers.TPESampler(seed=seed, n_startup_trials=int(startup_trials or 10), multivariate=True,
                                          constant_liar=True)
    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    if name == "cmaes":
        try:
            import cmaes  # noqa: F401
        except ImportError:
            raise ImtuneError("sampler cmaes needs the `cmaes` package: pip install cmaes") from None
        # its UserWarning "Constraints have been set, but CmaEsSampler will not use them" came after every trial (two
        # lines of file and line each): no sampler here is given the budget constraint (TPE neither); freeze reads it
        warnings.filterwarnings("ignore", message="Constraints have been set, but CmaEsSampler", category=UserWarning)
        return optuna.samplers.CmaEsSampler(seed=seed, n_startup_trials=int(startup_trials or 1),
                                            warn_independent_sampling=False)
    return optuna.samplers.GridSampler(space.grid(), seed=seed)


def make_pruner(name: str):
    """Optuna's pruner ``name``. A trial's steps are its chunks of pairs (``--chunk-pairs``, stratified over the
    scenes so that an early chunk is representative; the intermediate value is the running mAA(10)):

    - ``median``: MedianPruner, after 5 complete trials, from the second chunk on: stop a trial whose running value
      is below the median of the other trials' at the same chunk;
    - ``sha``: SuccessiveHalvingPruner (asynchronous successive halving), rungs at chunks 1, 2, 4, ... (reduction
      factor 2): a trial continues past a rung only in the top half of the trials that reached it;
    - ``hyperband``: HyperbandPruner (several successive-halving brackets; the maximum resource is the number of
      chunks of the first complete trial), reduction factor 2;
    - ``none``: every trial runs all its pairs.

    Whatever the pruner, a trial proven over the time budget is stopped (``tuner.objective``)."""
    import optuna
    if name not in PRUNERS:
        raise ImtuneError(f"unknown pruner {name!r} (choose from {', '.join(PRUNERS)})")
    if name == "none":
        return optuna.pruners.NopPruner()
    if name == "sha":
        return optuna.pruners.SuccessiveHalvingPruner(min_resource=1, reduction_factor=2, min_early_stopping_rate=0)
    if name == "hyperband":
        return optuna.pruners.HyperbandPruner(min_resource=1, max_resource="auto", reduction_factor=2)
    return optuna.pruners.MedianPruner(n_startup_trials=5, n_warmup_steps=1)


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


def load_study(storage, name: str):
    """An existing study, or ImtuneError listing the studies in the storage."""
    import optuna
    try:
        return optuna.load_study(study_name=name, storage=storage)
    except KeyError:
        names = [s.study_name for s in optuna.get_all_study_summaries(storage, include_best_trial=False)]
        raise ImtuneError(f"no study {name!r} in the storage (studies: {', '.join(names) or 'none'})") from None


def _first_difference(a, b, path="") -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b or a[k] != b[k]:
                return _first_difference(a.get(k), b.get(k), f"{path}.{k}" if path else str(k))
        return path
    return f"{path}: {a!r} -> {b!r}" if path else f"{a!r} -> {b!r}"


class IncompatibleStudy(ImtuneError):
    """A study of this name exists with other settings or data (:func:`check_compatible`)."""


def check_compatible(name: str, stored: dict, mine: dict) -> None:
    """Resume only with the same search space, pipeline, budget and validation data (IncompatibleStudy)."""
    import json

    def norm(x):
        return json.loads(json.dumps(x, default=str))
    checks = [("search_space", "a different search space"),
              ("pipeline", "a different pipeline configuration"),
              ("data_fingerprint", "different validation data"),
              ("task_options", "different task settings")]
    for key, what in checks:
        if norm(stored.get(key)) != norm(mine.get(key)):
            diff = _first_difference(norm(stored.get(key)), norm(mine.get(key)))
            raise IncompatibleStudy(f"study {name!r} exists with {what} ({diff}); rerun with its original settings "
                                    "or name a new study with --study")
    b_old = (stored.get("budget") or {}).get("seconds_per_pair")
    b_new = mine["budget"]["seconds_per_pair"]
    if b_old is not None and not math.isclose(float(b_old), float(b_new)):
        raise IncompatibleStudy(f"study {name!r} exists with budget {b_old} s per pair, not {b_new}; "
                                f"rerun with --budget {b_old} or name a new study with --study")


def check_task_scene(task, scene, role: str, others: str) -> None:
    """A one-line ImtuneError when ``task`` cannot evaluate ``scene`` (``Task.check_scene``: no pairs, no ground
    truth, no bags), naming the ``role`` ("validation", "test") and ending with ``others`` (the flag that fixes it)."""
    why = task.check_scene(scene)
    if why and why.startswith("no ground truth"):
        raise ImtuneError(f"{role} scene {scene.name!r} has {why}; build it with `tune data build-gt --data "
                          f"{scene.root}`, {others}")
    if why:
        raise ImtuneError(f"{role} scene {scene.name!r}: {why}; {others}")


def open_validation(s: TuneSettings, task):
    """The ValidationSet of the settings' data and validation scenes for ``task``."""
    from tuner.evaluate import load_scenes
    from tuner.objective import ValidationSet
    scenes = load_scenes(s.data_root, s.val_scenes, split="val", gt_dir=s.gt_dir)
    if not scenes:
        raise ImtuneError(f"no validation scenes in {s.data_root}")
    for scene in scenes:  # before the study exists: a study whose every trial must fail is never created
        check_task_scene(task, scene, "validation", "choose others with --scenes")
    return ValidationSet.from_scenes(scenes, task)


def test_scene_names(s: TuneSettings) -> list[str]:
    if s.test_scenes:
        return list(s.test_scenes)
    from pipeline.data import default_splits
    return list(default_splits(s.data_root).get("test", []))


def preflight(s: TuneSettings, task, stored: dict | None = None) -> list[str]:
    """Fail fast: check, before any calibration or trial, everything that would stop the study after tuning —
    the test run's scenes (``--test-scenes``, else those the study was created with, else the data set's test
    split) exist, load, have ground truth and something for ``task`` to evaluate. Reads the scenes' metadata
    only (no features). Returns the test scene names ([] with ``--no-test``); a one-line ImtuneError naming
    the flag that fixes it (``--test-scenes``, ``--no-test``) otherwise."""
    if not s.test:
        return []
    from tuner.evaluate import load_scenes
    skip = "or tune without the test run: --no-test"
    names = list(s.test_scenes or ((stored or {}).get("data") or {}).get("test_scenes") or test_scene_names(s))
    from tuner.evaluate import check_unique_scenes
    check_unique_scenes(names, "test scenes: ")
    if not names:
        raise ImtuneError(f"no test scenes: {s.data_root} has no test split; name them with --test-scenes A,B "
                          f"(or add a splits.yaml with 'test' to the data folder), {skip}")
    for n in names:
        try:
            (scene,) = load_scenes(s.data_root, [n], split="test", gt_dir=s.gt_dir)
        except ImtuneError as e:
            raise ImtuneError(f"test scene {n!r}: {e}; choose others with --test-scenes, {skip}") from None
        for note in task.scene_notes(scene):  # e.g. bag sizes above the scene's image count
            s.warn(f"test {note}")
        check_task_scene(task, scene, "test", f"choose others with --test-scenes, {skip}")
    return names


def pinned_gamma_warning(s: TuneSettings, space, fingerprint: str | None = None) -> str | None:
    """The warning for ``--fix max_iters=G`` above Gamma_max(B), else None. Gamma_max is the search space's ceiling,
    not a hard cap (a trial is feasible when its measured median estimator seconds per pair are within B, whatever
    its Gamma), so a pinned Gamma above it is allowed; but it will exceed the budget on most pairs, and every trial
    is then infeasible. A pinned Gamma calibrates nothing: Gamma_max(B) is the one stored for this configuration in
    budgets.json when there is one, else the largest any calibration gives (``tuner.budget.GAMMA_CEILING``)."""
    g = space.fixed.get("max_iters")
    if isinstance(g, bool) or not isinstance(g, int):
        return None
    from pipeline.geometry import ESTIMATORS
    ransac = s.base.geometry.ransac
    if not getattr(ESTIMATORS.get(ransac), "uses_iterations", True):
        return None
    from tuner.budget import GAMMA_CEILING, calibration_key, stored_calibration
    cal = None
    if fingerprint is not None and s.studies_dir is not None:
        from pipeline.tasks.pool import resolve_jobs
        cal_conf = space.calibration or {}
        key = calibration_key(ransac, s.base.feature, float(cal_conf.get("ratio", 0.9)),
                              float(cal_conf.get("threshold", 0.5)), fingerprint, jobs=resolve_jobs(s.jobs))
        cal = stored_calibration(Path(s.studies_dir), key)
    if cal is not None and cal.covers(s.budget):
        gmax = cal.gamma_max(s.budget)
        basis = f"Gamma_max({s.budget:g} s) = {gmax:,} calibrated for {ransac} on this machine"
    else:
        gmax = GAMMA_CEILING
        basis = f"the largest Gamma_max any calibration gives ({GAMMA_CEILING:,})"
    if g <= gmax:
        return None
    return (f"--fix max_iters={g} is above {basis}: a pinned Gamma above Gamma_max(B) will exceed the "
            f"{s.budget:g} s per pair budget on most pairs (their trials are infeasible and cannot be frozen); pin a "
            "smaller Gamma, or let it be searched")


def load_study_space(s: TuneSettings, task):
    """The study's search space: ``--space``, else the task's own file (``Task.space_file``), else the estimator
    family's; then ``--fix`` pins; then every parameter the task does not use dropped (never searched, never
    recorded)."""
    from tuner.protocol import searchable, unused_by
    from tuner.space import SPACES_DIR, load_space
    path = s.space_path or (SPACES_DIR / task.space_file if task.space_file else None)
    space = load_space(path, feature=s.base.feature.name, estimator=s.base.geometry.ransac, fixes=s.fixes)
    from tuner.space import parse_fixes
    unused = [k for k in parse_fixes(s.fixes) if k in unused_by(task)]
    if unused:  # dropped below like the rest: a typed pin that does nothing was silently forgotten
        s.warn(f"--fix {', '.join(unused)}: the {task.name} task does not use "
               f"{'it' if len(unused) == 1 else 'them'} (it uses {', '.join(searchable(task))}); ignored")
    if s.unused_options:  # stereo options of a multiview run, found by the command line (tuner.commands.study)
        s.warn(f"{', '.join(s.unused_options)}: the {task.name} task does not use "
               f"{'it' if len(s.unused_options) == 1 else 'them'} (COLMAP reconstructs each bag whole, with its own "
               "RANSAC, untimed; --bags sets the work); ignored")
    for k in unused_by(task):
        space.params.pop(k, None)
        space.fixed.pop(k, None)
    if not space.params:
        pinned = f"every parameter is fixed ({', '.join(sorted(space.fixed))}: in the file or by --fix)" \
            if space.fixed else "no parameter is searched"  # the file was not named: the culprit unsaid
        raise ImtuneError(f"search space {space.source}: {pinned}; nothing to tune: give one a range there, or drop "
                          "its --fix")
    return space


def study_identity(s: TuneSettings, task, space, vs, base: PipelineConfig) -> dict:
    """The user attributes a new study of these settings records before its calibration: among them what
    :func:`check_compatible` compares when a study of that name is resumed (search space, pipeline, validation data,
    task options, budget). ``vs``: the settings' :func:`open_validation`; ``base``: ``s.base`` with the estimator
    seed set."""
    from tuner.formatting import ground_truth_origins
    from tuner.protocol import blank_searched
    return {
        "imtune": SCHEMA, "task": task.name, "task_options": task.options(),
        "feature": feature_label(base), "feature_name": base.feature.name,
        "num_features": base.feature.num_features, "ransac": base.geometry.ransac,
        "pipeline": blank_searched(base, list(space.params) + list(space.fixed)),
        "search_space": space.spec(), "search_space_source": space.source,
        "data_fingerprint": vs.fingerprint,
        "data": {"root": str(s.data_root), "val_scenes": vs.scene_names, "test_scenes": test_scene_names(s),
                 "min_covisibility": s.min_covisibility, "max_pairs": s.max_pairs, "pairs": vs.n_pairs,
                 # where the validation scenes' poses come from (their own, or imtune's SfM), and the task's notes
                 # on them (pairs an SfM ground truth dropped): what the reports say beside validation figures
                 "ground_truth": ground_truth_origins(vs.scene_objs), "notes": vs.notes},
        "budget": {"seconds_per_pair": float(s.budget), "test_seconds_per_pair": float(s.test_budget),
                   "statistic": "median estimator seconds per pair"},
        "code_version": code_version(),
        "seed": int(s.seed or 0),
    }


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
    _quiet_optuna(s.verbose)
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
                          "(accuracy against estimator time); use --objective mAA10")
    get_estimator(s.base.geometry.ransac)  # unknown / unavailable estimator: one line, now
    s.studies_dir = Path(s.studies_dir) if s.studies_dir else default_studies_dir()
    check_studies_dir(s.studies_dir)  # budgets.json, frozen.yaml, reports: read-only or a file in the way -> now
    space = load_study_space(s, task)
    name = s.study_name or default_study_name(s.base, task.name) + (
        PARETO_SUFFIX if pareto else f"-{s.objective}" if s.objective in AUC_OBJECTIVES else "")
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
            mine["objective"] = {"name": "pareto", "values": ["mAA10", "median estimator seconds per pair"],
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
    return StudyContext(study=study, storage=storage, name=name, space=resolved, vs=vs, objective=objective,
                        attrs=stored, cache=cache, created=created)


def study_objective(attrs: dict) -> str:
    """The figure a study maximised, from its user attributes: "mAA10" (the default, and every study created
    before --objective auc10/auc20), "auc10", "auc20" or "pareto"."""
    o = attrs.get("objective")
    return str(o.get("name", "mAA10")) if isinstance(o, dict) else "mAA10"


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

    fail_stale_trials(study)  # trials of killed workers: FAIL, parameters re-enqueued once
    warm_start(study, ctx.storage, ctx.space, s.warm_start, say=s.say)  # a new study only
    done0 = finished(study)
    bar = None
    if s.progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=n_target, initial=min(done0, n_target), desc=f"{ctx.name}", unit="trial",
                   dynamic_ncols=True)
        _set_postfix(bar, study)

    def callback(st, trial):
        fail_stale_trials(st)
        done = finished(st)
        if bar is not None:
            bar.n = min(done, n_target)
            _set_postfix(bar, st)
            bar.refresh()
        if done >= n_target:
            st.stop()

    t0 = time.perf_counter()
    try:
        if done0 < n_target:
            study.optimize(ctx.objective, n_trials=None, timeout=s.timeout, callbacks=[callback],
                           gc_after_trial=False, show_progress_bar=False)
    except BaseException as e:
        from tuner.storage import fail_interrupted_trials, interrupt_in_chain
        if isinstance(e, KeyboardInterrupt) or interrupt_in_chain(e) is not None:
            fail_interrupted_trials(study, ctx.objective.trials_run[-1:], created)  # this process's
        raise
    finally:
        if bar is not None:
            bar.close()
    return {"trials_run": list(ctx.objective.trials_run), "seconds": time.perf_counter() - t0,
            "target": n_target}


def _set_postfix(bar, study) -> None:
    b = best_feasible(study)
    c = trial_counts(study)
    parts = []
    if b is not None:
        from tuner.protocol import trial_value
        parts.append(f"best mAA10={trial_value(b):.4f} (#{b.number})")
    if c["pruned"]:
        parts.append(f"pruned={c['pruned']}")
    if c["infeasible"]:
        parts.append(f"infeasible={c['infeasible']}")
    bar.set_postfix_str(", ".join(parts))


def tune(s: TuneSettings) -> dict:
    """The whole protocol: study (create or resume) -> trials -> freeze -> test. Returns a JSON-able
    dict: study, storage (masked), counts, frozen settings, test results (None if skipped)."""
    from optuna.trial import TrialState

    from tuner.freeze import freeze, run_test_for_study
    from tuner.storage import storage_label
    ctx = setup_study(s)
    s.say(f"study {ctx.name} in {storage_label(s.storage, s.studies_dir)} "
          f"({'created' if ctx.created else 'resumed'}; sampler {s.sampler}, target "
          f"{s.n_trials or ('the grid' if s.sampler == 'grid' else DEFAULT_TRIALS)} trials)")
    if ctx.objective.pareto:
        s.say("objective pareto: maximize mAA(10°), minimize median estimator seconds per pair; no pruning "
              "(Optuna prunes single-objective studies only); frozen: the best trial within B on the front")
    run = optimize(ctx, s)
    out = {"study": ctx.name, "storage": storage_label(s.storage, s.studies_dir), "worker": run,
           "counts": trial_counts(ctx.study), "timed": bool(getattr(ctx.objective.task, "timed", True)),
           "frozen": None, "frozen_path": None, "test": None, "warnings": []}
    if best_feasible(ctx.study) is None:
        raise ImtuneError(f"study {ctx.name!r}: no feasible completed trial yet (all over the "
                          f"{ctx.attrs['budget']['seconds_per_pair']} s budget, pruned or failed); run more trials")
    frozen, path = freeze(ctx.study, s.studies_dir, select=s.select)
    out["frozen"], out["frozen_path"] = frozen, str(path)
    from tuner.diagnostics import optimum_warnings  # on a bound, Gamma_max at the ceiling, every trial 0
    out["warnings"] = list(frozen["warnings"]) if "warnings" in frozen else optimum_warnings(ctx.study, frozen)
    for w in out["warnings"]:
        s.warn(f"{ctx.name}: {w}" if s.name_warnings else w)
    from tuner.storage import fail_stale_trials
    fail_stale_trials(ctx.study)
    others = [t for t in ctx.study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))]
    if not s.test:
        return out
    if others:
        s.say(f"{len(others)} trial(s) still running in other workers: skipping the test run "
              f"(the last worker runs it; or `tune test --study {ctx.name}`)")
        return out
    out["test"] = run_test_for_study(ctx.study, frozen, s.studies_dir, data_root=s.data_root,
                                     scenes=s.test_scenes, cache=ctx.cache, runs=s.test_runs,
                                     max_pairs=s.max_pairs, progress=s.progress, reuse=not s.retest, jobs=s.jobs,
                                     workers=s.workers, reference=s.reference, ci_resamples=s.ci_resamples,
                                     gt_dir=s.gt_dir)
    from tuner.freeze import earlier_test_line
    if earlier_test_line(out["test"]):
        s.warn(earlier_test_line(out["test"]))
    return out
