"""One fixed configuration evaluated on some scenes, by one or several tasks — what `tune evaluate` prints.

    from tuner.evaluate import evaluate_config, load_scenes
    out = evaluate_config(conf, data_root, ["fountain-P11"], task="stereo")
    out["stereo"]["mAA10"], out["stereo"]["scenes"]["fountain-P11"]
"""
from __future__ import annotations

from pathlib import Path

from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError


def check_unique_scenes(names, where: str = "") -> None:
    """One-line ImtuneError when a scene is named twice: its pairs would be evaluated twice, counted twice in
    every mAA and narrow its interval as if they were independent pairs."""
    seen = set()
    for n in names:
        if n in seen:
            raise ImtuneError(f"{where}scene {n!r} is named twice ({', '.join(names)}): name each scene once")
        seen.add(n)


def load_scenes(data_root: Path, names: list[str] | str | None, split: str = "val", gt_dir=None,
                ground_truth: bool = True):
    """Scenes by name (a list or a comma-separated string), or the data set's default split.

    With ``ground_truth`` (default), a ground truth built by `tune data build-gt` (in ``gt_dir``, default
    $IMTUNE_CACHE/gt) is attached to each scene: 3D points, co-visibility of its pairs (so the stereo
    pairs are selected at co-visibility >= 0.1), poses for SfM-built scenes."""
    from pipeline.data import default_splits, list_scenes, load_scene
    from pipeline.data.ground_truth import prepare_scene_ground_truth
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    check_unique_scenes(names or [])
    if not names:
        names = list_scenes(data_root) if split == "all" else default_splits(data_root)[split]
    scenes = [load_scene(data_root, n) for n in names]
    if ground_truth:
        for sc in scenes:
            prepare_scene_ground_truth(sc, gt_dir)
    return scenes


def _check_arguments(conf, max_pairs, ci_resamples, workers) -> None:
    """What the CLI's parser checks, for a Python caller (one-line ImtuneError naming the argument, before any scene
    is read): a dict or None as ``conf`` was an AttributeError, ``max_pairs=-1`` / ``1.5`` numpy's ValueError /
    TypeError, ``ci_resamples=-1`` scipy's ValueError after every pair, and ``ci_resamples=1`` an interval that
    misses its own estimate."""
    from tuner.argtypes import MAX_RESAMPLES, MIN_RESAMPLES

    def whole(v) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)

    if not isinstance(conf, PipelineConfig):
        raise ImtuneError(f"conf must be a PipelineConfig (pipeline.config; from a file: "
                          f"pipeline.config_files.load_config_file(PATH).conf), got {type(conf).__name__}")
    if max_pairs is not None and not (whole(max_pairs) and max_pairs >= 0):
        raise ImtuneError(f"max_pairs must be None or 0 (every pair) or an integer >= 1, got {max_pairs!r}")
    if ci_resamples is not None and not (whole(ci_resamples) and (ci_resamples == 0 or
                                                                 MIN_RESAMPLES <= ci_resamples <= MAX_RESAMPLES)):
        raise ImtuneError(f"ci_resamples must be None (the default, 2000), 0 (no interval) or an integer from "
                          f"{MIN_RESAMPLES} to {MAX_RESAMPLES:,}, got {ci_resamples!r}")
    if workers is not None and not (whole(workers) and workers >= 1):
        raise ImtuneError(f"workers must be None (every usable CPU) or an integer >= 1, got {workers!r}")


def evaluate_config(conf: PipelineConfig, data_root: Path, scenes=None, cache_dir=None,
                    min_covisibility: float | None = 0.1, progress: bool = False,
                    with_pairs: bool = False, task: str = "stereo", multiview=None, workers: int | None = None,
                    gt_dir=None, with_bags: bool = False, keep_models=None, intermediate: bool = False,
                    max_pairs: int | None = None, ci_resamples: int | None = None, jobs: int | None = None,
                    task_options: dict | None = None, mapper: str | None = None,
                    submission=None) -> dict:
    """Evaluate one configuration; returns the JSON-able result of `tune evaluate`.

    task: a registered task name (``stereo``, ``multiview``), a comma-separated list, or ``both``: the result
    has one section per task (its summary, ``scenes``, and with ``with_pairs`` / ``with_bags`` its records) and
    ``<task>_config`` with the task's options where it has any. The remaining arguments are the tasks' options
    (each task takes those it knows: :func:`pipeline.tasks.make_task`): min_covisibility, max_pairs (stereo);
    multiview (a ``MultiviewConfig``), workers (parallel bag processes), keep_models (multiview); gt_dir: where
    built ground truth lives; intermediate: add an "intermediate" section (repeatability, matching scores,
    ``pipeline.tasks.intermediate``); ci_resamples: bootstrap resamples of the mAA intervals (``mAA5_ci``,
    ``mAA10_ci``; None: the task's default, 2000; 0: none); jobs: stereo pair worker processes (None: every
    usable CPU; the records do not depend on it); mapper: "incremental" / "global" and submission: where
    submission.csv goes (reconstruction); task_options: a task's :meth:`~pipeline.tasks.base.Task.options`
    (a study's recorded ones, with one task; the arguments above override them where given: multiview then None). ``ground_truth``: scene name -> where the poses it is evaluated
    against come from (``Scene.truth_origin``). Raises ImtuneError when there is nothing to evaluate."""
    from pipeline.cache import H5Cache
    from pipeline.tasks import TASKS, task_list
    _check_arguments(conf, max_pairs, ci_resamples, workers)
    names = task_list(task)
    scene_objs = load_scenes(data_root, scenes, split="all", gt_dir=gt_dir)
    if not scene_objs:
        raise ImtuneError(f"no scenes in {data_root} (see `tune data scenes --data {data_root}`)")
    cache = H5Cache(cache_dir)
    from tuner.formatting import ground_truth_origins
    out = {"config": conf.to_dict(), "data": str(data_root), "scenes": [s.name for s in scene_objs],
           "ground_truth": ground_truth_origins(scene_objs)}  # each scene's poses: its own, or imtune's SfM
    for name in names:
        # each task takes the options its constructor knows (pipeline.tasks.make_task)
        t = TASKS.get(name).from_options(task_options, min_covisibility=min_covisibility, max_pairs=max_pairs,
                                         mv=multiview, workers=workers, keep_models=keep_models, progress=progress,
                                         jobs=jobs, mapper=mapper, submission=submission,
                                         **({} if ci_resamples is None else {"ci_resamples": ci_resamples}))
        units = sum(len(t.evaluation_units(s)) for s in scene_objs)
        if units == 0:
            raise ImtuneError(f"nothing to evaluate: no {name} pairs in {', '.join(s.name for s in scene_objs)} "
                              f"(a scene needs at least 2 images{' and co-visibility >= ' + str(min_covisibility) if min_covisibility else ''})")
        res = t.evaluate(scene_objs, conf, cache)
        out[name] = res.to_dict(with_records=with_pairs or with_bags)
        notes = t.notes(scene_objs)
        if notes:  # where the task could not follow its options (bag sizes above a scene's images)
            out[name]["notes"] = notes
        if t.options():
            out[f"{name}_config"] = t.options()
    if intermediate:
        from pipeline.tasks.intermediate import evaluate_intermediate
        out["intermediate"] = evaluate_intermediate(scene_objs, conf, cache, min_covisibility=min_covisibility,
                                                    progress=progress)
    return out
