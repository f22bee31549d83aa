"""The protocol table: the parameters a study may search, where each lives in the pipeline configuration,
its type and valid range, and the one feasibility rule. A leaf module (it imports nothing from the tuner).

    from tuner.protocol import LEAVES, config_for, within_budget
    LEAVES["threshold"]          # Leaf(section="geometry", field="threshold", type="float", ...)
    conf = config_for(base, {"ratio": 0.85, "threshold": 0.5})
    searchable("multiview")      # ("ratio", "strategy"): what the task consumes (Task.uses)

Everything that needs the list derives from :data:`LEAVES`: search-space validation (``tuner.space``), the
trial -> configuration mapping (:func:`config_for`), what a task does not search (:func:`unused_by`), the
fixed part of a study (:func:`blank_searched`) and the frozen file's ``fixed`` section (:func:`fixed_values`).
Which tasks use a parameter is each task's own declaration (``Task.uses``, see ``pipeline.tasks.base``):
:func:`tasks_using` reads it from the task registry.

Feasibility (the paper's budget): a configuration is within the budget B when the task's budget statistic
(median estimator seconds per pair; ``Task.budget_seconds``) is <= B, or when the task times no estimator.
A trial records it as the Optuna constraint ``budget`` (statistic - B, > 0 = infeasible) and the user attribute
``feasible``; :func:`trial_within_budget` is what freeze, reports, plots and the dashboard notes all read.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from pipeline.config import MAX_ITERS, STRATEGIES, PipelineConfig
from pipeline.errors import ImtuneError

BUDGET_CONSTRAINT = "budget"


@dataclass(frozen=True)
class Leaf:
    """One searchable parameter: ``section`` and ``field`` of ``PipelineConfig`` it sets, its ``type``
    ("float", "int", "categorical"), valid range (``low`` / ``high``, ``low_open``: low excluded) or
    ``choices``, its ``unit``, and how tables print its name (``symbol``: LaTeX, ``label``: plain)."""
    name: str
    section: str
    field: str
    type: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    choices: tuple = ()
    unit: str = ""
    symbol: str = ""
    label: str = ""

    def check(self, value, where: str):
        """The validated value (strings from the command line converted); one-line ImtuneError otherwise."""
        try:
            if self.type == "categorical":
                value = str(value)
                if value not in self.choices:
                    raise ValueError(f"must be one of {', '.join(self.choices)}")
                return value
            if isinstance(value, bool):
                raise ValueError("is not a number")
            if isinstance(value, str):
                value = float(value)
            value = float(value)
            if not math.isfinite(value):
                raise ValueError("must be finite")
            if self.type == "int":
                if value != int(value):
                    raise ValueError("must be an integer")
                value = int(value)
            lo_ok = self.low is None or (value > self.low if self.low_open else value >= self.low)
            hi_ok = self.high is None or value <= self.high
            if not (lo_ok and hi_ok):
                if self.type == "int" and not lo_ok and not self.low_open:
                    raise ValueError(f"must be an integer >= {self.low:g}")
                if self.type == "int" and not hi_ok:
                    raise ValueError(f"must be at most {int(self.high)}" + (f" {self.unit}" if self.unit else ""))
                raise ValueError(f"must be in {self.range_text()}")
            return value
        except (TypeError, ValueError) as e:
            msg = str(e) if str(e).startswith(("must", "is not")) else "is not a valid value"
            raise ImtuneError(f"{where}: {value!r} {msg}") from None

    def range_text(self) -> str:
        if self.type == "categorical":
            return "{" + ", ".join(self.choices) + "}"
        lo = "(" if self.low_open else "["
        hi = (f"{int(self.high)}]" if self.type == "int" else f"{self.high:g}]") if self.high is not None else "inf)"
        return f"{lo}{self.low if self.low is None else format(self.low, 'g')}, {hi}" + (f" {self.unit}" if self.unit else "")


LEAVES: dict[str, Leaf] = {
    "ratio": Leaf("ratio", "matching", "ratio", "float", 0.0, 1.0, low_open=True, symbol="$r$", label="r",
                  unit=""),
    "strategy": Leaf("strategy", "matching", "strategy", "categorical", choices=STRATEGIES, symbol="strategy",
                     label="strategy"),
    "threshold": Leaf("threshold", "geometry", "threshold", "float", 0.0, None, low_open=True, unit="px",
                      symbol=r"$\eta$", label="eta"),
    # Gamma up to what the estimators take (pipeline.config.MAX_ITERS; a larger value was clamped to it silently)
    "max_iters": Leaf("max_iters", "geometry", "max_iters", "int", 1, MAX_ITERS, unit="iterations",
                      symbol=r"$\Gamma$", label="Gamma"),
    # a learned matcher's (LightGlue's) match-confidence threshold: r's place when --matcher lightglue
    "min_confidence": Leaf("min_confidence", "matching", "min_confidence", "float", 0.0, 1.0, symbol="$c$",
                           label="c", unit=""),
    # the reconstruction task's mapper options that decide registration (pipeline.config.MapperConfig)
    "min_inliers": Leaf("min_inliers", "mapper", "min_inliers", "int", 5, 1000, unit="inliers",
                        symbol=r"$n_{\min}$", label="min inliers"),
    "min_model_size": Leaf("min_model_size", "mapper", "min_model_size", "int", 2, 1000, unit="images",
                           symbol=r"$m_{\min}$", label="min model size"),
    # COLMAP's incremental-mapper options entrants hand-tune, and the global mapper's view-graph thresholds
    "max_num_models": Leaf("max_num_models", "mapper", "max_num_models", "int", 1, 1000, unit="models",
                           symbol="max models", label="max models"),
    "init_min_num_inliers": Leaf("init_min_num_inliers", "mapper", "init_min_num_inliers", "int", 1, 10000,
                                 unit="inliers", symbol="init inliers", label="init inliers"),
    "abs_pose_min_num_inliers": Leaf("abs_pose_min_num_inliers", "mapper", "abs_pose_min_num_inliers", "int", 1,
                                     10000, unit="inliers", symbol="abs-pose inliers", label="abs-pose inliers"),
    "abs_pose_max_error": Leaf("abs_pose_max_error", "mapper", "abs_pose_max_error", "float", 0.0, None,
                               low_open=True, unit="px", symbol="abs-pose error", label="abs-pose error"),
    "filter_max_reproj_error": Leaf("filter_max_reproj_error", "mapper", "filter_max_reproj_error", "float", 0.0,
                                    None, low_open=True, unit="px", symbol="filter error", label="filter error"),
    "global_max_rotation_error": Leaf("global_max_rotation_error", "mapper", "global_max_rotation_error", "float",
                                      0.0, 180.0, low_open=True, unit="deg", symbol="GA rotation error",
                                      label="GA rotation error"),
    "global_max_angular_error": Leaf("global_max_angular_error", "mapper", "global_max_angular_error", "float", 0.0,
                                     180.0, low_open=True, unit="deg", symbol="GA angular error",
                                     label="GA angular error"),
}
PARAMS: tuple[str, ...] = tuple(LEAVES)
TYPES: dict[str, str] = {k: v.type for k, v in LEAVES.items()}


def leaf(name: str, where: str = "parameter") -> Leaf:
    if name not in LEAVES:
        raise ImtuneError(f"{where} {name!r}: unknown parameter (expected {', '.join(PARAMS)})")
    return LEAVES[name]


def tasks_using(name: str) -> list[str]:
    """The registered tasks whose ``uses`` lists the parameter ``name``."""
    from pipeline.tasks import TASKS
    return [t for t in TASKS.names() if name in TASKS.get(t).uses]


#: the parameters only the k-NN matchers use (the ratio test and its strategy), and those only a learned matcher
#: uses (its confidence threshold takes r's place): which set applies follows the configuration's matcher
KNN_ONLY: tuple[str, ...] = ("ratio", "strategy")
LEARNED_ONLY: tuple[str, ...] = ("min_confidence",)


def _learned(conf) -> bool:
    """``conf`` (a PipelineConfig, a MatchConfig or None = the k-NN matcher) matches with a learned matcher."""
    m = getattr(conf, "matching", conf)
    return bool(getattr(m, "learned", False))


def searchable(task, conf=None) -> tuple[str, ...]:
    """The parameters ``task`` (a Task or a registered name) consumes, in table order, with the matcher of ``conf``
    (a PipelineConfig or MatchConfig; None: the k-NN matcher): a learned matcher's threshold replaces r and the
    strategy."""
    if isinstance(task, str):
        from pipeline.tasks import TASKS
        task = TASKS.get(task)
    skip = KNN_ONLY if _learned(conf) else LEARNED_ONLY
    return tuple(p for p in PARAMS if p in task.uses and p not in skip)


def unused_by(task, conf=None) -> tuple[str, ...]:
    """The parameters ``task`` does not consume (with the matcher of ``conf``, as :func:`searchable`): a study of
    that task never searches or records them."""
    used = searchable(task, conf)
    return tuple(p for p in PARAMS if p not in used)


def config_for(base: PipelineConfig, values: dict, seed: int | None = None) -> PipelineConfig:
    """``base`` with the protocol parameters in ``values`` set (validated), and the estimator seed."""
    sections: dict[str, dict] = {}
    for name, v in values.items():
        lf = leaf(name)
        sections.setdefault(lf.section, {})[lf.field] = lf.check(v, name)
    if seed is not None:
        sections.setdefault("geometry", {})["seed"] = int(seed)
    return dataclasses.replace(base, **{sec: dataclasses.replace(getattr(base, sec), **kw)
                                        for sec, kw in sections.items()})


def value_of(conf: PipelineConfig, name: str):
    lf = leaf(name)
    return getattr(getattr(conf, lf.section), lf.field)


def blank_searched(conf: PipelineConfig, names) -> dict:
    """``conf.to_dict()`` with the parameters ``names`` and the estimator seed blanked (None): the fixed part
    of a study, which a resumed study must match."""
    d = conf.to_dict()
    for name in names:
        lf = leaf(name)
        d.setdefault(lf.section, {})[lf.field] = None  # mapper: absent from to_dict() at its defaults
    d["geometry"]["seed"] = None
    return d


def fixed_values(conf: PipelineConfig, searched, task) -> dict:
    """The protocol parameters ``task`` uses but the study did not search, with their value in ``conf``."""
    return {p: value_of(conf, p) for p in searchable(task, conf) if p not in searched}


def within_budget(seconds: float | None, budget: float | None) -> bool:
    """THE feasibility rule: the budget statistic (median estimator seconds per pair) <= B. A task that times
    no estimator (statistic None) or no budget is always within."""
    return seconds is None or budget is None or float(seconds) <= float(budget)


def trial_within_budget(trial) -> bool:
    """:func:`within_budget` as a study records it: every Optuna constraint <= 0 (``budget`` = statistic - B)
    and the user attribute ``feasible`` not False (set while the trial runs, before Optuna stores constraints)."""
    return all(v <= 0 for v in (trial.constraints or {}).values()) and trial.user_attrs.get("feasible") is not False


def trial_value(trial) -> float | None:
    """The trial's objective figure (mAA(10 deg)): its value, or in a multi-objective (``--objective pareto``)
    study the first of its values (the second is the median estimator seconds per pair). Optuna's
    ``FrozenTrial.value`` raises on a multi-objective trial: read this instead."""
    return float(trial.values[0]) if trial.values else None


def trial_seconds(trial) -> float:
    """The trial's budget statistic: the time objective of a pareto trial, else its user attribute (0 if unknown)."""
    if trial.values and len(trial.values) > 1:
        return float(trial.values[1])
    return float(trial.user_attrs.get("ransac_seconds_median", 0.0) or 0.0)


