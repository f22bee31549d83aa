"""Tasks: what a configuration is evaluated by (the seam the tuner drives; see ``base``).

    from pipeline.tasks import TASKS, get_task
    task = get_task("stereo", min_covisibility=0.1)     # or "multiview"
    result = task.evaluate(scenes, conf, cache)

Registered here: ``stereo`` (two-view pose from F, the paper's stereo task), ``multiview`` (COLMAP
reconstructions of bags of images) and ``reconstruction`` (IMC 2024/2025 datasets reconstructed whole and clustered). ``TASKS.names()`` lists them; docs/extending.md shows how to add one.
"""
from __future__ import annotations

# Importing registers the tasks: the import order is the listing order, so isort leaves it.
# isort: off
from pipeline.tasks.base import TASKS, Task, TaskResult
from pipeline.tasks import stereo, multiview, reconstruction  # noqa: F401,E402
from pipeline.features import load_plugins  # noqa: E402  (after the tasks: a plug-in may register one)
# isort: on

load_plugins()  # $IMTUNE_PLUGINS modules may register tasks too (idempotent)

__all__ = ["TASKS", "Task", "TaskResult", "get_task", "is_timed", "make_task", "task_class", "task_list", "task_names"]


def get_task(name: str, **options) -> Task:
    """The task registered as ``name``, built with its options (one-line ImtuneError for an unknown name)."""
    return TASKS.get(name)(**options)


def task_class(name: str | None) -> type[Task]:
    """The class registered as ``name`` (what it declares: ``unit``, ``verifier``, ...), or :class:`Task` itself (the
    defaults: units are pairs, our estimator) for a name not registered here (a study of a plug-in task not loaded)."""
    return TASKS.get(name) if name is not None and name in TASKS else Task


def task_names() -> list[str]:
    return TASKS.names()


def make_task(name: str, **options) -> Task:
    """The task ``name`` built from a pool of options: each task takes the ones its constructor accepts (so a
    caller such as `tune evaluate` can offer every task's options without knowing which task uses which)."""
    return TASKS.get(name).from_options(None, **options)


def is_timed(name: str) -> bool:
    """Task ``name`` times an estimator of ours per pair (stereo, or a plug-in built on it): the estimator and budget
    options apply to it. False for an untimed task (multiview: COLMAP's own RANSAC) and an unknown name."""
    return name in TASKS and TASKS.get(name).timed


def task_list(spec: str) -> list[str]:
    """Task names from a spec: one name, a comma-separated list, ``both`` (every task that evaluates the paper's
    scenes: stereo, multiview and plug-in tasks; not ``reconstruction``, which needs IMC datasets: ``Task.in_both``)
    or ``all`` (every task)."""
    if spec == "all":
        return TASKS.names()
    if spec == "both":
        return [n for n in TASKS.names() if TASKS.get(n).in_both]
    names = [s.strip() for s in str(spec).split(",") if s.strip()]
    for n in names:
        TASKS.get(n)  # unknown -> one-line error listing the tasks
    return names
