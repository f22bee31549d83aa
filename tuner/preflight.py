"""Before a study's first trial: the validation set, the test scenes, the search space and a pinned Gamma checked,
so that nothing after tuning can stop it (each failure a one-line error naming the flag that fixes it)."""
from __future__ import annotations

from pathlib import Path

from pipeline.errors import ImtuneError


def check_task_scene(task, scene, role: str, others: str) -> None:
    """A one-line ImtuneError when ``task`` cannot evaluate ``scene`` (``Task.check_scene``: no pairs, no ground
    truth, no bags), naming the ``role`` ("validation", "test") and ending with ``others`` (the flag that fixes it)."""
    why = task.check_scene(scene)
    if why and why.startswith("no ground truth"):
        raise ImtuneError(f"{role} scene {scene.name!r} has {why}; build it with `tune data build-gt --data "
                          f"{scene.root}`, {others}")
    if why:
        raise ImtuneError(f"{role} scene {scene.name!r}: {why}; {others}")


def open_validation(s, task):
    """The ValidationSet of the settings' data and validation scenes for ``task``."""
    from tuner.evaluate import load_scenes
    from tuner.objective import ValidationSet
    scenes = load_scenes(s.data_root, s.val_scenes, split="val", gt_dir=s.gt_dir)
    if not scenes:
        raise ImtuneError(f"no validation scenes in {s.data_root}")
    for scene in scenes:  # before the study exists: a study whose every trial must fail is never created
        check_task_scene(task, scene, "validation", "choose others with --scenes")
    return ValidationSet.from_scenes(scenes, task)


def test_scene_names(s) -> list[str]:
    if s.test_scenes:
        return list(s.test_scenes)
    from pipeline.data import default_splits
    return list(default_splits(s.data_root).get("test", []))


def preflight(s, task, stored: dict | None = None) -> list[str]:
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


def pinned_gamma_warning(s, space, fingerprint: str | None = None) -> str | None:
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
    from tuner.budget import CLOCK, GAMMA_CEILING, calibration_key, stored_calibration
    cal = None
    if fingerprint is not None and s.studies_dir is not None:
        from pipeline.tasks.pool import resolve_jobs
        cal_conf = space.calibration or {}
        key = calibration_key(ransac, s.base.feature, float(cal_conf.get("ratio", 0.9)),
                              float(cal_conf.get("threshold", 0.5)), fingerprint, jobs=resolve_jobs(s.jobs),
                              matching=s.base.matching)
        cal = stored_calibration(Path(s.studies_dir), key)
    if cal is not None and cal.clock == CLOCK and cal.covers(s.budget):  # a wall-clock one is measured again
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


def load_study_space(s, task):
    """The study's search space: ``--space``, else the task's own file (``Task.space_file``), else the estimator
    family's; then ``--fix`` pins; then every parameter the task does not use dropped (never searched, never
    recorded)."""
    from tuner.protocol import searchable, unused_by
    from tuner.space import SPACES_DIR, load_space
    path = s.space_path or (SPACES_DIR / task.space_file if task.space_file else None)
    space = load_space(path, feature=s.base.feature.name, estimator=s.base.geometry.ransac, fixes=s.fixes,
                       matcher=s.base.matching.method)
    from tuner.space import parse_fixes
    unused = [k for k in parse_fixes(s.fixes) if k in unused_by(task, s.base)]
    if unused:  # dropped below like the rest: a typed pin that does nothing was silently forgotten
        by = f"the {task.name} task" + (f" with --matcher {s.base.matching.method}" if s.base.matching.learned else "")
        s.warn(f"--fix {', '.join(unused)}: {by} does not use "
               f"{'it' if len(unused) == 1 else 'them'} (it uses {', '.join(searchable(task, s.base))}); ignored")
    if s.unused_options:  # stereo options of a multiview run, found by the command line (tuner.commands.study)
        s.warn(f"{', '.join(s.unused_options)}: the {task.name} task does not use "
               f"{'it' if len(s.unused_options) == 1 else 'them'} ({task.why_untimed}; --bags sets the work); ignored")
    for k in unused_by(task, s.base):  # the task's, and the matcher's: r or a learned matcher's threshold
        space.params.pop(k, None)
        space.fixed.pop(k, None)
    if not space.params:
        pinned = f"every parameter is fixed ({', '.join(sorted(space.fixed))}: in the file or by --fix)" \
            if space.fixed else "no parameter is searched"  # the file was not named: the culprit unsaid
        raise ImtuneError(f"search space {space.source}: {pinned}; nothing to tune: give one a range there, or drop "
                          "its --fix")
    return space
