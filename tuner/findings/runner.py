"""Run the studies of the findings: each an ordinary imtune study (``tuner.study.tune``: create or resume,
calibrate, trials, freeze, test), then the per-pair records the statistics need.

Per-pair test records come from the study's ``test.json`` when its runs carry them (``pair_errors`` triples or
``pair_records``); otherwise the frozen configuration is evaluated again on the same test pairs with the same
run seeds (``Task.for_run``) and the records are kept in ``<studies dir>/findings/records/<study>-test.json``,
keyed by the test result's identity (trial, configuration, data, runs), so a rerun reads them back. Each run's
mAA(10) from the records is checked against ``test.json``'s; a mismatch is reported, never hidden.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import ImtuneError, UnavailableError
from tuner.findings.definitions import StudySpec

QUICK = {"num_features": 2048, "trials": 10, "max_pairs": 12, "test_runs": 1,
         "multiview_bags": ((5, 6), (10, 3))}
FULL = {"num_features": 8000, "trials": None, "max_pairs": None, "test_runs": 3, "multiview_bags": None}


@dataclass
class FindingsSettings:
    """What `tune findings` runs with. ``trials`` / ``max_pairs`` / ``test_runs`` None: the mode's value
    (:data:`QUICK` with ``quick``, else :data:`FULL`: the protocol's 50 trials, every pair, 3 test runs)."""
    data_root: Path
    storage: str | None = None
    studies_dir: Path | None = None
    quick: bool = False
    only: list | None = None
    jobs: int | None = None
    trials: int | None = None
    max_pairs: int | None = None
    test_runs: int | None = None
    cache_dir: str | None = None
    seed: int = 0
    budget: float = 0.5
    test_budget: float = 1.0
    val_scenes: list | None = None
    test_scenes: list | None = None
    n_resamples: int = 2000
    replicates: int = 1  # K tuning replicates of every stereo study (tuner.replicates): verdicts hold the tuning variance
    progress: bool = True
    log: object = None
    _data_tag: str | None = field(default=None, init=False, repr=False, compare=False)

    def mode(self) -> dict:
        m = dict(QUICK if self.quick else FULL)
        for k in ("trials", "max_pairs", "test_runs"):
            if getattr(self, k) is not None:
                m[k] = getattr(self, k)
        m["trials_effective"] = m["trials"] or 50
        return m

    def say(self, msg: str) -> None:
        if self.log is not None:
            self.log(msg)
        elif self.progress:
            import sys
            print(msg, file=sys.stderr, flush=True)


@dataclass
class StudyOutcome:
    """One study's results (or why it could not run). ``test_runs``: per run, its stereo pair records."""
    spec: StudySpec
    name: str
    ok: bool = False
    reason: str = ""
    frozen: dict | None = None
    test: dict | None = None
    test_path: str | None = None
    test_runs: list | None = None
    records_note: str = ""
    attrs: dict = field(default_factory=dict)
    trials: list = field(default_factory=list)  # (params, value) of feasible COMPLETE trials
    over_budget: int = 0  # COMPLETE trials over the budget B (infeasible)
    best: tuple | None = None  # (params, value) of the best feasible trial
    val_ci: list | None = None  # 95% interval of the best trial's validation mAA(10)
    pending: str = ""  # reuse only (reuse_study): why the study is not finished yet ("" when it is, or cannot run)
    compute: dict = field(default_factory=dict)  # the study's own seconds: calibration, trials, test (see below)
    # what this invocation added to the study (run_study only; None when reused): {"trials": n trials this process
    # ran, "test": whether it wrote the test runs now}. A rerun of finished studies adds nothing, and says so.
    ran_now: dict | None = None
    # the outcomes of tuning replicates 2..K of this study (``--replicates K``; this outcome is replicate 1)
    others: list = field(default_factory=list)

    def replicates(self) -> list:
        """Every replicate's outcome, this one (replicate 1) first."""
        return [self, *self.others]


def canonical_spec(spec: StudySpec, default_features: int) -> StudySpec:
    """The first spec of the table (in finding order) with ``spec``'s configuration: it names the one study they
    share, so no configuration is tuned twice under two names."""
    from tuner.findings.definitions import FINDINGS
    want = spec.configuration(default_features)
    for f in FINDINGS:
        for other in f.studies.values():
            if other.configuration(default_features) == want:
                return other
    return spec


#: the budget (s per pair) the names of findings studies leave unsaid: the protocol's
DEFAULT_BUDGET = 0.5


def data_tag(fs: FindingsSettings) -> str:
    """8 hex naming the validation data: its scenes' names and each scene's images (names and sizes,
    :func:`pipeline.data.ground_truth.scene_content_id`, stable across copies of the data folder). Studies of
    other data get other names, so findings of several data sets share one storage (a rerun on other data found
    every study "exists with different validation data"). "" when the validation scenes cannot be loaded (the
    run stops on that elsewhere)."""
    if fs._data_tag is None:
        import hashlib

        from pipeline.data.ground_truth import scene_content_id
        from tuner.evaluate import load_scenes
        from tuner.findings import resolved_splits
        try:
            val, _, _ = resolved_splits(fs)
            scenes = load_scenes(Path(fs.data_root), val, split="val", ground_truth=False) if val else []
        except ImtuneError:
            return ""
        h = hashlib.sha1()
        for sc in sorted(scenes, key=lambda x: x.name):
            h.update(f"{sc.name}\0{scene_content_id(sc)}\n".encode())
        fs._data_tag = h.hexdigest()[:8] if scenes else ""
    return fs._data_tag


def study_name(spec: StudySpec, fs: FindingsSettings) -> str:
    """Deterministic: ``findings-<owner>-<variant>-<feature>-<n>-<ransac>`` of the :func:`canonical_spec`, plus
    ``-p<N>`` when the pairs per scene are capped (a capped study is a different study: its task options differ),
    ``-B<s>`` for a budget other than the protocol's 0.5 s, and ``-v<tag>`` naming the validation data
    (:func:`data_tag`)."""
    m = fs.mode()
    name = canonical_spec(spec, m["num_features"]).name(m["num_features"])
    name += f"-p{m['max_pairs']}" if m["max_pairs"] else ""
    name += f"-B{float(fs.budget):g}" if float(fs.budget) != DEFAULT_BUDGET else ""
    tag = data_tag(fs)
    return name + (f"-v{tag}" if tag else "")


def base_config(spec: StudySpec, num_features: int):
    from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
    return PipelineConfig(
        feature=FeatureConfig(name=spec.feature, num_features=int(num_features), upright=spec.upright,
                              upright_plus=spec.upright_plus, mr_size=spec.mr_size),
        matching=MatchConfig(ratio=1.0, strategy=spec.strategy, fginn=spec.fginn, method=spec.method),
        geometry=GeometryConfig(ransac=spec.ransac, threshold=1.0, confidence=spec.confidence, max_iters=1))


def unavailable(spec: StudySpec) -> str | None:
    """Why the study's feature or estimator cannot run here (missing weights, packages), else None."""
    from pipeline.features import resolve_feature
    from pipeline.geometry import get_estimator
    try:
        resolve_feature(spec.feature).check_available()
        get_estimator(spec.ransac)
    except UnavailableError as e:
        return str(e)
    except ImtuneError as e:
        return str(e)
    return None


def findings_gt_dir(fs: FindingsSettings) -> Path:
    """Where `tune findings` keeps the ground truth it builds for the multiview study: its own folder, so the stereo
    studies (whose pairs a built ground truth would filter by co-visibility) see the data exactly as `tune` does."""
    from tuner.storage import default_studies_dir
    return Path(fs.studies_dir or default_studies_dir()) / "findings" / "gt"


def ensure_multiview_ground_truth(spec: StudySpec, fs: FindingsSettings) -> None:
    """The multiview task samples its bags from 3D points: build the validation scenes' ground truth (pycolmap:
    triangulation with the known poses held fixed, or SfM without poses; what `tune data build-gt` does) into
    :func:`findings_gt_dir` when it is missing. Reused on a rerun."""
    from pipeline.tasks import TASKS
    if not TASKS.get(spec.task).needs_points:  # only a task choosing its units from 3D points (multiview bags)
        return
    from pipeline.data.ground_truth import GTConfig, build_ground_truth, gt_path
    from tuner.evaluate import load_scenes
    gt_dir = findings_gt_dir(fs)
    for sc in load_scenes(Path(fs.data_root), fs.val_scenes, split="val", ground_truth=False):
        if not gt_path(sc, gt_dir).is_file():
            fs.say(f"{sc.name}: building the multiview ground truth (pycolmap) into {gt_dir}")
        build_ground_truth(sc, gt_dir, GTConfig())


def multiview_bags(fs: FindingsSettings) -> tuple:
    """The (size, count) bags of the multiview study: --quick's, else the protocol's."""
    from pipeline.tasks.multiview import MultiviewConfig
    return tuple(fs.mode()["multiview_bags"] or MultiviewConfig().bags)


def multiview_notes(fs: FindingsSettings) -> list[str]:
    """The multiview task's notes on the validation scenes (bag sizes above a scene's images), for the report."""
    from pipeline.tasks.multiview import MultiviewConfig, MultiviewTask
    from tuner.evaluate import load_scenes
    task = MultiviewTask(MultiviewConfig(bags=multiview_bags(fs)))
    try:
        scenes = load_scenes(Path(fs.data_root), fs.val_scenes, split="val", ground_truth=False)
    except ImtuneError:  # the report of a run that could not load them says why elsewhere
        return []
    return task.notes(scenes)


def tune_settings(spec: StudySpec, fs: FindingsSettings):
    from tuner.study import TuneSettings
    m = fs.mode()
    kw = {}
    names = {f.name for f in dataclasses.fields(TuneSettings)}
    if fs.jobs is not None and "jobs" in names:  # the pair pool (issue 10), where this tree has it
        kw["jobs"] = int(fs.jobs)
    from pipeline.tasks import TASKS
    task = TASKS.get(spec.task)
    mv = None
    if m["multiview_bags"]:  # the multiview task's bags (a task that has no bags ignores this option)
        from pipeline.tasks.multiview import MultiviewConfig
        mv = MultiviewConfig(bags=tuple(m["multiview_bags"]))
    return TuneSettings(
        base=base_config(spec, spec.n_features(m["num_features"])), data_root=Path(fs.data_root), task=spec.task,
        study_name=study_name(spec, fs), storage=fs.storage, studies_dir=fs.studies_dir,
        fixes=[f"{k}={v}" for k, v in spec.fixes], n_trials=m["trials"], seed=fs.seed, budget=fs.budget,
        test_budget=fs.test_budget, val_scenes=fs.val_scenes, test_scenes=fs.test_scenes,
        max_pairs=m["max_pairs"], cache_dir=fs.cache_dir, progress=fs.progress, test=spec.test,
        test_runs=m["test_runs"], multiview=mv, log=fs.log,
        reference="none",  # the findings compare their own studies: no paper-defaults rerun of every test
        # the multiview study searches r alone: its space's grid (8 values, as the paper swept r), not 50 TPE trials
        # of ~110 COLMAP reconstructions each (hours on 2 cores for one 1-D curve)
        sampler="grid" if task.sweep else "tpe",
        name_warnings=True,  # twenty studies in one run: a warning says whose optimum it is about
        gt_dir=str(findings_gt_dir(fs)) if task.needs_points else None, **kw)


# ------------------------------------------------------------------------------------------ records

def _plain(o):
    from tuner.freeze import _plain as plain
    return plain(o)


def _err(e) -> float:
    return math.inf if e is None or e == "inf" else float(e)


def records_from_test(test: dict) -> list | None:
    """Per-run stereo pair records stored in a test result (``pair_errors`` [scene, pair, err] triples or
    ``pair_records`` dicts), or None when a run has neither."""
    out = []
    for r in test.get("runs") or []:
        if r.get("pair_errors") is not None:
            out.append([{"scene": sc, "pair": pr, "err": _err(e)} for sc, pr, e in r["pair_errors"]])
        elif r.get("pair_records") is not None:
            out.append([{"scene": x["scene"], "pair": x["pair"], "err": _err(x["err"])} for x in r["pair_records"]])
        else:
            return None
    return out or None


def _read_json(path: Path) -> dict | None:
    """A records file of ours as a dict; None when absent, unreadable or not a JSON object (then recomputed)."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def _error_value(e) -> float:
    """A stored rotation/translation error (deg): a number >= 0, inf, or None/"inf" for a failed pair."""
    v = _err(e)
    if isinstance(e, bool) or not (v >= 0):  # NaN and negatives are no error
        raise ValueError(f"error {e!r}")
    return v


def _cached_runs(old: dict | None, ident, runs: int) -> list | None:
    """Per-run pair records cached in a ``records/<study>-test.json`` for this identity, or None when there are
    none or they are not of the shape this module writes (cut short, hand-edited: recomputed, never trusted)."""
    if not old or old.get("identity") != ident:
        return None
    try:
        out = [[{"scene": str(r["scene"]), "pair": str(r["pair"]), "err": _error_value(r["err"])} for r in run]
               for run in old["runs"]]
    except (KeyError, TypeError, ValueError, AttributeError):
        return None
    return out if len(out) == int(runs) and all(out) else None


def _cached_val_records(old: dict | None, ident, bags: bool) -> list | None:
    """Validation records cached in ``records/<study>-val.json`` for this identity, checked like
    :func:`_cached_runs` (stereo: scene, err; multiview bags: scene, bag_size, errors)."""
    if not old or old.get("identity") != ident or not isinstance(old.get("records"), list) or not old["records"]:
        return None
    try:
        for r in old["records"]:
            if not isinstance(r, dict) or not isinstance(r["scene"], str):
                return None
            if bags:
                if not isinstance(r["errors"], list) or isinstance(r["bag_size"], bool):
                    return None
                int(r["bag_size"])
                [_error_value(e) for e in r["errors"]]
            else:
                _error_value(r["err"])
    except (KeyError, TypeError, ValueError):
        return None
    return old["records"]


def _evaluate_runs(frozen: dict, data_root: Path, scene_names: list, split: str, runs: int, cache) -> list:
    """[(records, summary), ...]: the frozen configuration on ``scene_names``, run k with the task's k-th seed
    (the very loop of :func:`tuner.freeze.run_test`, keeping the records)."""
    from tuner.evaluate import load_scenes
    from tuner.freeze import pipeline_from_dict, task_of
    from tuner.objective import ValidationSet
    task = task_of(frozen)
    conf = pipeline_from_dict(frozen["config"])
    vs = ValidationSet.from_scenes(load_scenes(data_root, scene_names, split=split), task)
    vs.prepare(conf, cache)
    out = []
    for k in range(int(runs)):
        t, c = task.for_run(conf, k)
        res = t.evaluate(vs.scene_objs, c, cache)
        out.append((res.records, dict(res.summary)))
    return out


def test_records(frozen: dict, test: dict, records_dir: Path, cache, compute: bool = True) -> tuple[list | None, str]:
    """(per-run pair records of the test result, note). See the module docstring. ``compute`` False: (None, "") when
    the records would have to be evaluated again."""
    stored = records_from_test(test)
    if stored is not None:
        return stored, "pair errors from test.json"
    path = records_dir / f"{test['study']}-test.json"
    ident = _plain(test.get("identity"))
    old = _read_json(path)
    cached = _cached_runs(old, ident, len(test["runs"]))
    if cached is not None:
        return cached, str(old.get("note", ""))
    if not compute:
        return None, ""
    fz = {"task": test.get("task", "stereo"), "task_options": test.get("task_options"), "config": frozen["config"]}
    got = _evaluate_runs(fz, Path(test["data"]["root"]), test["data"]["scenes"], "test", len(test["runs"]), cache)
    runs = [[{"scene": r["scene"], "pair": r["pair"], "err": _err(r["err"])} for r in recs] for recs, _ in got]
    diffs = [abs(float(s.get("mAA10", 0.0)) - float(tr.get("mAA10") or 0.0)) for (_, s), tr in zip(got, test["runs"])]
    worst = max(diffs) if diffs else 0.0
    note = ("pair errors re-evaluated (test.json has none); each run's mAA(10) equals test.json's"
            if worst <= 1e-9 else
            f"pair errors re-evaluated (test.json has none); mAA(10) differs from test.json by up to {worst:.4f} "
            "(the estimator is not deterministic here): intervals and paired tests use the re-evaluated errors")
    from pipeline.fileio import atomic_write
    atomic_write(path, json.dumps(_plain({"study": test["study"], "identity": ident, "note": note,
                                          "runs": [[{**r} for r in run] for run in runs]})))
    return runs, note


def validation_interval(study, frozen: dict, best, records_dir: Path, cache, n_resamples: int,
                        compute: bool = True) -> list | None:
    """95% interval of the best feasible trial's validation mAA(10): its own ``mAA10_ci`` attribute when the
    trial recorded one, else a bootstrap of its configuration's records re-evaluated on the validation pairs
    (cached in ``records/<study>-val.json``), shifted to the trial's value. ``compute`` False: None when the
    records are not cached (nothing evaluated)."""
    ci = best.user_attrs.get("mAA10_ci")
    if ci:
        return [float(ci[0]), float(ci[1])]
    from pipeline.metrics.uncertainty import bag_intervals, maa_intervals
    from tuner.freeze import pipeline_from_dict, task_of
    from tuner.protocol import config_for
    attrs = study.user_attrs
    base = pipeline_from_dict(attrs["pipeline"])
    fixed = dict(attrs["search_space_resolved"].get("fixed", {}))
    conf = config_for(base, {**fixed, **best.params}, seed=int(attrs.get("seed", 0)))
    path = records_dir / f"{study.study_name}-val.json"
    ident = _plain({"trial": best.number, "config": conf.to_dict(), "fingerprint": attrs.get("data_fingerprint")})
    task = task_of(attrs)
    recs = _cached_val_records(_read_json(path), ident, task.records_key == "bag_records")
    if recs is None and not compute:
        return None
    if recs is None:
        fz = {"task": attrs.get("task", "stereo"), "task_options": attrs.get("task_options"), "config": conf.to_dict()}
        (recs, _), = _evaluate_runs(fz, Path(frozen["data"]["root"]), attrs["data"]["val_scenes"], "val", 1, cache)
        from pipeline.fileio import atomic_write
        atomic_write(path, json.dumps(_plain({"study": study.study_name, "identity": ident, "records": recs})))
    if task.records_key == "bag_records":
        for r in recs:
            r["errors"] = [_err(e) for e in r["errors"]]
        iv = bag_intervals(recs, taus=(10,), n_resamples=n_resamples)
    else:
        for r in recs:
            r["err"] = _err(r["err"])
        iv = maa_intervals(recs, taus=(10,), n_resamples=n_resamples)
    # the interval's half-widths around its own point, placed at the trial's value (same pairs, same config)
    lo, hi = iv["mAA10_ci"]
    point = float(best.user_attrs.get("mAA10", best.value if best.value is not None else 0.0))
    centre = _point(recs, task)
    return [point - (centre - lo), point + (hi - centre)]


def _point(recs, task) -> float:
    import numpy as np

    from pipeline.metrics.uncertainty import maa_from_errors
    by: dict = {}
    if task.records_key == "bag_records":
        for r in recs:
            by.setdefault((r["scene"], r["bag_size"]), []).append(maa_from_errors(r["errors"], 10))
        scenes: dict = {}
        for (sc, _), v in by.items():
            scenes.setdefault(sc, []).append(float(np.mean(v)))
        return float(np.mean([np.mean(v) for v in scenes.values()])) if scenes else 0.0
    for r in recs:
        by.setdefault(r["scene"], []).append(r["err"])
    return float(np.mean([maa_from_errors(v, 10) for v in by.values()])) if by else 0.0


# ------------------------------------------------------------------------------------------ one study

def replicated(spec: StudySpec, fs: FindingsSettings) -> int:
    """How many tuning replicates the study of ``spec`` runs: ``fs.replicates`` for a task measured on pairs (the
    replicated interval pairs test pairs, :mod:`tuner.replicates`), 1 otherwise (the multiview study)."""
    from pipeline.tasks import task_class
    return int(fs.replicates) if task_class(spec.task).unit == "pairs" else 1


def _with_replicates(out: StudyOutcome, spec: StudySpec, fs: FindingsSettings, get) -> StudyOutcome:
    """``out`` (replicate 1) with the outcomes ``get(k)`` of replicates 2..K in ``out.others``. A replicate that did
    not run or is not finished makes the whole study so (its reason or pending, naming the replicate): a verdict on
    fewer replicates than asked would state an interval it does not have."""
    k_max = replicated(spec, fs)
    if k_max <= 1 or not out.ok:
        return out
    for k in range(2, k_max + 1):
        o = get(k)
        out.others.append(o)
        if not o.ok:
            out.ok = False
            if o.pending:
                out.pending = f"replicate {k} ({o.name}): {o.pending}"
            else:
                out.reason = f"replicate {k} ({o.name}): {o.reason}"
            break
    return out


def run_study(spec: StudySpec, fs: FindingsSettings, cache, need_regions: bool = False) -> StudyOutcome:
    """Create or resume the study of ``spec`` (and its replicates), run its missing trials, freeze, test; then its
    records."""
    out = _run_replicate(spec, fs, cache, need_regions, 1)
    return _with_replicates(out, spec, fs, lambda k: _run_replicate(spec, fs, cache, False, k))


def _run_replicate(spec: StudySpec, fs: FindingsSettings, cache, need_regions: bool, k: int) -> StudyOutcome:
    """:func:`run_study` of replicate ``k`` alone."""
    import optuna
    from optuna.trial import TrialState

    from tuner.freeze import study_dir
    from tuner.protocol import best_feasible, trial_within_budget
    from tuner.study import IncompatibleStudy, tune
    out, s = _open_outcome(spec, fs, k)
    if s is None:
        return out
    name = out.name
    started = _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0)
    try:
        ensure_multiview_ground_truth(spec, fs)
        res = tune(s)
    except UnavailableError as e:
        out.reason = str(e)
        return out
    except IncompatibleStudy as e:  # its name says data and budget: another pipeline or search space remains
        out.reason = _incompatible_reason(e)
        return out
    except ImtuneError as e:
        out.reason = f"could not run: {e}"
        out.compute = _spent(name, fs, Path(s.studies_dir))  # e.g. no feasible trial: it still cost its trials
        return out
    out.frozen, out.test = res["frozen"], res["test"]
    sdir = Path(s.studies_dir)
    records_dir = sdir / "findings" / "records"
    study = optuna.load_study(study_name=name, storage=_storage(fs, sdir))
    if out.test is None and spec.test:
        # tune() leaves the test to the last worker while other workers still run trials of this study; a
        # finding needs it now: test the current optimum (a later rerun re-tests if the optimum changes)
        out.test = _test_now(study, out.frozen, s)
    out.ran_now = {"trials": len(res["worker"]["trials_run"]), "test": _written_since(out.test, started)}
    out.attrs = dict(study.user_attrs)
    best = best_feasible(study)
    out.best = (dict(best.params), float(best.value)) if best is not None else None
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    out.trials = [(dict(t.params), float(t.value)) for t in complete if t.value is not None and trial_within_budget(t)]
    out.over_budget = sum(not trial_within_budget(t) for t in complete)
    if out.test is not None:
        out.test_path = str(study_dir(sdir, name) / "test.json")
        try:
            out.test_runs, out.records_note = test_records(out.frozen, out.test, records_dir, cache)
        except ImtuneError as e:
            out.reason = f"test records: {e}"
            out.compute = study_compute(study, out.test)  # frozen and tested: its compute counts all the same
            return out
    if need_regions and best is not None:
        out.val_ci = validation_interval(study, out.frozen, best, records_dir, cache, fs.n_resamples)
    out.compute = study_compute(study, out.test)
    out.ok = True
    return out


def _written_since(test: dict | None, started) -> bool:
    """Whether ``test`` (a test.json's content) was written at or after ``started`` (UTC, whole seconds): its
    ``created`` stamp, set when the runs are evaluated; a test.json reused from an earlier invocation is older."""
    try:
        return _dt.datetime.fromisoformat(str((test or {})["created"])) >= started
    except (KeyError, ValueError, TypeError):  # no stamp, not a date, or one without a time zone (not imtune's)
        return False


def _open_outcome(spec: StudySpec, fs: FindingsSettings, k: int = 1):
    """(the empty outcome of replicate ``k`` of the study, its TuneSettings); the settings are None when the study
    cannot run here (an unavailable feature: ``out.reason`` says why). Replicate k >= 2 is the study
    ``<name>-r<k>`` with its own sampler and estimator seeds (:func:`tuner.replicates.replicate_settings`)."""
    from tuner.replicates import replicate_name
    out = StudyOutcome(spec=spec, name=replicate_name(study_name(spec, fs), k))
    out.reason = unavailable(spec) or ""
    if out.reason:
        return out, None
    s = tune_settings(spec, fs)
    if k > 1:
        from tuner.replicates import replicate_settings
        s = replicate_settings(s, k, s.study_name)
    return out, s


def _incompatible_reason(e) -> str:
    """A findings study's name is fixed: one of that name with other settings asks for a storage of its own."""
    return (f"could not run: {str(e).split('; rerun')[0]}; findings studies have fixed names: give this run a "
            "storage of its own (--studies-dir DIR or --storage URL)")


def reuse_study(spec: StudySpec, fs: FindingsSettings, cache, need_regions: bool = False) -> StudyOutcome:
    """:func:`_reuse_replicate` of every replicate of ``spec``'s study (see there)."""
    out = _reuse_replicate(spec, fs, cache, need_regions, 1)
    return _with_replicates(out, spec, fs, lambda k: _reuse_replicate(spec, fs, cache, False, k))


def _reuse_replicate(spec: StudySpec, fs: FindingsSettings, cache, need_regions: bool, k: int) -> StudyOutcome:
    """The outcome :func:`run_study` would give, read from the storage and the study's folder alone when the study
    is finished: it holds its target of finished trials, its current optimum has a reusable test.json (the one
    ``tune`` would reuse: same trial, configuration, test data and runs) and the records the statistics need are
    stored or cached. No trial, no test run, no evaluation, no ground truth built; nothing written to the storage.
    A study that is not finished comes back with ``pending`` saying why (``ok`` False); one that could not run
    here (an unavailable feature, a study of that name with other settings) with ``reason``, as from
    :func:`run_study`. `tune findings --only` re-analyses the findings it does not run this way."""
    import optuna
    from optuna.trial import TrialState

    from tuner.freeze import frozen_from_study, run_test, study_data_root, study_dir
    from tuner.protocol import best_feasible, trial_within_budget
    from tuner.space import SearchSpace
    from tuner.study import (
        IncompatibleStudy,
        check_compatible,
        load_study_space,
        open_validation,
        study_identity,
        trial_target,
    )
    out, s = _open_outcome(spec, fs, k)
    if s is None:
        return out
    name = out.name
    s.progress = False
    sdir = Path(s.studies_dir)
    try:
        study = optuna.load_study(study_name=name, storage=_storage(fs, sdir))
    except KeyError:
        out.pending = "no study of that name in the storage yet"
        return out
    attrs = dict(study.user_attrs)
    if not attrs.get("imtune"):
        out.pending = "the study is being created"
        return out
    try:
        task = s.make_task()
        space = load_study_space(s, task)
        vs = open_validation(s, task)  # the validation scenes' metadata (multiview: the 3D points built for it)
        base = dataclasses.replace(s.base, geometry=dataclasses.replace(s.base.geometry, seed=int(s.seed or 0)))
        check_compatible(name, attrs, study_identity(s, task, space, vs, base))
    except IncompatibleStudy as e:  # as run_study says it
        out.reason = _incompatible_reason(e)
        return out
    except ImtuneError as e:
        out.pending = f"its validation data cannot be read without running it ({e})"
        return out
    target = trial_target(s, SearchSpace.from_spec(attrs["search_space_resolved"]))
    finished = len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED)))
    if finished < target:
        out.pending = f"{finished} of {target} trial{'s' * (target != 1)} finished"
        return out
    best = best_feasible(study)
    if best is None:  # what tune() stops on
        from tuner.protocol import no_feasible_message
        out.reason = f"could not run: {no_feasible_message(study, attrs['budget']['seconds_per_pair'])}; run more trials"
        out.compute = study_compute(study, None)
        return out
    try:
        out.frozen = frozen_from_study(study, s.select)  # what freeze() writes, not written here
        if spec.test:
            out.test = run_test(out.frozen, study_data_root(out.frozen, s.data_root), sdir, scenes=s.test_scenes,
                                runs=s.test_runs, max_pairs=s.max_pairs, reuse=True, workers=s.workers,
                                reference=s.reference, jobs=s.jobs, ci_resamples=s.ci_resamples, gt_dir=s.gt_dir,
                                compute=False)
            if out.test is None:
                out.pending = f"its optimum (trial #{out.frozen['trial']}) has no test result yet"
                return out
    except ImtuneError as e:
        out.pending = f"its results cannot be read ({e})"
        return out
    records_dir = sdir / "findings" / "records"
    out.attrs = attrs
    out.best = (dict(best.params), float(best.value))
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    out.trials = [(dict(t.params), float(t.value)) for t in complete if t.value is not None and trial_within_budget(t)]
    out.over_budget = sum(not trial_within_budget(t) for t in complete)
    if out.test is not None:
        out.test_path = str(study_dir(sdir, name) / "test.json")
        out.test_runs, out.records_note = test_records(out.frozen, out.test, records_dir, cache, compute=False)
        if out.test_runs is None:
            out.pending = "the pair errors of its test are not stored yet"
            return out
    if need_regions:
        out.val_ci = validation_interval(study, out.frozen, best, records_dir, cache, fs.n_resamples, compute=False)
        if out.val_ci is None:
            out.pending = "the validation interval of its optimum is not computed yet"
            return out
    out.compute = study_compute(study, out.test)
    out.ok = True
    return out


