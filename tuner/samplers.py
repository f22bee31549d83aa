"""Optuna's samplers and pruners as the `tune` command names them (``--sampler``, ``--pruner``), and Optuna's
own log quietened to the CLI's one-line errors."""
from __future__ import annotations

import warnings

from pipeline.errors import ImtuneError

SAMPLERS = ("tpe", "random", "cmaes", "grid")
PRUNERS = ("median", "sha", "hyperband", "none")
DEFAULT_PRUNER = "hyperband"  # the fastest to the same frozen optimum in benchmarks/study_wall_time.py (docs/tuning.md)


def quiet_optuna(verbose: bool = False):
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
