"""What a study is: its default name, the objective it maximised, the user attributes it records when created, and
the check that a resumed study was created with the same settings (search space, pipeline, data, task, budget)."""
from __future__ import annotations

import math
from pathlib import Path

from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError
from tuner.budget import CLOCK
from tuner.version import code_version

# mAA10: maximise mAA(10 deg) within the budget B; pareto: a two-objective study (maximise mAA(10 deg), minimise
# the median estimator seconds per pair) whose Pareto front tuner.pareto draws and reads the best within B off
OBJECTIVES = ("mAA10", "auc10", "auc20", "pareto")
# auc10 / auc20: maximise the pose AUC (pipeline.metrics.auc) instead; the study records it (user attribute
# "objective"), its default name ends in -auc10 / -auc20, and a study without the attribute maximised mAA10
AUC_OBJECTIVES = ("auc10", "auc20")
PARETO_SUFFIX = "-pareto"
PARETO_SPAN = 4.0
SCHEMA = 1


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


def study_objective(attrs: dict) -> str:
    """The figure a study maximised, from its user attributes: "mAA10" (the default, and every study created
    before --objective auc10/auc20), "auc10", "auc20" or "pareto"."""
    o = attrs.get("objective")
    return str(o.get("name", "mAA10")) if isinstance(o, dict) else "mAA10"


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
    if mine.get("budget_clock") and stored.get("budget_clock") != mine["budget_clock"]:
        raise IncompatibleStudy(f"study {name!r} was timed in wall-clock seconds (made before imtune's budget became "
                                "estimator CPU time), so its trials cannot be mixed with CPU-time ones; name a new "
                                "study with --study")
    b_old = (stored.get("budget") or {}).get("seconds_per_pair")
    b_new = mine["budget"]["seconds_per_pair"]
    if b_old is not None and not math.isclose(float(b_old), float(b_new)):
        raise IncompatibleStudy(f"study {name!r} exists with budget {b_old} s per pair, not {b_new}; "
                                f"rerun with --budget {b_old} or name a new study with --study")


def study_identity(s, task, space, vs, base: PipelineConfig) -> dict:
    """``s``: the run's ``tuner.study.TuneSettings``. The user attributes a new study of these settings records before its calibration: among them what
    :func:`check_compatible` compares when a study of that name is resumed (search space, pipeline, validation data,
    task options, budget). ``vs``: the settings' :func:`open_validation`; ``base``: ``s.base`` with the estimator
    seed set."""
    from tuner.formatting import ground_truth_origins
    from tuner.preflight import test_scene_names
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
                   "statistic": "median estimator CPU seconds per pair"},
        # the clock of every estimator time the study records (a study without it: wall-clock seconds, refused when
        # resumed by check_compatible); None for a task that times no estimator of ours
        "budget_clock": CLOCK if getattr(task, "timed", False) else None,
        "code_version": code_version(),
        "seed": int(s.seed or 0),
    }