def findings_command(fs: FindingsSettings, ids) -> str:
    """The `tune findings` command that runs findings ``ids`` with ``fs``'s settings (same studies, same storage; a
    storage URL's password masked)."""
    import shlex

    from tuner.findings.definitions import FINDINGS
    from tuner.storage import storage_label
    words = ["tune", "findings"] + (["--quick"] if fs.quick else [])
    words += ["--only", ",".join(str(i) for i in ids)] if len(ids) < len(FINDINGS) else []
    words += ["--data", str(fs.data_root)]
    if fs.studies_dir is not None:
        words += ["--studies-dir", str(fs.studies_dir)]
    if fs.storage:
        words += ["--storage", storage_label(fs.storage, fs.studies_dir)]
    for flag, v in (("--val-scenes", fs.val_scenes), ("--test-scenes", fs.test_scenes)):
        if v:
            words += [flag, ",".join(v)]
    if fs.cache_dir:
        words += ["--cache", str(fs.cache_dir)]
    for flag, v, default in (("--seed", fs.seed, 0), ("--replicates", fs.replicates, 1), ("--trials", fs.trials, None),
                             ("--max-pairs", fs.max_pairs, None), ("--test-runs", fs.test_runs, None),
                             ("--ci-resamples", fs.n_resamples, 2000)):
        if v != default:
            words += [flag, str(v)]
    cmd = " ".join(shlex.quote(w) for w in words)
    if float(fs.budget) != DEFAULT_BUDGET or float(fs.test_budget) != 1.0:  # no command-line flag: Python only
        cmd += (f" (with budget={fs.budget:g}, test_budget={fs.test_budget:g}: from Python, "
                f"run_findings(FindingsSettings(..., only={list(ids)})))")
    return cmd


