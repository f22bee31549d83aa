"""Freeze the validation optimum and run it on the test scenes.

    from tuner.freeze import freeze, run_test
    frozen, path = freeze(study, studies_dir)        # studies/<study>/frozen.yaml
    result = run_test(frozen, data_root, studies_dir) # studies/<study>/test.json

``frozen.yaml`` holds the best *feasible* completed trial (median estimator seconds per pair within
the validation budget): its searched values (``params``), the values that were not searched
(``fixed``), the complete pipeline configuration (``config``: every parameter of every stage), the
budget (B, Gamma_max), the data (root, scenes, fingerprint) and the validation metrics.

The test run evaluates ``config`` on the test scenes ``runs`` times (default 3, as the paper) with
estimator seeds ``seed, seed + 1, ...``, and averages; ``test.json`` holds every run's summary, the
mean and standard deviation, and whether the median estimator time per pair kept within the test
budget (default 1 s). The mean is also stored in the study's user attribute ``test`` so that
``tune results`` can read it from the storage alone.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
from pathlib import Path

import numpy as np
import yaml

from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
from pipeline.errors import ImtuneError

SUMMARY_KEYS = ("mAA5", "mAA10", "NF", "NM", "NI", "match_seconds", "ransac_seconds", "ransac_seconds_median",
                "ransac_seconds_p90", "failed", "pairs")


from pipeline.fileio import atomic_write  # noqa: E402  (re-exported: budget.py and the reports use it)


def study_dir(studies_dir: Path | str, name: str) -> Path:
    safe = "".join(c if (c.isalnum() or c in "-_.+") else "_" for c in name)
    return Path(studies_dir) / safe


def _previous_result(out_path: Path | None, ident: dict) -> dict | None:
    """The test.json already written for exactly this identity (trial, config, data, runs), if any."""
    if out_path is None or not out_path.is_file():
        return None
    try:
        old = json.loads(out_path.read_text())
    except (OSError, ValueError):
        return None  # unreadable: rerun the test rather than trust it
    return old if old.get("identity") == _plain(ident) else None


def _plain(o):
    """JSON/YAML-safe: tuples -> lists, non-finite floats -> strings, numpy scalars -> Python."""
    if isinstance(o, dict):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None if math.isnan(o) else ("inf" if o > 0 else "-inf")
    return o


def frozen_from_study(study) -> dict:
    """The frozen settings (a dict) of the study's best feasible trial; ImtuneError if there is none."""
    from tuner.objective import config_for
    from tuner.study import best_feasible
    attrs = study.user_attrs
    if not attrs.get("imtune"):
        raise ImtuneError(f"study {study.study_name!r} was not created by imtune")
    best = best_feasible(study)
    if best is None:
        raise ImtuneError(f"study {study.study_name!r} has no feasible completed trial (none within the "
                          f"{attrs['budget']['seconds_per_pair']} s per pair budget); run more trials first")
    base = pipeline_from_dict(attrs["pipeline"])
    fixed = dict(attrs["search_space_resolved"].get("fixed", {}))
    conf = config_for(base, dict(best.params), fixed, seed=int(attrs.get("seed", 0)))
    searched = list(best.params)
    # parameters neither searched nor pinned keep the command line's value: record them as fixed too
    from tuner.study import SEARCHED
    cd = conf.to_dict()
    all_fixed = {k: cd[sec][key] for k, (sec, key) in SEARCHED.items() if k not in searched}
    if attrs.get("task") == "multiview":  # COLMAP runs its own RANSAC: eta and Gamma play no part
        from tuner.study import NOT_MULTIVIEW
        for k in NOT_MULTIVIEW:
            all_fixed.pop(k, None)
    ua = best.user_attrs
    if attrs.get("task") == "multiview":
        from tuner.objective import MULTIVIEW_ATTRS
        validation = {k: ua.get(k) for k in MULTIVIEW_ATTRS + ("scenes",)}
    else:
        validation = {k: ua.get(k) for k in ("mAA5", "mAA10", "NF", "NM", "NI", "ransac_seconds_median",
                                             "ransac_seconds_p90", "match_seconds", "failed", "scenes")}
        validation["pairs"] = (ua.get("timing") or {}).get("pairs")
    budget = dict(attrs["budget"])
    budget.pop("calibration", None)
    return _plain({
        "study": study.study_name,
        "trial": best.number,
        "value": best.value,
        "task": attrs.get("task", "stereo"),
        "feature": attrs.get("feature"), "num_features": attrs.get("num_features"), "ransac": attrs.get("ransac"),
        "params": dict(best.params),
        "fixed": all_fixed,
        "config": conf.to_dict(),
        "budget": budget,
        "data": {**attrs.get("data", {}), "fingerprint": attrs.get("data_fingerprint")},
        "validation": validation,
        "search_space": attrs.get("search_space_resolved"),
        **({"multiview": attrs["multiview"]} if attrs.get("multiview") else {}),
        "code_version": attrs.get("code_version"),
        "frozen_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    })


def freeze(study, studies_dir: Path | str) -> tuple[dict, Path]:
    """Write ``<studies_dir>/<study>/frozen.yaml`` from the best feasible trial; returns (dict, path)."""
    frozen = frozen_from_study(study)
    path = study_dir(studies_dir, study.study_name) / "frozen.yaml"
    header = (f"# imtune frozen settings of study {study.study_name}: best feasible trial #{frozen['trial']}\n"
              "# params: searched values; fixed: values not searched; config: the complete pipeline\n")
    atomic_write(path, header + yaml.safe_dump(frozen, sort_keys=False, default_flow_style=False))
    from tuner.annotate import annotate_study; annotate_study(study, frozen)  # noqa: E702 - dashboard notes
    return frozen, path


def load_frozen(studies_dir: Path | str, name: str) -> dict:
    path = study_dir(studies_dir, name) / "frozen.yaml"
    if not path.is_file():
        raise ImtuneError(f"no frozen settings for study {name!r} ({path} does not exist; run `tune` first)")
    try:
        d = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ImtuneError(f"{path}: invalid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(d, dict) or "config" not in d:
        raise ImtuneError(f"{path}: not a frozen-settings file (no 'config')")
    return d


def pipeline_from_dict(d: dict) -> PipelineConfig:
    """PipelineConfig from its ``to_dict()`` form (None placeholders take the dataclass defaults)."""
    def build(cls, sub):
        names = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in (sub or {}).items() if k in names and v is not None}
        if "options" in kw:
            kw["options"] = tuple(tuple(x) if isinstance(x, list) else x for x in kw["options"])
        return cls(**kw)
    try:
        return PipelineConfig(feature=build(FeatureConfig, d.get("feature")), matching=build(MatchConfig, d.get("matching")),
                              geometry=build(GeometryConfig, d.get("geometry")))
    except TypeError as e:
        raise ImtuneError(f"invalid pipeline configuration: {e}") from None


def _mean_summaries(runs: list[dict]) -> tuple[dict, dict]:
    mean, std = {}, {}
    for k in SUMMARY_KEYS:
        vals = [float(r[k]) for r in runs if r.get(k) is not None]
        if vals:
            mean[k] = float(np.mean(vals))
            std[k] = float(np.std(vals))
    scenes = {}
    for name in runs[0].get("scenes", {}):
        per = [r["scenes"][name] for r in runs if name in r.get("scenes", {})]
        scenes[name] = {k: float(np.mean([float(p[k]) for p in per])) for k in SUMMARY_KEYS if k in per[0]}
    mean["scenes"] = scenes
    return mean, std


def run_test(frozen: dict, data_root: Path | str, studies_dir: Path | str | None = None, *, scenes=None,
             cache=None, runs: int = 3, max_pairs: int | None = None, test_budget: float | None = None,
             progress: bool = False, reuse: bool = True, workers: int | None = None) -> dict:
    """Evaluate the frozen configuration on the test scenes ``runs`` times (different estimator seeds)
    and average. Writes ``<studies_dir>/<study>/test.json`` when ``studies_dir`` is given; with
    ``reuse``, an existing test.json for the same trial, configuration and data is returned as is.
    Multiview studies: :func:`run_test_multiview` (``workers`` bag processes)."""
    if frozen.get("task") == "multiview":
        return run_test_multiview(frozen, data_root, studies_dir, scenes=scenes, cache=cache, runs=runs,
                                  progress=progress, reuse=reuse, workers=workers)
    from pipeline.cache import H5Cache
    from pipeline.tasks.stereo import evaluate_stereo
    from tuner.objective import ValidationSet, summarize_records
    from tuner.options import load_scenes
    from tuner.study import code_version
    data_root = Path(data_root)
    names = list(scenes) if scenes else list(frozen.get("data", {}).get("test_scenes") or [])
    if not names:
        from pipeline.data import default_splits
        names = list(default_splits(data_root).get("test", []))
    if not names:
        raise ImtuneError(f"no test scenes for study {frozen.get('study')!r} in {data_root} "
                          "(give --scenes or add a splits.yaml with 'test')")
    if max_pairs is None:
        max_pairs = frozen.get("data", {}).get("max_pairs")
    min_cov = frozen.get("data", {}).get("min_covisibility", 0.1)
    conf = pipeline_from_dict(frozen["config"])
    tb = float(test_budget if test_budget is not None else frozen.get("budget", {}).get("test_seconds_per_pair", 1.0))
    vs = ValidationSet.from_scenes(load_scenes(data_root, names, split="test"), min_cov, max_pairs,
                                   chunk_pairs=10**9)
    out_path = study_dir(studies_dir, frozen["study"]) / "test.json" if studies_dir is not None else None
    ident = {"trial": frozen.get("trial"), "config": frozen["config"], "fingerprint": vs.fingerprint,
             "runs": int(runs), "test_budget": tb}
    old = _previous_result(out_path, ident) if reuse else None
    if old is not None:
        return old
    cache = cache if cache is not None else H5Cache()
    vs.prepare(conf, cache, progress=progress)
    seed0 = int(conf.geometry.seed)
    results = []
    it = range(int(runs))
    if progress:
        from tqdm.auto import tqdm
        it = tqdm(it, desc=f"test {frozen['study']}", unit="run", leave=False)
    for k in it:
        c = dataclasses.replace(conf, geometry=dataclasses.replace(conf.geometry, seed=seed0 + k))
        res = evaluate_stereo(vs.chunks, c, cache, min_covisibility=None, progress=False)
        s = summarize_records(res.records, vs)
        s["seed"] = seed0 + k
        results.append(s)
    mean, std = _mean_summaries(results)
    within = bool(mean.get("ransac_seconds_median", 0.0) <= tb)
    out = _plain({
        "study": frozen["study"], "trial": frozen.get("trial"), "task": frozen.get("task", "stereo"),
        "feature": frozen.get("feature"), "num_features": frozen.get("num_features"), "ransac": frozen.get("ransac"),
        "params": frozen.get("params"), "fixed": frozen.get("fixed"),
        "data": {"root": str(data_root), "scenes": names, "fingerprint": vs.fingerprint, "min_covisibility": min_cov,
                 "max_pairs": max_pairs, "pairs": vs.n_pairs},
        "budget": {"test_seconds_per_pair": tb, "within_budget": within,
                   "statistic": "median estimator seconds per pair"},
        "runs": [{k: r.get(k) for k in ("seed",) + SUMMARY_KEYS + ("scenes",)} for r in results],
        "mean": mean, "std": {k: std[k] for k in ("mAA5", "mAA10", "NI") if k in std},
        "validation": frozen.get("validation"),
        "code_version": code_version(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "identity": ident,
    })
    if out_path is not None:
        atomic_write(out_path, json.dumps(out, indent=2))
    return out


def _test_scene_names(frozen: dict, data_root: Path, scenes) -> list[str]:
    names = list(scenes) if scenes else list(frozen.get("data", {}).get("test_scenes") or [])
    if not names:
        from pipeline.data import default_splits
        names = list(default_splits(data_root).get("test", []))
    if not names:
        raise ImtuneError(f"no test scenes for study {frozen.get('study')!r} in {data_root} "
                          "(give --scenes or add a splits.yaml with 'test')")
    return names


def run_test_multiview(frozen: dict, data_root: Path | str, studies_dir: Path | str | None = None, *, scenes=None,
                       cache=None, runs: int = 3, progress: bool = False, reuse: bool = True,
                       workers: int | None = None) -> dict:
    """The multiview test: the frozen configuration's multiview evaluation of the test scenes, ``runs``
    times with COLMAP seeds ``seed, seed + 1, ...`` (the bags are the same in every run), averaged."""
    from pipeline.cache import H5Cache
    from pipeline.tasks.multiview import MultiviewConfig, evaluate_multiview
    from tuner.objective import MULTIVIEW_ATTRS, data_fingerprint, multiview_attrs
    from tuner.options import load_scenes
    from tuner.study import code_version
    data_root = Path(data_root)
    names = _test_scene_names(frozen, data_root, scenes)
    conf = pipeline_from_dict(frozen["config"])
    mvd = dict(frozen.get("multiview") or {})
    mv = MultiviewConfig(**{k: (tuple(tuple(x) for x in v) if k == "bags" else v) for k, v in mvd.items()})
    scene_objs = load_scenes(data_root, names, split="test")
    fp = data_fingerprint([(sc, sc.select_pairs(None)) for sc in scene_objs], None)
    out_path = study_dir(studies_dir, frozen["study"]) / "test.json" if studies_dir is not None else None
    ident = {"trial": frozen.get("trial"), "config": frozen["config"], "multiview": mvd, "fingerprint": fp,
             "runs": int(runs)}
    old = _previous_result(out_path, ident) if reuse else None
    if old is not None:
        return old
    cache = cache if cache is not None else H5Cache()
    results = []
    for k in range(int(runs)):
        m = dataclasses.replace(mv, seed=int(mv.seed) + k)
        res = evaluate_multiview(scene_objs, conf, m, cache, workers=workers, progress=progress)
        s = multiview_attrs(res.summary, res.scenes)
        s["seed"] = int(mv.seed) + k
        results.append(s)
    mean, std = {}, {}
    for key in MULTIVIEW_ATTRS + ("accuracy",):
        vals = [r[key] for r in results if r.get(key) is not None]
        if vals:
            mean[key] = np.mean(np.asarray(vals, float), axis=0).tolist()
            std[key] = np.std(np.asarray(vals, float), axis=0).tolist()
    mean["scenes"] = {}
    for name in results[0]["scenes"]:
        per = [r["scenes"][name] for r in results]
        mean["scenes"][name] = {key: np.mean(np.asarray([p[key] for p in per], float), axis=0).tolist()
                                for key in MULTIVIEW_ATTRS + ("accuracy",) if all(p.get(key) is not None for p in per)}
    out = _plain({
        "study": frozen["study"], "trial": frozen.get("trial"), "task": "multiview",
        "feature": frozen.get("feature"), "num_features": frozen.get("num_features"), "ransac": frozen.get("ransac"),
        "params": frozen.get("params"), "fixed": frozen.get("fixed"), "multiview": mvd,
        "data": {"root": str(data_root), "scenes": names, "fingerprint": fp},
        "runs": results, "mean": mean, "std": {k: std[k] for k in ("mAA5", "mAA10", "SR") if k in std},
        "validation": frozen.get("validation"),
        "code_version": code_version(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "identity": ident,
    })
    if out_path is not None:
        atomic_write(out_path, json.dumps(out, indent=2))
    return out


def test_summary(result: dict) -> dict:
    """The part of a test result stored in the study (what `tune results` reads)."""
    m = result.get("mean", {})
    return {"trial": result.get("trial"), "runs": len(result.get("runs", [])), "scenes": result["data"]["scenes"],
            "mAA5": m.get("mAA5"), "mAA10": m.get("mAA10"), "NF": m.get("NF"), "NM": m.get("NM"), "NI": m.get("NI"),
            "mAA10_std": result.get("std", {}).get("mAA10"),
            "ransac_seconds_median": m.get("ransac_seconds_median"),
            "within_budget": result.get("budget", {}).get("within_budget"),
            "per_scene": {k: {"mAA10": v.get("mAA10"), "mAA5": v.get("mAA5")} for k, v in m.get("scenes", {}).items()},
            "created": result.get("created")}


def run_test_for_study(study, frozen: dict, studies_dir, *, data_root=None, scenes=None, cache=None, runs: int = 3,
                       max_pairs=None, test_budget=None, progress: bool = False, reuse: bool = True,
                       workers: int | None = None) -> dict:
    """:func:`run_test` and store its summary in the study's user attribute ``test``."""
    root = data_root or frozen.get("data", {}).get("root")
    if root is None or not Path(root).is_dir():
        from tuner.options import resolve_data
        root = resolve_data(None)
    result = run_test(frozen, root, studies_dir, scenes=scenes, cache=cache, runs=runs, max_pairs=max_pairs,
                      test_budget=test_budget, progress=progress, reuse=reuse, workers=workers)
    study.set_user_attr("test", test_summary(result))
    return result
