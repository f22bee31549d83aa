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
mean and standard deviation, and whether the median estimator CPU time per pair kept within the test
budget (default 1 s). The mean is also stored in the study's user attribute ``test`` so that
``tune results`` can read it from the storage alone.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import time
from pathlib import Path

import numpy as np
import yaml

from pipeline.config_files import pipeline_from_dict  # noqa: F401  (re-exported)
from pipeline.errors import ImtuneError
from pipeline.fileio import atomic_write  # noqa: E402  (re-exported: budget.py and the reports use it)
from pipeline.metrics.uncertainty import STD_DDOF

#: longest study name used as a folder name as it is (file systems allow 255 bytes per name)
MAX_DIR_NAME = 120


def study_dir(studies_dir: Path | str, name: str) -> Path:
    """``<studies_dir>/<name>``: the study's folder (frozen.yaml, test.json, report.html). A name that is not a safe
    folder name as it is (a path separator, a character outside ``[A-Za-z0-9-_.+]``, ".", "..", an empty or an
    over-long name) is made one and given a hash of the whole name, so two studies never share a folder and no
    study writes outside ``studies_dir`` ("a/b" and "a_b" once both wrote to ``a_b``; ".." wrote beside it)."""
    safe = "".join(c if (c.isascii() and (c.isalnum() or c in "-_.+")) else "_" for c in name)
    if safe == name and safe not in ("", ".", "..") and len(safe) <= MAX_DIR_NAME:
        return Path(studies_dir) / safe
    import hashlib
    tag = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:10]
    return Path(studies_dir) / f"{safe.strip('.')[:MAX_DIR_NAME - 11] or 'study'}-{tag}"


def load_test_file(path: Path | str | None, study: str | None = None,
                   refresh: bool = True) -> tuple[dict | None, str | None]:
    """A study's test.json: (the result, None); (None, None) when there is none; (None, why) when it is there but
    cannot be read or holds no test result (cut short, binary, a JSON list), or, given ``study``, holds another
    study's (a study folder copied under a new name: its numbers passed for this study's). The one reader every
    table, report and rerun check goes through, so that a damaged file is said (or rerun), never a crash or
    silently ignored. ``refresh``: a result whose intervals an earlier imtune made with another method gets the
    current ones, recomputed from its pair errors in memory (``tuner.select.refresh_intervals``), so a report or
    table never shows the old ones beside numbers recomputed the new way; `tune test` rewrites the file."""
    if path is None or not Path(path).is_file():
        return None, None
    try:
        d = json.loads(Path(path).read_text())
    except UnicodeDecodeError:
        return None, "not UTF-8 text"
    except json.JSONDecodeError:
        return None, "not valid JSON"
    except (OSError, ValueError) as e:
        return None, getattr(e, "strerror", None) or str(e).splitlines()[0][:120]
    if not isinstance(d, dict) or not isinstance(d.get("runs", []), list) \
            or not all(isinstance(r, dict) for r in d.get("runs", [])):
        return None, "not a test result (a JSON object with a list of runs)"
    why = _test_figures_problem(d)
    if why is None and study is not None and d.get("study") is not None and d["study"] != study:
        why = f"it holds the test of study {d.get('study')!r}, not {study!r} (copied from another study?)"
    if why is None and refresh:
        from tuner.select import refresh_intervals
        iv = d.get("interval") if isinstance(d.get("interval"), dict) else {}
        n = iv.get("resamples") or (d.get("identity") or {}).get("ci_resamples") or 2000
        if isinstance(n, int) and not isinstance(n, bool) and n > 0:
            refresh_intervals(d, n)
    return (None, why) if why else (d, None)


def _figure(v) -> bool:
    """A figure as test.json holds it: a number, null (NaN), "inf" / "-inf" (_plain), or a list of such."""
    if isinstance(v, list):
        return all(_figure(x) for x in v)
    return v is None or v in ("inf", "-inf") or isinstance(v, (int, float)) and not isinstance(v, bool)