def study_compute(study, test: dict | None) -> dict:
    """What the study cost, from its own records (so a run resumed across sessions still adds up): the budget
    calibration's seconds (``calibration_created`` identifies it: studies of one estimator share one), the summed
    durations of its COMPLETE and PRUNED trials (a FAIL trial is one a killed run left, its span the downtime), and
    the test's wall seconds (test.json's ``wall_seconds``; None for a test written before it was recorded, or for
    a study that runs no test, ``tested`` False: finding 6's multiview study)."""
    from optuna.trial import TrialState
    cal = ((study.user_attrs.get("budget") or {}).get("calibration") or {})
    trials = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED))
    secs = [(t.datetime_complete - t.datetime_start).total_seconds() for t in trials
            if t.datetime_start is not None and t.datetime_complete is not None]
    return {"calibration_seconds": cal.get("seconds"), "calibration_created": cal.get("created"),
            "trial_seconds": float(sum(secs)), "trials": len(secs),
            "tested": test is not None, "test_seconds": (test or {}).get("wall_seconds")}


def _spent(name: str, fs: FindingsSettings, sdir: Path) -> dict:
    """:func:`study_compute` of a study that ran (some of) its trials and then could not be frozen (no feasible
    trial: every one over the budget), which the run's compute must still count; {} when there is no such study
    in the storage (it failed before any trial) or the storage cannot be read."""
    import optuna
    try:
        study = optuna.load_study(study_name=name, storage=_storage(fs, sdir))
    except Exception:  # noqa: BLE001 - no study, or a storage the error above already explains
        return {}
    c = study_compute(study, None)
    return c if c["trials"] or c["calibration_seconds"] is not None else {}


def _test_now(study, frozen: dict, s) -> dict:
    """:func:`tuner.freeze.run_test_for_study` with the settings ``tune`` would use."""
    import inspect

    from pipeline.cache import H5Cache
    from tuner.freeze import run_test_for_study
    kw = dict(data_root=s.data_root, scenes=s.test_scenes, cache=H5Cache(s.cache_dir), runs=s.test_runs,
              max_pairs=s.max_pairs, progress=s.progress, reuse=True, workers=s.workers)
    if "jobs" in inspect.signature(run_test_for_study).parameters and getattr(s, "jobs", None) is not None:
        kw["jobs"] = s.jobs
    return run_test_for_study(study, frozen, s.studies_dir, **kw)


def _storage(fs: FindingsSettings, sdir: Path):
    from tuner.storage import open_storage
    return open_storage(fs.storage, heartbeat=None, studies_dir=sdir)
