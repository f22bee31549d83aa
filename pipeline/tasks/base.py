"""The seam between the pipeline and whatever drives it (the tuner, `tune evaluate`, figures): one ``Task``.

A task turns one fixed pipeline configuration and some scenes into figures::

    from pipeline.tasks import get_task            # TASKS.get(name)(**options)
    task = get_task("stereo", min_covisibility=0.1)
    res = task.evaluate(scenes, conf, cache)           # TaskResult
    res.summary["mAA10"], res.scenes["fountain-P11"], res.records[0]

What a task declares (class attributes, read by the tuner, which has no task-specific branches):

- ``name``: its registry name;
- ``uses``: the searched parameters it consumes (names of ``tuner.protocol``'s table: ``ratio``,
  ``strategy``, ``threshold``, ``max_iters``); a study never searches a parameter its task does not use;
- ``summary_keys``: the figures it reports; repeated runs are aggregated over these (mean, std);
- ``std_keys``: the figures whose run-to-run standard deviation is reported (the sample standard deviation, ddof 1:
  :data:`STD_DDOF`);
- ``columns``: the columns of its readable per-scene table;
- ``objective``: the figure a study maximises (mAA(10 deg));
- ``space_file``: the search-space file used by default (None: the estimator family's file);
- ``records_key``: the JSON key under which ``TaskResult.to_dict(with_records=True)`` lists the records;
- ``note``: one line printed above its tables (units, what the figures mean);
- ``timed``: whether it times an estimator of ours per pair, so that a time budget applies
  (:meth:`Task.budget_seconds`);
- ``search_seconds``: the wall seconds of trials a study of this task searches at most unless told (stereo: 300, the
  main job's bound: its trials cost at most B a pair, so the trial count, not the task, sets their number); None
  where one evaluation takes minutes (multiview, reconstruction) and a bound would cut a study to a few trials;
- ``unit`` / ``unit_one``: what one record is, plural and singular ("pairs" / "pair", "bags" / "bag"); the summary
  counts them under ``unit``, intervals and paired tests resample them;
- ``units_label``: how `tune compare` names what every source is evaluated on ("stereo pairs");
- ``verifier``: what verifies the matches in place of the configuration's estimator (multiview: "COLMAP"), or None
  (our estimator, whose eta and Gamma then play their part); tables head its column with it;
- ``why_untimed``: why an untimed task ignores the stereo options (--max-pairs, --test-budget), for the warnings;
- ``test_figures``: what the figures of its test table are, for the caption;
- ``reapplied``: the :meth:`options` a comparison on this task takes from the studies compared (their recorded
  options, which their test runs used), unless typed;
- ``needs_points``: whether it needs a scene's built 3D points (`tune data build-gt`) to choose its units;
- ``sweep``: whether `tune findings` sweeps its space's grid rather than sampling it (each trial is expensive);
- ``in_both``: whether ``--task both`` runs it (the reconstruction task needs IMC datasets: only by name or ``all``).

How its numbers are resampled is declared by :meth:`Task.intervals` (95% intervals) and :meth:`Task.paired` (a
paired comparison of two configurations on the same units); which constructor options it takes by
:meth:`Task.takes`.

How the pieces are measured (the paper's protocol) lives in the concrete tasks beside this module
(``stereo``, ``multiview``); how repeated runs aggregate is :meth:`Task.aggregate`. ``on_step`` is how a
caller watches a long evaluation (the tuner feeds a pruner through it): it is called after each step with
the summary of the records so far and may raise to stop; the task knows nothing of Optuna.

A new task is one module with a ``Task`` subclass and one registry line::

    @TASKS.register("mytask", "what it measures")
    class MyTask(Task): ...
"""
from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar, TypeVar

import numpy as np

from pipeline.config import PipelineConfig
from pipeline.metrics.uncertainty import STD_DDOF
from pipeline.registry import Registry

TASKS = Registry("task")

#: a Task subclass: :meth:`Task.from_options` builds the class it is called on
T = TypeVar("T", bound="Task")

#: on_step(step, n_steps, summary_so_far): called after each evaluation step; may raise to stop early.
OnStep = Callable[[int, int, dict], None]


@dataclass
class TaskResult:
    """What a task's evaluation gives: ``summary`` (overall figures: the mean over scenes), ``scenes``
    (per-scene summaries), ``records`` (one JSON-able dict per evaluated unit: a stereo pair, a multiview
    bag), ``pairs`` (stereo with ``keep_pairs``: (scene, pair key) -> :class:`pipeline.tasks.stereo.PairResult`,
    for figures that must not recompute anything) and ``seconds`` (wall time of the phases)."""
    summary: dict
    scenes: dict[str, dict]
    records: list[dict] = field(default_factory=list)
    pairs: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    records_key: str = "records"

    def to_dict(self, with_records: bool = False) -> dict:
        """JSON-able: the summary's keys, ``scenes``, ``wall_seconds`` and (optionally) the records."""
        d = dict(self.summary)
        d["scenes"] = self.scenes
        if self.seconds:
            d["wall_seconds"] = self.seconds
        if with_records:
            d[self.records_key] = self.records
        return d