def best_feasible(study):
    """The COMPLETE trial with the highest value (:func:`trial_value`) among those within budget, the faster
    then the earlier on ties (None if none). In a pareto study this is the best trial within B read off the
    Pareto front (the fastest of equal mAA, so it is on the front)."""
    from optuna.trial import TrialState
    best = None
    for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        if trial_value(t) is None or not trial_within_budget(t):
            continue
        key = (trial_value(t), -trial_seconds(t), -t.number)
        if best is None or key > best[0]:
            best = (key, t)
    return best[1] if best else None


def no_feasible_reason(study, budget: float | None) -> str:
    """Why ``study`` has no feasible trial, for the one-line error: each state's count (complete over B with the
    lowest median seen, pruned with the first trial's reason, failed, still running), e.g. "2 trials: 1 over the
    0.5 s budget [fastest median 0.61 s per pair], 1 pruned [#1: likely over budget ...]"."""
    from optuna.trial import TrialState
    trials = study.get_trials(deepcopy=False)
    over = [t for t in trials if t.state == TrialState.COMPLETE]
    pruned = [t for t in trials if t.state == TrialState.PRUNED]
    failed = [t for t in trials if t.state == TrialState.FAIL]
    running = [t for t in trials if t.state in (TrialState.RUNNING, TrialState.WAITING)]
    parts = []
    if over:
        fastest = min(trial_seconds(t) for t in over)
        parts.append(f"{len(over)} over the {budget:g} s budget [fastest median {fastest:.3g} s per pair]"
                     if budget is not None else f"{len(over)} complete without a value")
    if pruned:
        why = pruned[0].user_attrs.get("pruned_reason") or "pruned by the pruner (below the median of earlier trials)"
        parts.append(f"{len(pruned)} pruned [#{pruned[0].number}: {why}]")
    if failed:
        parts.append(f"{len(failed)} failed [#{failed[0].number}{', ...' if len(failed) > 1 else ''}: an error "
                     "or a non-finite value; rerun without --quiet to see Optuna's warning]")
    if running:
        parts.append(f"{len(running)} still running or waiting")
    return f"{len(trials)} trial{'s' * (len(trials) != 1)}: " + ", ".join(parts or ["none run"])


def no_feasible_message(study, budget: float | None) -> str:
    """"study NAME: no feasible completed trial yet (:func:`no_feasible_reason`)": where `tune` stops, and the
    reason `tune findings` gives a study it cannot freeze."""
    return f"study {study.study_name!r}: no feasible completed trial yet ({no_feasible_reason(study, budget)})"
