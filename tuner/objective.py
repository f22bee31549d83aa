"""The objective: trial parameters -> PipelineConfig -> the study's task on the validation scenes -> the task's
objective figure (mAA(10 deg)), to maximise. One objective for every task (``pipeline.tasks``): the task says
what it consumes, what it reports and what a time budget bounds.

The task evaluates in steps (stereo: chunks of ``chunk_pairs`` pairs stratified over the scenes; multiview:
one scene at a time); after each step the running objective is reported as an intermediate value so the pruner
can stop a hopeless trial early. A trial is also stopped once more than half of all its pairs took more than B (a
proof: its median is over B whatever the rest take), and, to save time, once its running budget statistic exceeds
``prune_over_budget`` x B (a guess, like any pruner's: the pairs seen so far may be the slow ones; its
``pruned_reason`` says so). A task that stops an evaluation at a bound it was given
(:class:`pipeline.errors.EvaluationStopped`: the reconstruction task's ``--trial-timeout``) has its trial pruned
with that reason. A stopped trial is never frozen; its ``feasible`` and budget constraint are those of the
pairs it evaluated. Features and k-NN tables come from the cache (warmed once by
:meth:`ValidationSet.prepare`).

Each trial records, as user attributes, the task's figures (``Task.figures``: for stereo ``mAA5``, ``mAA10``,
``NF``, ``NM``, ``NI``, ``ransac_seconds_median`` / ``ransac_seconds_p90``, ``match_seconds``, ``accuracy``,
``covisibility``, ``scenes``, ``failed``; for multiview ``SR``, ``RC``, ``NL``, ``TL``, ``ATE``, ``by_size``, ...),
``failed_pairs`` (the units that failed), ``feasible`` (:func:`tuner.protocol.within_budget`) and ``timing``
(units, budget B, ``ransac_seconds_total`` and ``evaluate_seconds`` of the trial, for the overhead benchmark).
Feasibility is also an Optuna constraint (``trial.set_constraint("budget", statistic - B)``), so TPE treats
infeasible trials so; a task that times no estimator records no constraint.

``objectives=PARETO`` (``tune --objective pareto``, see :mod:`tuner.pareto`): the trial returns (mAA(10 deg),
median estimator seconds per pair) for a two-objective study (maximise, minimise). Such a trial reports no
intermediate values and is never pruned (Optuna's ``Trial.report`` / ``should_prune`` do not support
multi-objective studies; and a trial over B is a point of the front, not a waste), and records no budget
constraint (Optuna's Pareto front, ``study.best_trials``, would keep only trials within B); ``feasible``
still says whether it is within B.
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field

import numpy as np

from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError
from tuner.protocol import BUDGET_CONSTRAINT, config_for, within_budget

MAX_FAILED_LISTED = 50
#: ``--trial-timeout auto``: the bound is this multiple of the completed trials' median mapping seconds, and at
#: least AUTO_TIMEOUT_FLOOR seconds (a few seconds of mapping measured on a loaded machine must not cut good trials)
AUTO_TIMEOUT_FACTOR = 10.0
AUTO_TIMEOUT_FLOOR = 60.0
SINGLE = ("mAA10",)  # objectives: the task's objective figure, maximised
PARETO = ("mAA10", "seconds")  # ... and the median estimator seconds per pair, minimised


def data_fingerprint(scenes_units, task_options: dict | None = None) -> str:
    """SHA-1 (16 hex) of the evaluation data: per scene its name, every used image's file digest and
    ground-truth K, R, t, the evaluated pair list (with co-visibility), and the task's options."""
    from pipeline.cache import file_digest
    h = hashlib.sha1()
    h.update(json.dumps(task_options or {}, sort_keys=True, default=str).encode())
    for scene, pairs in sorted(scenes_units, key=lambda sp: sp[0].name):
        h.update(b"scene:" + scene.name.encode())
        names = sorted({p.i for p in pairs} | {p.j for p in pairs})
        for n in names:
            info = scene.images[n]
            h.update(n.encode())
            h.update(file_digest(info.path).encode())
            for a in (info.K, info.R, info.t):
                if a is not None:
                    h.update(np.round(np.asarray(a, np.float64), 9).tobytes())
        for p in pairs:
            h.update(p.key.encode())
            h.update(repr(None if p.covisibility is None else round(float(p.covisibility), 6)).encode())
            for a in (p.R, p.t, p.K_i, p.K_j):
                if a is not None:
                    h.update(np.round(np.asarray(a, np.float64), 9).tobytes())
    return h.hexdigest()[:16]


