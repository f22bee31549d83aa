"""Sampler seeds per worker: the same ``--seed`` in several workers, or in a resumed study, must not
replay the same trial parameters.

A sampler seeded with the study's ``--seed`` draws the same sequence in every process, so two workers
started with the same command (and a worker resuming an interrupted study) evaluate the same
parameters again. Here each worker's sampler is seeded with ``derive_seed(seed, n)`` where ``n`` is the
number of the first trial the worker is given. Trial numbers are assigned atomically by the storage, so
``n`` differs between concurrent workers and between a run and its resume, while a single worker on a
new study (first trial 0) stays reproducible: the same command on a fresh storage gives the same trials.
The derived seed is recorded in every trial's user attribute ``sampler_seed``.

Only Optuna's public sampler interface is used: the wrapped sampler is built at the worker's first
``before_trial`` (the first moment the trial number is known) and every call is delegated to it.

    from tuner.seeding import worker_seeded
    sampler = worker_seeded(lambda seed: optuna.samplers.TPESampler(seed=seed), seed=0)
"""
from __future__ import annotations

import hashlib
from collections.abc import Callable
from typing import Any

from optuna.samplers import BaseSampler

SEED_ATTR = "sampler_seed"


def derive_seed(seed: int, first_trial: int) -> int:
    """A 32-bit seed (numpy's range) from the study seed and the worker's first trial number."""
    digest = hashlib.sha256(f"imtune-sampler:{int(seed)}:{int(first_trial)}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


class WorkerSeededSampler(BaseSampler):
    """Delegates to ``factory(derive_seed(seed, first trial number of this worker))``."""

    def __init__(self, factory: Callable[[int], BaseSampler], seed: int) -> None:
        self._factory = factory
        self._seed = int(seed)
        self._inner: BaseSampler | None = None
        self.worker_seed: int | None = None

    def _sampler(self) -> BaseSampler:
        if self._inner is None:  # a call before any trial (not done by Optuna today): seed from trial 0
            self.worker_seed = derive_seed(self._seed, 0)
            self._inner = self._factory(self.worker_seed)
        return self._inner

    def __str__(self) -> str:
        return f"WorkerSeeded({self._inner if self._inner is not None else '?'})"

    def before_trial(self, study, trial) -> None:
        if self._inner is None:
            self.worker_seed = derive_seed(self._seed, trial.number)
            self._inner = self._factory(self.worker_seed)
        study._storage.set_trial_user_attr(trial._trial_id, SEED_ATTR, int(self.worker_seed))
        self._inner.before_trial(study, trial)

    def infer_relative_search_space(self, study, trial) -> dict[str, Any]:
        return self._sampler().infer_relative_search_space(study, trial)

    def sample_relative(self, study, trial, search_space) -> dict[str, Any]:
        return self._sampler().sample_relative(study, trial, search_space)

    def sample_independent(self, study, trial, param_name, param_distribution) -> Any:
        return self._sampler().sample_independent(study, trial, param_name, param_distribution)

    def after_trial(self, study, trial, state, values) -> None:
        self._sampler().after_trial(study, trial, state, values)

    def reseed_rng(self) -> None:
        self._sampler().reseed_rng()


def worker_seeded(factory: Callable[[int | None], BaseSampler], seed: int | None) -> BaseSampler:
    """``factory(None)`` when no seed is given (every process draws its own), else a
    :class:`WorkerSeededSampler`."""
    if seed is None:
        return factory(None)
    return WorkerSeededSampler(factory, int(seed))


__all__ = ["SEED_ATTR", "WorkerSeededSampler", "derive_seed", "worker_seeded"]