def _test_figures_problem(d: dict) -> str | None:
    """What is wrong with the figures of a test result, or None: ``mean`` / ``std`` (and each scene of ``mean``) map
    names to figures, ``data`` and ``budget`` are objects, ``data.scenes`` a list of names. A hand-edited
    ``"mAA10": "high"`` or ``"mean": [1]`` was an internal error in tune results, tune plot and tune test --reuse."""
    for key in ("data", "budget", "mean", "std"):
        if d.get(key) is not None and not isinstance(d[key], dict):
            return f"{key} is not an object"
    scenes = (d.get("data") or {}).get("scenes")
    if scenes is not None and not (isinstance(scenes, list) and all(isinstance(x, str) for x in scenes)):
        return "data.scenes is not a list of scene names"
    parts = [("mean", d.get("mean") or {}), ("std", d.get("std") or {})]
    per = parts[0][1].get("scenes")
    if per is not None and not (isinstance(per, dict) and all(isinstance(v, dict) for v in per.values())):
        return "mean.scenes is not an object of scenes"
    parts += [(f"mean.scenes.{k}", v) for k, v in (per or {}).items()]
    for where, figures in parts:
        for k, v in figures.items():
            if not (where == "mean" and k == "scenes") and not _figure(v):
                return f"{where}.{k} is not a number: {v!r}"[:160]
    return None


def _previous_result(out_path: Path | None, ident: dict, study: str | None = None) -> dict | None:
    """The test.json already written for exactly this identity (trial, config, data, runs), if any. Asked with no
    reference (``--reference none``), a result that also compared a reference serves too: its own runs are the
    same."""
    old, _ = load_test_file(out_path, study, refresh=False)  # run_test refreshes and rewrites it
    if old is None:
        return None  # none, or unreadable: rerun the test rather than trust it
    if any(len(e) == 4 for r in old.get("runs") or [] for e in (r.get("bag_errors") or []) if isinstance(e, list)):
        return None  # multiview bags without their images (an earlier imtune): rerun, so that ranks can pair them
    have, want = old.get("identity"), _plain(ident)
    if have == want:
        return old
    if isinstance(have, dict) and want.get("reference") is None and "reference" in have:
        return old if {**have, "reference": None} == want else None
    return None


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


def task_of(d: dict, **extra):
    """The task a study, frozen file or test result was made with (its name and recorded options)."""
    from pipeline.tasks import TASKS
    from tuner.study_identity import AUC_OBJECTIVES, study_objective
    task = TASKS.get(d.get("task", "stereo")).from_options(d.get("task_options"), **extra)
    if study_objective(d) in AUC_OBJECTIVES:  # a study that maximised a pose AUC: its figure is the objective
        task.objective = study_objective(d)
    return task