@dataclass
class ValidationSet:
    """The scenes a study evaluates, with the pairs its task evaluates in each (``scenes``: [(Scene, [Pair])]),
    and their fingerprint."""
    task: object
    scenes: list
    fingerprint: str = ""
    nf: dict = field(default_factory=dict)  # scene name -> features per image (set by prepare)

    @classmethod
    def from_scenes(cls, scene_objs, task) -> ValidationSet:
        sp = []
        for s in scene_objs:
            units = task.evaluation_units(s)
            if not units:
                raise ImtuneError(f"scene {s.name}: nothing for the {task.name} task to evaluate "
                                  f"(no pairs with the task's options {task.options() or ''})")
            sp.append((s, units))
        return cls(task=task, scenes=sp, fingerprint=data_fingerprint(sp, task.options()))

    @property
    def scene_objs(self) -> list:
        return [s for s, _ in self.scenes]

    @property
    def scene_names(self) -> list[str]:
        return [s.name for s, _ in self.scenes]

    @property
    def notes(self) -> list[str]:
        """The task's notes on these scenes (:meth:`pipeline.tasks.base.Task.scene_notes`)."""
        return self.task.notes(self.scene_objs)

    @property
    def n_pairs(self) -> int:
        return sum(len(p) for _, p in self.scenes)

    def prepare(self, conf: PipelineConfig, cache, progress: bool = False) -> None:
        """Warm the task's caches once (features, k-NN tables of every pair)."""
        self.nf = self.task.prepare(self.scene_objs, conf, cache, progress=progress)


def set_budget_constraint(trial, value: float) -> None:
    """``trial.set_constraint("budget", value)`` (> 0: infeasible). A retried trial (the parameters of
    a killed worker's trial, re-enqueued) inherits the dead trial's system attributes; its own
    measurement replaces the inherited value."""
    key = f"constraints:{BUDGET_CONSTRAINT}"
    if key in trial.storage.get_trial_system_attrs(trial._trial_id):
        trial.storage.set_trial_system_attr(trial._trial_id, key, float(value))
    else:
        trial.set_constraint(BUDGET_CONSTRAINT, float(value))


def failed_units(records: list[dict], several_scenes: bool) -> list[str]:
    """Labels of the failed units of a result (stereo pairs, multiview bags): ``[scene:]pair``."""
    out = []
    for r in records:
        bad = r.get("failure") is not None or not np.isfinite(r.get("err", 0.0))
        if not bad:
            continue
        unit = r.get("pair") or f"bag {r.get('bag_size')}-{r.get('bag')}"
        out.append(f"{r['scene']}:{unit}" if several_scenes else str(unit))
    return out


def auto_trial_timeout(study) -> float | None:
    """``--trial-timeout auto``: :data:`AUTO_TIMEOUT_FACTOR` x the median mapping seconds
    (``timing.mapping_seconds``) of the study's completed trials, at least :data:`AUTO_TIMEOUT_FLOOR`; None (no
    bound yet) until a trial has completed (the first is the task's defaults). Read again before every trial: one
    mapping timed on a loaded machine (31 s where the same setting took 2.3 s, seen in a replicated study) set the
    bound for a whole study when it was read from the defaults trial alone."""
    from optuna.trial import TrialState
    secs = [float(s) for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
            if isinstance(s := (t.user_attrs.get("timing") or {}).get("mapping_seconds"), (int, float))
            and np.isfinite(s)]
    if not secs:
        return None
    return max(AUTO_TIMEOUT_FLOOR, AUTO_TIMEOUT_FACTOR * float(np.median(secs)))


