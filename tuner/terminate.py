"""`--terminate auto`: stop a study when more trials cannot beat the incumbent by more than its validation interval.

Optuna's :class:`optuna.terminator.Terminator` (Makarova et al., "Automatic termination for hyperparameter
optimization", AutoML 2022): after ``min_trials`` finished trials it fits a Gaussian process to the completed trials
(:class:`optuna.terminator.RegretBoundEvaluator`, Optuna's own ``optuna._gp`` on torch; no botorch) and stops when
the upper bound of the regret -- how much better than the incumbent the best point could still be -- falls below the
statistical error of the incumbent. The error here is the incumbent's own validation interval
(:class:`IncumbentIntervalError`: the half-width of the best completed trial's 95% interval of the objective, which
every trial records as ``<objective>_ci``): a trial that could only win by less than that margin would be a tie
on the validation pairs. Single-objective studies only (a pareto study has no incumbent).

    from tuner.terminate import make_terminator
    terminator = make_terminator("auto", n_target=50, objective="mAA10")   # None for "off"
    terminator.should_terminate(study)
"""
from __future__ import annotations

import math
import warnings

from optuna.study import StudyDirection
from optuna.terminator import BaseErrorEvaluator, RegretBoundEvaluator, Terminator
from optuna.trial import FrozenTrial, TrialState

from pipeline.errors import ImtuneError

MODES = ("off", "auto")
MIN_TRIALS = 20  # Optuna's default: the GP needs trials to model the surface


class IncumbentIntervalError(BaseErrorEvaluator):
    """The half-width of the best completed trial's 95% validation interval (``<objective>_ci``); 0 where no
    completed trial has one (then the terminator never stops: no margin is known)."""

    def __init__(self, objective: str = "mAA10") -> None:
        self.objective = objective

    def evaluate(self, trials: list[FrozenTrial], study_direction: StudyDirection) -> float:
        done = [t for t in trials if t.state == TrialState.COMPLETE and t.value is not None]
        if not done:
            return 0.0
        pick = max if study_direction == StudyDirection.MAXIMIZE else min
        best = pick(done, key=lambda t: t.value)
        ci = (best.user_attrs or {}).get(f"{self.objective}_ci")
        if not ci or len(ci) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in ci):
            return 0.0
        return float(ci[1] - ci[0]) / 2.0


def min_trials(n_target: int) -> int:
    """Trials before termination is considered: :data:`MIN_TRIALS`, at most half the study's target (at least 5)."""
    return max(5, min(MIN_TRIALS, int(n_target) // 2))


def make_terminator(mode: str, n_target: int, objective: str = "mAA10", seed: int | None = None) -> Terminator | None:
    """The study's terminator for ``--terminate mode`` (None for "off"); one-line ImtuneError for an unknown mode or
    a pareto study."""
    if mode not in MODES:
        raise ImtuneError(f"--terminate {mode!r}: choose {' or '.join(MODES)}")
    if mode == "off":
        return None
    if objective == "pareto":
        raise ImtuneError("--terminate auto stops a single-objective study (its incumbent's interval); a pareto study "
                          "has no incumbent: drop --terminate or use --objective mAA10")
    k = min_trials(n_target)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Terminator(improvement_evaluator=RegretBoundEvaluator(min_n_trials=k, seed=seed),
                          error_evaluator=IncumbentIntervalError(objective), min_n_trials=k)


TERMINATED_ATTR = "terminated"


def should_terminate(terminator: Terminator, study, say=None) -> bool:
    """``terminator.should_terminate(study)``; when it stops, the study records why in its user attribute
    ``terminated`` ({trials, reason}) and ``say`` is told. A study that recorded it stays stopped (a rerun resumes
    nothing)."""
    if study.user_attrs.get(TERMINATED_ATTR):
        return True
    with warnings.catch_warnings():  # experimental / deprecated in Optuna 4.9+ (removed in 6.0): said in the notes
        warnings.simplefilter("ignore")
        stop = bool(terminator.should_terminate(study))
    if stop:
        n = len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED)))
        reason = ("regret bound below the incumbent's validation interval half-width (optuna.terminator, "
                  "RegretBoundEvaluator)")
        study.set_user_attr(TERMINATED_ATTR, {"trials": n, "reason": reason})
        if say is not None:
            say(f"--terminate auto: stopped after {n} trials: more trials cannot beat the incumbent by more than its "
                "validation interval")
    return stop


__all__ = ["MODES", "TERMINATED_ATTR", "IncumbentIntervalError", "make_terminator", "min_trials", "should_terminate"]