def frozen_from_study(study, select: str | None = None) -> dict:
    """The frozen settings (a dict) of the trial the selection rule picks (``tuner.select``: best, one-se,
    smooth; None: the rule recorded in the study, else ``tuner.select.DEFAULT_RULE``) among the feasible ones;
    ImtuneError if there is none. Also records the selection, how flat the optimum is and warnings (optimum on
    a bound of the search space, ...)."""
    from tuner import select as sel
    from tuner.protocol import best_feasible, config_for, fixed_values, trial_value
    attrs = study.user_attrs
    if not attrs.get("imtune"):
        raise ImtuneError(f"study {study.study_name!r} was not created by imtune")
    missing = [k for k in ("pipeline", "budget", "search_space_resolved") if not isinstance(attrs.get(k), dict)]
    if missing:  # edited (the dashboard, SQL) or of another version: was "internal error: KeyError: 'budget'"
        raise ImtuneError(f"study {study.study_name!r} lacks its imtune attribute{'s' * (len(missing) > 1)} "
                          f"{', '.join(missing)} (edited, or written by another version of imtune): it cannot be "
                          "frozen; evaluate its frozen.yaml with `tune evaluate --config`, or run a new study with --study")
    optimum = best_feasible(study)
    best, selection = sel.select_trial(study, sel.check_rule(select or attrs.get("select")))
    if best is None:
        from tuner.protocol import no_feasible_reason
        raise ImtuneError(f"study {study.study_name!r} has no feasible completed trial "
                          f"({no_feasible_reason(study, attrs['budget']['seconds_per_pair'])}); run more trials first")
    task = task_of(attrs)
    base = pipeline_from_dict(attrs["pipeline"])
    fixed = dict(attrs["search_space_resolved"].get("fixed", {}))
    conf = config_for(base, {**fixed, **best.params}, seed=int(attrs.get("seed", 0)))
    ua = best.user_attrs
    validation = {k: ua.get(k) for k in task.summary_keys + ("scenes",)}
    validation.update({k: v for k, v in ua.items() if k.endswith("_ci")})  # 95% intervals (tuner.select)
    if validation.get("pairs") is None and task.unit == "pairs":  # a task of other units (bags) counts those
        validation["pairs"] = (ua.get("timing") or {}).get("pairs")
    budget = dict(attrs["budget"])
    budget.pop("calibration", None)
    out = _plain({
        "study": study.study_name,
        "trial": best.number,
        "value": trial_value(best),  # the objective (mAA(10 deg), or auc10/auc20); pareto: best within B on its front
        "objective": attrs.get("objective") or {"name": "mAA10"},
        "task": task.name,
        "task_options": task.options(),
        "feature": attrs.get("feature"), "num_features": attrs.get("num_features"), "ransac": attrs.get("ransac"),
        "params": dict(best.params),
        # parameters the task uses but the study did not search keep the command line's (or --fix) value
        "fixed": fixed_values(conf, list(best.params), task),
        "config": conf.to_dict(),
        "budget": budget,
        "data": {**attrs.get("data", {}), "fingerprint": attrs.get("data_fingerprint")},
        "validation": validation,
        "selection": selection,
        # how flat the optimum is: the trials within the optimum's 95% interval and the region they span
        "robustness": sel.flat_region(study, optimum, task.objective),
        "search_space": attrs.get("search_space_resolved"),
        "code_version": attrs.get("code_version"),
        "frozen_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    })
    out["warnings"] = _plain(sel.optimum_warnings(study, out))  # on a bound, Gamma_max at the ceiling, all 0
    return out


def freeze(study, studies_dir: Path | str, select: str | None = None, warn=None) -> tuple[dict, Path]:
    """Write ``<studies_dir>/<study>/frozen.yaml`` from the trial the selection rule ``select`` picks (None: the
    study's recorded rule, else the default; an explicit rule is recorded in the study); returns (dict, path).
    Each of ``frozen["warnings"]`` (``tuner.select.optimum_warnings``: optimum on a bound, ...) is also passed to
    ``warn`` (a callable taking one line) when given."""
    if select is not None:
        from tuner.select import check_rule
        study.set_user_attr("select", check_rule(select))
    frozen = frozen_from_study(study, select)
    if warn is not None:  # one line each (tune run prints them itself, through TuneSettings.warn)
        for w in frozen["warnings"]:
            warn(w)
    path = study_dir(studies_dir, study.study_name) / "frozen.yaml"
    rule = (frozen.get("selection") or {}).get("rule", "best")
    header = (f"# imtune frozen settings of study {study.study_name}: feasible trial #{frozen['trial']} "
              f"(selection rule {rule})\n"
              "# params: searched values; fixed: values not searched; config: the complete pipeline\n")
    atomic_write(path, header + yaml.safe_dump(frozen, sort_keys=False, default_flow_style=False))
    from tuner.annotate import annotate_study
    annotate_study(study, frozen)  # the dashboard's notes
    return frozen, path


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _positive_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 1


#: the numbers a frozen file carries and what they must be: (key path, check, what); ``None`` is allowed for each
#: (a value not measured), "*" matches every key of a mapping
FROZEN_NUMBERS = (
    (("trial",), lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "an integer >= 0"),
    (("value",), _finite, "a finite number"),
    (("budget", "seconds_per_pair"), lambda v: _finite(v) and v > 0, "a finite number of seconds > 0"),
    (("budget", "test_seconds_per_pair"), lambda v: _finite(v) and v > 0, "a finite number of seconds > 0"),
    (("budget", "gamma_max"), _positive_int, "a positive integer (Gamma)"),
    (("budget", "gamma_max_test"), _positive_int, "a positive integer (Gamma)"),
    (("budget", "gamma_max_front"), _positive_int, "a positive integer (Gamma)"),
    (("params", "max_iters"), _positive_int, "a positive integer (Gamma)"),
    (("fixed", "max_iters"), lambda v: _positive_int(v) or v == "calibrated", "a positive integer (Gamma)"),
    (("params", "*"), lambda v: not isinstance(v, float) or math.isfinite(v), "a finite number"),
    (("fixed", "*"), lambda v: not isinstance(v, float) or math.isfinite(v), "a finite number"),
)


def _at(d, path: tuple):
    """(dotted key, value) pairs found at ``path`` in ``d`` ("*": every key of a mapping)."""
    items = [("", d)]
    for k in path:
        nxt = []
        for where, node in items:
            if not isinstance(node, dict):
                continue
            keys = list(node) if k == "*" else [k] if k in node else []
            nxt += [(f"{where}.{kk}" if where else str(kk), node[kk]) for kk in keys]
        items = nxt
    return items


def _non_finite(node, where: str = ""):
    """The first (dotted key, value) holding a float NaN or infinity anywhere in ``node``, else None (imtune writes
    non-finite numbers as null or "inf": a YAML .nan / .inf is an edit)."""
    if isinstance(node, float) and not math.isfinite(node):
        return where, node
    if isinstance(node, dict):
        for k, v in node.items():
            hit = _non_finite(v, f"{where}.{k}" if where else str(k))
            if hit:
                return hit
    if isinstance(node, list):
        for i, v in enumerate(node):
            hit = _non_finite(v, f"{where}[{i}]")
            if hit:
                return hit
    return None


#: the sections of a frozen file its readers use and what each must be (absent or null is allowed but for
#: ``study`` and ``config``): ``budget: x`` or ``data: [..]`` was an internal error in `tune test`, ``test_scenes:
#: fountain-P11`` (no list) a scene per character
FROZEN_SHAPE = (
    (("study",), lambda v: isinstance(v, str) and v != "", "a study name", True),
    (("config",), lambda v: isinstance(v, dict), "a mapping (feature / matching / geometry)", True),
    (("task",), lambda v: isinstance(v, str), "a task name", False),
    *((((k,), lambda v: isinstance(v, dict), "a mapping", False))
      for k in ("task_options", "params", "fixed", "budget", "data", "validation", "selection")),
    (("data", "root"), lambda v: isinstance(v, str), "a folder name", False),
    *(((k, "min_covisibility"), lambda v: _finite(v) and 0 <= v <= 1, "a number in [0, 1]", False)
      for k in ("data", "task_options")),
    (("task_options", "max_pairs"), _positive_int, "a positive integer", False),
    *((("data", k), lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v), "a list of scene names",
       False) for k in ("val_scenes", "test_scenes")),
)


def frozen_problem(d: dict) -> str | None:
    """What is wrong with a frozen-settings dict, or None: its sections of the right type (:data:`FROZEN_SHAPE`);
    the validation value finite, the budgets finite seconds > 0, Gamma (gamma_max, max_iters) a positive integer,
    the measured seconds >= 0, no NaN or infinity anywhere. A frozen file carrying ``value: .nan``,
    ``gamma_max: .inf`` or ``seconds_per_pair: -1`` was tested as if it were sound."""
    from pipeline.config import yaml_number_hint
    for path, ok, what, required in FROZEN_SHAPE:
        found = _at(d, path)
        if required and not found:
            return f"no {'.'.join(path)} (cut short, or not a frozen-settings file?)"
        for key, v in found:
            if (v is not None or required) and not ok(v):
                return f"{key} must be {what}, got {v!r}"
    for path, ok, what in FROZEN_NUMBERS:
        for key, v in _at(d, path):
            if v is not None and not ok(v):
                return f"{key} must be {what}, got {v!r}{yaml_number_hint(v)}"
    for key, v in _at(d, ("validation", "*")) + [(f"{k}.{kk}", vv) for k, sc in _at(d, ("validation", "scenes", "*"))
                                                if isinstance(sc, dict) for kk, vv in sc.items()]:
        if "seconds" in key.rsplit(".", 1)[-1] and v is not None and not (_finite(v) and v >= 0):
            return f"{key} must be a finite number of seconds >= 0, got {v!r}{yaml_number_hint(v)}"
    hit = _non_finite(d)
    if hit:
        return f"{hit[0]} must be a finite number, got {hit[1]!r}"
    return None


def check_frozen(d: dict, where) -> dict:
    """``d`` if its numbers are sound (:func:`frozen_problem`), else a one-line ImtuneError naming ``where`` (the
    file) and the key."""
    why = frozen_problem(d)
    if why:
        raise ImtuneError(f"{where}: {why}; correct it, or write the file again from the study's storage "
                          "(`tune test --study NAME --storage URL` freezes it anew)")
    return d


#: what a study writes in its folder and reads back
STUDY_FILES = ("frozen.yaml", "test.json")


def check_study_outputs(studies_dir: Path | str, name: str) -> Path:
    """Before any trial or test run: the study's folder can be created and written, and none of
    :data:`STUDY_FILES` is a folder (found only once every trial or the whole test had run: "cannot write
    .../frozen.yaml: File exists", "... test.json: Is a directory"). One-line ImtuneError naming the culprit;
    nothing is created. Returns the folder."""
    from pipeline.fileio import check_writable_folder
    d = study_dir(studies_dir, name)
    check_writable_folder(d, "study folder", "move what is in the way (the study's frozen.yaml and test.json go "
                                             "there), or give another --studies-dir")
    for f in STUDY_FILES:
        if (d / f).is_dir():
            raise ImtuneError(f"{d / f} is a folder where study {name!r} writes its {f}: move it away, or give "
                              "another --studies-dir")
    return d


#: prefix of the folder inside a study's folder that keeps an earlier study's outputs (see set_aside_earlier_outputs)
EARLIER_PREFIX = "earlier-"


def _move_to_earlier(d: Path, entries: list, what: str, fix: str) -> Path:
    """Move ``entries`` (paths in ``d``) into a new ``d/earlier-<UTC time>`` (``-2``, ``-3``, ... when taken);
    returns that folder. An entry gone meanwhile is skipped; any other failure is one line: ``what`` could not be
    set aside ..., move it away, ``fix``."""
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    dest, k = d / f"{EARLIER_PREFIX}{stamp}", 1
    while dest.exists():
        k += 1
        dest = d / f"{EARLIER_PREFIX}{stamp}-{k}"
    try:
        dest.mkdir()
        for e in entries:
            try:
                Path(e).rename(dest / Path(e).name)
            except FileNotFoundError:
                pass
    except OSError as e:
        raise ImtuneError(f"{what} could not be set aside in {dest} ({e.strerror or e}): move it away, {fix}") from None
    return dest


def set_aside_earlier_outputs(studies_dir: Path | str, name: str) -> Path | None:
    """A new study ``name`` is being created while its folder still holds the outputs of an earlier study of that
    name that the storage no longer has (optuna.db deleted or replaced, or another ``--storage`` using this studies
    folder): move them (frozen.yaml, test.json, report.html, viz/, ...) into ``<folder>/earlier-<UTC time>/`` so
    that nothing the earlier study measured is overwritten by the new one. Returns that folder, or None when
    there was nothing to keep. Earlier ``earlier-*`` folders stay where they are."""
    d = study_dir(studies_dir, name)
    try:
        entries = [e for e in d.iterdir() if not e.name.startswith(EARLIER_PREFIX) and not e.name.startswith(".")]
    except (FileNotFoundError, NotADirectoryError):
        return None
    if not entries:
        return None
    dest = _move_to_earlier(d, entries, f"study folder {d} holds an earlier study's outputs "
                                        f"({', '.join(x.name for x in entries)}) that", "or name a new study with --study")
    if not any(dest.iterdir()):  # another worker creating the same study moved them first
        dest.rmdir()
        return None
    return dest


def load_frozen(studies_dir: Path | str, name: str) -> dict:
    path = study_dir(studies_dir, name) / "frozen.yaml"
    if not path.exists():  # a folder or a device there: read_text names it
        raise ImtuneError(f"no frozen settings for study {name!r} ({path} does not exist; run `tune` first)")
    from pipeline.fileio import load_yaml, read_text
    text = read_text(path, "frozen settings file")
    try:
        d = load_yaml(text, str(path))  # a hand-edited key given twice is one line, not the last one silently
    except yaml.YAMLError as e:
        raise ImtuneError(f"{path}: invalid YAML ({str(e).splitlines()[0]})") from None
    if d is None:  # empty, or comments only
        raise ImtuneError(f"{path} is empty (cut short?): write it again from the study's storage "
                          f"(`tune test --study {name} --storage URL` freezes it anew)")
    if not isinstance(d, dict) or "config" not in d:
        raise ImtuneError(f"{path}: not a frozen-settings file (no 'config')")
    check_frozen(d, path)  # its sections' types before its study name is read
    if d.get("study") != name:  # its test.json would go to that study's folder, and its numbers pass for it
        raise ImtuneError(f"{path} holds the frozen settings of study {d.get('study')!r}, not {name!r} (copied from "
                          f"another study?): test that study (`tune test --study {d.get('study')}`), or evaluate the "
                          f"file itself (`tune evaluate --config {path}`)")
    pipeline_from_dict(d["config"], where=str(path))  # a wrong value names the file, not "configuration"
    return d


def test_scene_names(frozen: dict, data_root: Path, scenes=None) -> list[str]:
    """The test scenes: given, else the study's, else the data set's test split; ImtuneError if none."""
    names = list(scenes) if scenes else list(frozen.get("data", {}).get("test_scenes") or [])
    if not names:
        from pipeline.data import default_splits
        names = list(default_splits(data_root).get("test", []))
    if not names:
        raise ImtuneError(f"no test scenes for study {frozen.get('study')!r} in {data_root} "
                          "(give --scenes or add a splits.yaml with 'test')")
    return names


def run_test(frozen: dict, data_root: Path | str, studies_dir: Path | str | None = None, *, scenes=None,
             cache=None, runs: int = 3, max_pairs: int | None = None, test_budget: float | None = None,
             progress: bool = False, reuse: bool = True, workers: int | None = None, reference: str | None = None,
             jobs: int | None = None,
             ci_resamples: int | None = None, gt_dir=None, compute: bool = True) -> dict | None:
    """Evaluate the frozen configuration with its task on the test scenes ``runs`` times (the k-th run with the
    task's k-th seed: ``Task.for_run``) and aggregate (``Task.aggregate``: mean and std). Each run keeps its pair
    errors (``pair_errors``; multiview: its bags' pair errors, ``bag_errors``); the mean carries the 95% interval of ``tuner.select.test_interval`` (``interval``
    says how it accounts for the run-to-run variation; ``ci_resamples`` 0: none). ``reference`` (None: the
    paper defaults, "none", a config file or study: ``tuner.select.reference_config``) is evaluated on the same
    pairs and runs and compared by a paired bootstrap (``reference.comparison``). Writes
    ``<studies_dir>/<study>/test.json`` when ``studies_dir`` is given; with ``reuse``, an existing test.json for
    the same trial, configuration, task options and data is returned as is. ``max_pairs`` / ``workers``
    override the task's options (stereo pairs per scene; multiview bag processes). ``compute`` False: only that
    reusable test.json, or None when there is none (nothing evaluated, nothing written but a refreshed interval)."""
    from pipeline.cache import H5Cache
    from tuner.evaluate import load_scenes
    from tuner.formatting import ground_truth_origins
    from tuner.objective import ValidationSet
    from tuner.protocol import within_budget
    from tuner.version import code_version
    data_root = Path(data_root)
    names = test_scene_names(frozen, data_root, scenes)
    from tuner import select as sel
    task = task_of(frozen, max_pairs=max_pairs, workers=workers, progress=progress, ci_resamples=ci_resamples,
                   jobs=jobs)  # stereo pair processes: not a task option (the numbers do not depend on it)
    conf = pipeline_from_dict(frozen["config"])
    n_ci = int(getattr(task, "ci_resamples", 0) or 0)
    ref = sel.reference_config(frozen, reference, task)
    rtask = sel.reference_task_of(reference, task) if ref is not None else task  # "colmap": COLMAP's own pipeline
    tb = float(test_budget if test_budget is not None else frozen.get("budget", {}).get("test_seconds_per_pair", 1.0))
    vs = ValidationSet.from_scenes(load_scenes(data_root, names, split="test", gt_dir=gt_dir), task)
    out_path = study_dir(studies_dir, frozen["study"]) / "test.json" if studies_dir is not None else None
    ident = {"trial": frozen.get("trial"), "config": frozen["config"], "task_options": task.options(),
             "fingerprint": vs.fingerprint, "runs": int(runs), "test_budget": tb, "ci_resamples": n_ci,
             "reference": None if ref is None else ref[0].to_dict()}
    if ref is not None and rtask is not task:
        ident["reference"] = {**ident["reference"], "reference_task": rtask.options()}
    old = _previous_result(out_path, ident, frozen["study"]) if reuse else None
    if old is not None:
        changed = sel.refresh_intervals(old, n_ci)  # an earlier imtune's intervals
        changed = _refresh_std(old, task) or changed  # ... or its population std over runs
        if changed and out_path is not None:
            atomic_write(out_path, json.dumps(_plain(old), indent=2))
        return old
    if not compute:
        return None
    cache = cache if cache is not None else H5Cache()
    t_start = time.perf_counter()
    vs.prepare(conf, cache, progress=progress)
    results, errors = [], []
    it = range(int(runs))
    if progress:
        from tqdm.auto import tqdm
        it = tqdm(it, desc=f"test {frozen['study']}", unit="run", leave=False)
    for k in it:
        t, c = task.for_run(conf, k)
        res = t.evaluate(vs.scene_objs, c, cache)
        f = t.figures(res)
        f.update(run=k, seed=int(c.geometry.seed), task_options=t.options())
        subs = _submissions(res.records)
        if subs:  # reconstruction: where each dataset's submission.csv of this run went
            f["submissions"] = subs
        errors.append(sel.unit_errors(res.records))
        if errors[-1] is not None:  # [[scene, pair, err deg], ...] or multiview [[scene, size, bag, [errs]], ...]
            f[sel.errors_key(errors[-1])] = errors[-1]  # what the interval and paired comparisons read
        results.append(f)
    mean, std = task.aggregate(results)
    interval = sel.test_interval(mean, errors, n_ci)
    reference_out = None
    if ref is not None:  # the same pairs, runs and seeds with the reference configuration
        rconf, rlabel = ref
        vs.prepare(rconf, cache, progress=progress)
        rres, rerr = [], []
        for k in range(int(runs)):
            t, c = rtask.for_run(rconf, k)
            res = t.evaluate(vs.scene_objs, c, cache)
            f = t.figures(res)
            f.update(run=k, seed=int(c.geometry.seed))
            subs = _submissions(res.records)
            if subs:
                f["submissions"] = subs
            rerr.append(sel.unit_errors(res.records))
            if rerr[-1] is not None:
                f[sel.errors_key(rerr[-1])] = rerr[-1]
            rres.append(f)
        rmean, rstd = task.aggregate(rres)
        sel.test_interval(rmean, rerr, n_ci)
        cmp = sel.compare_reference(rerr, errors, n_ci or 2000)
        if cmp is None:  # no per-unit errors (reconstruction): the task's own comparison of the runs' figures
            cmp = task.compare_runs(rres, results)
        reference_out = {"label": rlabel, "spec": sel.reference_kind(reference, task), "config": rconf.to_dict(),
                         "objective": task.objective,
                         task.objective: rmean.get(task.objective), "mean": rmean, "std": rstd, "runs": rres,
                         "comparison": cmp,
                         "note": "" if cmp else f"no per-pair or per-bag errors in {task.name} records: no paired "
                                                  "comparison"}
    sec = task.budget_seconds(mean)  # the one feasibility rule, on the mean over runs
    out = _plain({
        "study": frozen["study"], "trial": frozen.get("trial"), "task": task.name, "task_options": task.options(),
        "objective": frozen.get("objective") or {"name": "mAA10"}, "feature": frozen.get("feature"), "num_features": frozen.get("num_features"), "ransac": frozen.get("ransac"),
        "params": frozen.get("params"), "fixed": frozen.get("fixed"),
        "data": {"root": str(data_root), "scenes": names, "fingerprint": vs.fingerprint, "pairs": vs.n_pairs,
                 **task.options(),
                 # where each test scene's poses come from: its own (laser scan, calibration) or imtune's SfM
                 "ground_truth": ground_truth_origins(vs.scene_objs)},
        "budget": {"test_seconds_per_pair": tb, "within_budget": within_budget(sec, tb),
                   "statistic": "median estimator CPU seconds per pair", "clock": "cpu"},
        "runs": results, "mean": mean, "std": std, "std_ddof": STD_DDOF, "interval": interval,
        "reference": reference_out,
        "validation": frozen.get("validation"),
        "notes": vs.notes,  # where the task could not follow its options on a scene (bag sizes above its images)
        "code_version": code_version(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "wall_seconds": time.perf_counter() - t_start,  # features, the runs and the reference's runs
        "identity": ident,
    })
    if out_path is not None and results and results[0].get("submissions"):
        sub = out_path.parent / "submission.csv"  # the frozen settings' first run, every test dataset in one file
        join_submissions(list(results[0]["submissions"].values()), sub)
        out["submission"] = str(sub)
    if out_path is not None:
        prev, _ = load_test_file(out_path, frozen["study"], refresh=False)
        if prev is not None and (prev.get("data") or {}).get("fingerprint") != vs.fingerprint:
            # another test set (`tune test --scenes` on one scene after the full test): kept, never replaced
            kept = keep_earlier_file(out_path)
            out["earlier_test"] = {"path": str(kept), "scenes": (prev.get("data") or {}).get("scenes"),
                                   "pairs": (prev.get("data") or {}).get("pairs"),
                                   "fingerprint": (prev.get("data") or {}).get("fingerprint")}
        atomic_write(out_path, json.dumps(out, indent=2))
    return out


def _submissions(records: list[dict]) -> dict:
    """{dataset: submission.csv path} of a run's records (the reconstruction task writes one per dataset)."""
    return {r["dataset"]: r["submission"] for r in records if r.get("submission") and r.get("dataset")}


def join_submissions(paths: list[str], out: Path) -> None:
    """One submission.csv of several datasets' files (the challenge's format: one header, a row per image, the
    dataset in its first column), written atomically."""
    lines: list[str] = []
    for i, p in enumerate(paths):
        text = Path(p).read_text().splitlines()
        lines += text if i == 0 else text[1:]
    atomic_write(out, "\n".join(lines) + "\n")


def _refresh_std(result: dict, task) -> bool:
    """Recompute the std over runs of a test result written before it was the sample std (``std_ddof`` missing:
    ddof 0, 0.82 of the sample std at 3 runs) from its runs' figures, its reference's too. Returns whether it
    changed the result (the caller rewrites the file)."""
    if result.get("std_ddof") == STD_DDOF or not result.get("runs"):
        return False
    try:
        result["std"] = task.aggregate(result["runs"])[1]
        ref = result.get("reference")
        if isinstance(ref, dict) and ref.get("runs"):
            ref["std"] = task.aggregate(ref["runs"])[1]
    except (TypeError, ValueError, KeyError, AttributeError):  # runs that are not figures: left as they are
        return False
    result["std_ddof"] = STD_DDOF
    return True


def keep_earlier_file(path: Path) -> Path:
    """Move ``path`` into ``<its folder>/earlier-<UTC time>/`` (:data:`EARLIER_PREFIX`); returns where it went."""
    path = Path(path)
    return _move_to_earlier(path.parent, [path], f"the earlier {path}", "then rerun") / path.name


def earlier_test_line(result: dict) -> str | None:
    """The warning line for a test result that set an earlier test.json of another test set aside, or None."""
    e = result.get("earlier_test")
    if not e:
        return None
    what = ", ".join(e.get("scenes") or []) or "other scenes"
    now = result.get("data") or {}
    if e.get("scenes") == now.get("scenes") and e.get("pairs") == now.get("pairs"):
        # same scenes and pair count: "another test set" named the very set just measured
        return (f"the study's earlier test.json measured the same scenes ({what}; {e.get('pairs')} pairs) with other "
                f"data (data fingerprint {e.get('fingerprint')}, now {now.get('fingerprint')}: other pairs or images, "
                "or a ground truth built or removed since: co-visibility from `tune data build-gt`): kept at "
                f"{e.get('path')}, not replaced")
    return (f"the study's earlier test.json measured another test set ({what}; {e.get('pairs')} pairs): kept at "
            f"{e.get('path')}, not replaced")


def test_summary(result: dict) -> dict:
    """The part of a test result stored in the study (what `tune results` reads)."""
    m = result.get("mean", {})
    scalars = {k: v for k, v in m.items() if k != "scenes" and not isinstance(v, (list, dict))}
    return {"trial": result.get("trial"), "task": result.get("task", "stereo"), "runs": len(result.get("runs", [])),
            "scenes": result["data"]["scenes"], **scalars,
            # where each test scene's poses come from (Scene.truth_origin); absent in a test.json written before
            "ground_truth": result["data"].get("ground_truth"),
            **{f"{k}_std": v for k, v in (result.get("std") or {}).items() if not isinstance(v, list)},
            "within_budget": result.get("budget", {}).get("within_budget"),
            **{k: v for k, v in m.items() if k.endswith("_ci")},  # 95% intervals of the mean over runs
            "reference": _reference_summary(result.get("reference")),
            "per_scene": {k: {kk: vv for kk, vv in v.items() if not isinstance(vv, (list, dict)) or kk.endswith("_ci")}
                          for k, v in m.get("scenes", {}).items()},
            "created": result.get("created")}


def _reference_summary(ref: dict | None) -> dict | None:
    if not ref:
        return None
    c = ref.get("comparison") or {}
    key = ref.get("objective") or "mAA10"
    return {"label": ref.get("label"), "mAA10": ref.get("mAA10"), **({key: ref.get(key)} if key != "mAA10" else {}),
            **{k: c.get(k) for k in ("difference", "ci", "p_value", "significant", "pairs", "datasets") if k in c}}


def study_data_root(frozen: dict, given=None) -> Path:
    """The data folder a study's test runs on: ``given`` (--data), else the one the study was tuned on. A recorded
    folder that is gone is an error naming it, never a silent switch to whatever data ``tune`` would find now
    (another data set with other scenes would give numbers that look like this study's)."""
    if given:
        return Path(given)
    recorded = (frozen.get("data") or {}).get("root")
    if recorded and Path(recorded).is_dir():
        return Path(recorded)
    from tuner.options import resolve_data
    if not recorded:  # a frozen file that does not say: the data `tune` finds, as for any command
        return resolve_data(None)
    raise ImtuneError(f"the data folder study {frozen.get('study')!r} was tuned on, {recorded}, does not exist (moved "
                      "or deleted?): give --data DIR, the folder that holds its scenes now")


def run_test_for_study(study, frozen: dict, studies_dir, *, data_root=None, scenes=None, cache=None, runs: int = 3,
                       max_pairs=None, test_budget=None, progress: bool = False, reuse: bool = True,
                       workers: int | None = None, reference: str | None = None,
                       ci_resamples: int | None = None, jobs: int | None = None, gt_dir=None) -> dict:
    """:func:`run_test` and store its summary in the study's user attribute ``test``."""
    root = study_data_root(frozen, data_root)
    result = run_test(frozen, root, studies_dir, scenes=scenes, cache=cache, runs=runs, max_pairs=max_pairs,
                      test_budget=test_budget, progress=progress, reuse=reuse, workers=workers, reference=reference,
                      jobs=jobs, ci_resamples=ci_resamples, gt_dir=gt_dir)
    study.set_user_attr("test", test_summary(result))
    return result