class Objective:
    """Callable for ``study.optimize``: one trial = one evaluation of the validation set by the study's task.

    task: a ``pipeline.tasks.Task``; base: the study's fixed pipeline configuration; space: the (resolved)
    search space; vs: the prepared validation set; cache: an H5Cache (shared by all trials of this process);
    budget: B in seconds per pair (median estimator CPU time; None = no budget); prune_over_budget: stop a trial
    early once its running budget statistic exceeds this multiple of B (0: never; a guess that saves time, not a
    proof: only more than half of all its pairs over B proves a trial over budget); objectives: :data:`SINGLE` (return the task's objective figure) or :data:`PARETO` (return it
    and the median estimator seconds per pair; a task that times no estimator cannot)."""

    def __init__(self, task, base: PipelineConfig, space, vs: ValidationSet, cache, budget: float | None = None,
                 prune_over_budget: float = 2.0, objectives: tuple = SINGLE):
        if tuple(objectives) not in (SINGLE, PARETO):
            raise ImtuneError(f"objectives {tuple(objectives)!r}: expected {SINGLE!r} or {PARETO!r}")
        if tuple(objectives) == PARETO and not task.timed:
            raise ImtuneError(f"task {task.name} times no estimator of imtune's: it cannot run a pareto study "
                              "(accuracy against estimator CPU time); use --objective mAA10")
        self.objectives = tuple(objectives)
        self.task = task
        self.base = base
        self.space = space
        self.vs = vs
        self.cache = cache
        self.budget = float(budget) if budget is not None else None
        self.prune_over_budget = prune_over_budget
        self.trials_run: list[int] = []
        self.sampler: str | None = None  # the --sampler of this worker (set by tuner.study.optimize), per trial
        self.auto_trial_timeout = False  # --trial-timeout auto (:func:`auto_trial_timeout`)

    def config(self, params: dict) -> PipelineConfig:
        """The pipeline configuration of one trial: the base with the fixed, then the searched values."""
        return config_for(self.base, {**self.space.fixed, **params})

    def _timing(self, n_units: int, ransac_total: float, t0: float) -> dict:
        if not self.task.timed:  # multiview: its units are bags, and no estimator of ours is timed against a budget
            return {"bags" if "bags" in self.task.summary_keys else "units": n_units,
                    "evaluate_seconds": time.perf_counter() - t0}
        return {"pairs": n_units, "budget": self.budget, "ransac_seconds_total": float(ransac_total),
                "evaluate_seconds": time.perf_counter() - t0}

    @property
    def pareto(self) -> bool:
        return self.objectives == PARETO

    def __call__(self, trial) -> float | tuple[float, float]:
        import optuna
        task = self.task
        t0 = time.perf_counter()
        params = self.space.suggest(trial)
        conf = self.config(params)
        self.trials_run.append(trial.number)
        if self.sampler:  # a resume or another worker may sample otherwise than the study's creator
            trial.set_user_attr("sampler", self.sampler)

        def on_step(step: int, n_steps: int, summary: dict) -> None:
            trial.report(float(summary[task.objective]), step)
            if step + 1 >= n_steps:
                return  # the last step: the trial is complete, never pruned after all the work is done
            sec = task.budget_seconds(summary)
            over = bool(self.prune_over_budget) and self.budget is not None and sec is not None \
                and sec > self.prune_over_budget * self.budget
            # a proof, not a guess: once more than half of ALL the trial's units (the task's ``units_total``) took
            # more than B (``budget_seconds_units``: the per-unit values of the budget statistic so far), the
            # trial's final median is > B whatever the remaining units take
            each, total = summary.get("budget_seconds_units"), summary.get("units_total")
            n_over = sum(1 for x in each if float(x) > self.budget) if each and total and self.budget is not None else 0
            proven = bool(total) and 2 * n_over > int(total)
            over = over or proven
            if over or trial.should_prune():
                n = int(summary.get("pairs", 0) or 0)
                if sec is not None and self.budget is not None:
                    set_budget_constraint(trial, sec - self.budget)
                    trial.set_user_attr("ransac_seconds_median", sec)
                trial.set_user_attr("pruned_at_pairs", n)
                trial.set_user_attr("feasible", within_budget(sec, self.budget))
                trial.set_user_attr("timing", self._timing(n, float(summary.get("ransac_seconds", 0.0)) * n, t0))
                if proven:
                    trial.set_user_attr("pruned_reason", f"over budget: {n_over} of its {int(total)} pairs already "
                                                         f"took more than {self.budget:g} s (median > B whatever "
                                                         "the rest take)")
                elif over:
                    trial.set_user_attr("pruned_reason", f"likely over budget: running median {sec:.3f} s > "
                                                         f"{self.prune_over_budget:g} x {self.budget:g} s after "
                                                         f"{n} of {int(total or 0) or '?'} pairs (stopped to save "
                                                         "time: a guess, not a proof)")
                raise optuna.TrialPruned()

        from pipeline.errors import EvaluationStopped
        if self.auto_trial_timeout and hasattr(task, "trial_timeout"):
            task.trial_timeout = auto_trial_timeout(trial.study)
        if getattr(task, "trial_timeout", None) is not None:
            trial.set_user_attr("trial_timeout", float(task.trial_timeout))
        try:
            res = task.evaluate(self.vs.scene_objs, conf, self.cache, on_step=None if self.pareto else on_step)
        except EvaluationStopped as e:  # a bound the task was given (reconstruction: --trial-timeout): never frozen
            trial.set_user_attr("pruned_reason", str(e))
            trial.set_user_attr("timing", self._timing(0, 0.0, t0))
            raise optuna.TrialPruned(str(e)) from None
        attrs = task.figures(res)
        sec = task.budget_seconds(res.summary)
        if sec is not None and self.budget is not None and not self.pareto:
            set_budget_constraint(trial, sec - self.budget)
        failed = failed_units(res.records, len(self.vs.scenes) > 1)
        attrs["failed_pairs"] = failed[:MAX_FAILED_LISTED]
        attrs["feasible"] = within_budget(sec, self.budget)
        attrs["timing"] = self._timing(len(res.records), sum(r.get("ransac_seconds", 0.0) for r in res.records), t0)
        attrs["timing"].update({f"{k}_seconds": float(v) for k, v in res.seconds.items()})
        for k, v in attrs.items():
            trial.set_user_attr(k, v)
        if self.pareto:
            return float(res.summary[task.objective]), float(sec)
        return float(res.summary[task.objective])