class Task(abc.ABC):
    """Base class of the tasks (see the module docstring). Options are keyword arguments of the
    constructor, stored as attributes; :meth:`options` gives them back JSON-able (they are what a study
    records and what a resumed study must match)."""

    name: ClassVar[str] = ""
    uses: tuple[str, ...] = ()  # an instance may narrow it and space_file (the reconstruction task: by its mapper)
    summary_keys: ClassVar[tuple[str, ...]] = ("mAA5", "mAA10")
    std_keys: ClassVar[tuple[str, ...]] = ("mAA5", "mAA10")
    columns: ClassVar[tuple[str, ...]] = ("mAA5", "mAA10")
    objective: ClassVar[str] = "mAA10"
    space_file: str | None = None
    records_key: ClassVar[str] = "records"
    note: ClassVar[str] = ""  # one line printed above the task's tables (units, what the figures mean)
    timed: ClassVar[bool] = False  # True: it times an estimator of ours per pair (a time budget applies)
    search_seconds: ClassVar[float | None] = None  # wall seconds a study's search runs at most unless told; None: no bound
    unit: ClassVar[str] = "pairs"
    unit_one: ClassVar[str] = "pair"
    units_label: ClassVar[str] = ""  # "" -> "<name> <unit>"
    verifier: ClassVar[str | None] = None
    why_untimed: ClassVar[str] = "it times no estimator of ours"
    test_figures: ClassVar[str] = "mAA(10°) [95% interval over the evaluated units and runs]"
    reapplied: ClassVar[tuple[str, ...]] = ()
    needs_points: ClassVar[bool] = False
    sweep: ClassVar[bool] = False
    in_both: ClassVar[bool] = True  # `--task both` runs it (False: it needs data of its own kind, e.g. IMC datasets)
    #: pipeline options (command-line dests: feature, threshold, ...) this task runs with where the command line does
    #: not set them (the command-line defaults are the stereo protocol's)
    pipeline_defaults: ClassVar[dict] = {}
    #: what ``--reference`` means by default: "paper" (the paper defaults) or a named reference pipeline of
    #: :attr:`references` ("colmap": :meth:`reference_task`)
    default_reference: ClassVar[str] = "paper"
    #: a new study's first trial is the task's defaults (the searched parameters at their values in the study's base
    #: configuration), so that a study freezes something worse on validation than the defaults only by their noise
    start_at_defaults: ClassVar[bool] = False
    #: ``tune --confirm``'s default: how many of the best trials are re-evaluated at more seeds before freezing
    #: (tuner.confirm; 0: none). A task whose runs are as noisy as its good settings are apart sets it
    confirm_default: ClassVar[int] = 0
    #: the named reference pipelines :meth:`reference_task` runs (the reconstruction task: "colmap",
    #: "imc2025-baseline"); a task that overrides :meth:`reference_task` without naming them has "colmap"
    references: ClassVar[tuple[str, ...]] = ()

    def reference_task(self, kind: str = "colmap") -> Task | None:
        """The task that runs the named reference ``kind`` (e.g. "colmap": COLMAP's own pipeline on the same data),
        or None when this task has none."""
        return None

    @classmethod
    def compare_runs(cls, ref_runs: list[dict], runs: list[dict]) -> dict | None:
        """Frozen - reference from the runs' figures (``figures`` dicts, run k of each side with the k-th seed) when
        the records carry no per-unit errors for a paired bootstrap; None: no such comparison (the default)."""
        return None

    @classmethod
    def takes(cls, option: str) -> bool:
        """Whether the constructor takes keyword ``option`` (``workers``, ``max_pairs``, ...): a command-line option
        that sets it applies to this task."""
        import inspect
        return option in inspect.signature(cls.__init__).parameters

    @classmethod
    def units_text(cls) -> str:
        """What the task's numbers are over, for a table's first line: ``units_label`` or "<name> <unit>"."""
        return cls.units_label or f"{cls.name} {cls.unit}"

    @classmethod
    def intervals(cls, records: list[dict], **kw) -> dict:
        """95% intervals of mAA(5), mAA(10) from the records (``mAA5_ci``, ``mAA10_ci``, per scene under
        ``scenes``): :func:`pipeline.metrics.uncertainty.maa_intervals`, units resampled within each scene.
        ``kw``: n_resamples, seed, level, scenes."""
        from pipeline.metrics.uncertainty import maa_intervals
        return maa_intervals(records, **kw)

    @classmethod
    def paired(cls, records_a: list[dict], records_b: list[dict], **kw) -> dict:
        """Configuration B against A on the same units: :func:`pipeline.metrics.uncertainty.paired_bootstrap`
        (difference of mAA(tau), its CI, a sign-flip p, overall and per scene). ``kw``: tau, n_resamples, seed,
        level."""
        from pipeline.metrics.uncertainty import paired_bootstrap
        return paired_bootstrap(records_a, records_b, **kw)

    @abc.abstractmethod
    def evaluate(self, scenes: list, conf: PipelineConfig, cache=None, on_step: OnStep | None = None) -> TaskResult:
        """Evaluate one configuration over the scenes (see the concrete classes for the protocol)."""

    def options(self) -> dict:
        """The task's settings that change its numbers, JSON-able (recorded by studies and test runs);
        :meth:`from_options` rebuilds the task from them."""
        return {}

    @classmethod
    def from_options(cls: type[T], options: dict | None, **extra) -> T:
        """The task from :meth:`options`' dict (a study's, a frozen file's) and run-time ``extra`` keyword options
        (progress, workers, ...; those the constructor does not take and None values are ignored)."""
        import inspect
        accepted = inspect.signature(cls.__init__).parameters
        # None is dropped from each side before they are merged: an unset run-time option (tune test's --max-pairs
        # None) must not wipe the recorded one (the study's max_pairs 8: every test pair was tested)
        kw = {k: v for k, v in (options or {}).items() if k in accepted and v is not None}
        kw.update({k: v for k, v in extra.items() if k in accepted and v is not None})
        return cls(**kw)

    def evaluation_units(self, scene) -> list:
        """The pairs of ``scene`` this task's numbers depend on (the data fingerprint hashes them)."""
        return list(scene.pairs)

    def check_scene(self, scene) -> str | None:
        """Why this task cannot evaluate ``scene`` (nothing to evaluate, missing ground truth), or None. Reads
        the scene's metadata only (callers check test scenes before any tuning)."""
        units = self.evaluation_units(scene)
        if not units:
            return f"nothing for the {self.name} task to evaluate (no pairs with {self.options() or 'its options'})"
        why = scene.missing_ground_truth(units)
        if why:
            return f"no ground truth to evaluate against ({why})"
        return scene.zero_baseline(units)

    def scene_notes(self, scene) -> list[str]:
        """What a user must know about how this task evaluates ``scene`` where it cannot follow its options as
        given (one line each; the callers print them as warnings and keep them in the results). Reads the scene's
        metadata only. Default: none."""
        return []

    def notes(self, scenes: list) -> list[str]:
        """:meth:`scene_notes` of every scene, in order."""
        return [n for s in scenes for n in self.scene_notes(s)]

    def prepare(self, scenes: list, conf: PipelineConfig, cache, progress: bool = False) -> dict[str, float]:
        """Warm the caches the evaluation reads (features, k-NN tables) once; returns features per image
        (NF) per scene. Default: nothing to warm."""
        return {}

    def for_run(self, conf: PipelineConfig, k: int) -> tuple[Task, PipelineConfig]:
        """The task and configuration of the ``k``-th repeated run (k = 0, 1, ...): the paper repeats test
        runs with different random seeds. Default: the estimator seed ``seed + k`` (``pipeline.config.run_seed``)."""
        import dataclasses

        from pipeline.config import run_seed
        g = conf.geometry
        return self, dataclasses.replace(conf, geometry=dataclasses.replace(g, seed=run_seed(g.seed, k)))

    def budget_seconds(self, summary: dict) -> float | None:
        """The statistic a time budget bounds (median estimator seconds per pair), or None when the task
        has no estimator of ours to time (then every configuration is within any budget)."""
        return None

    def figures(self, result: TaskResult) -> dict:
        """The JSON-able figures of a result that a study keeps per trial and a frozen file as its
        validation figures: the summary keys and, per scene, the same."""
        def part(s):
            return {k: s.get(k) for k in self.summary_keys}
        out = part(result.summary)
        out["scenes"] = {name: part(s) for name, s in result.scenes.items()}
        return out

    def aggregate(self, runs: list[dict]) -> tuple[dict, dict]:
        """Mean and standard deviation over repeated runs (``figures`` dicts) of every summary key, overall
        and per scene (numbers and equal-length lists are averaged elementwise; None values are skipped).

        The standard deviation is the *sample* one (ddof 1, :data:`STD_DDOF`): the runs are a sample of the
        estimator's seeds, and "mean +- std over 3 runs" estimates their spread; the population form (ddof 0)
        reads sqrt(2/3) = 0.82 of it at 3 runs. One run: 0 (no spread measured; the callers say "one run")."""
        def stats(parts, keys):
            mean, std = {}, {}
            for k in keys:
                vals = [p[k] for p in parts if p.get(k) is not None]
                if vals:
                    a = np.asarray(vals, float)
                    mean[k] = np.mean(a, axis=0).tolist()
                    sd = np.std(a, axis=0, ddof=STD_DDOF) if len(vals) > STD_DDOF else np.zeros_like(a[0])
                    std[k] = sd.tolist()
            return mean, std
        mean, std = stats(runs, self.summary_keys)
        mean["scenes"] = {}
        for name in (runs[0].get("scenes") or {}) if runs else {}:
            per = [r["scenes"][name] for r in runs if name in (r.get("scenes") or {})]
            mean["scenes"][name] = stats(per, self.summary_keys)[0]
        return mean, {k: std[k] for k in self.std_keys if k in std}

