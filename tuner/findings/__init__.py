"""The paper's findings, checked on your data: `tune findings`.

    from tuner.findings import FindingsSettings, run_findings
    out = run_findings(FindingsSettings(data_root=Path("data/strecha"), quick=True, only=[1, 4]))
    out["findings"][0]["verdict"]      # "holds" | "does not hold" | "inconclusive" | "not run" | "not run yet"
    out["findings"][0]["this_run"]     # "ran" (selected) | "reused" (from its finished studies) | "not run yet"
    out["findings"][0]["measured"]["studies"]["tuned"]["ran_now"]  # {"trials": 0, "test": False}: nothing added
    out["report"]                      # <studies dir>/findings/report.html (report.md, findings.json beside it)

Each finding (:data:`tuner.findings.definitions.FINDINGS`) names its studies; each study is an ordinary imtune
study in the storage, tuned on the validation scenes and tested on the test scenes (``tuner.study.tune``), with
a deterministic name, so a rerun reuses finished studies and several workers on one storage share the work.
The verdict rules are in :mod:`tuner.findings.analysis`; the report writer in :mod:`tuner.findings.report`.
"""
from __future__ import annotations

import time
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.findings.analysis import NOT_RUN, NOT_RUN_YET, analyse
from tuner.findings.definitions import BY_ID, FINDINGS, Finding, StudySpec  # noqa: F401
from tuner.findings.runner import FindingsSettings, StudyOutcome, findings_command, reuse_study, run_study, study_name  # noqa: F401

#: ``this_run`` of a finding in findings.json: its studies run (or resumed, or reused by `tune`) by this invocation;
#: not selected (--only) and re-analysed from its finished studies; not selected and not all of them finished
THIS_RUN_RAN, THIS_RUN_REUSED = "ran", "reused"

__all__ = ["FindingsSettings", "run_findings", "FINDINGS", "BY_ID", "parse_only", "check_scenes", "check_settings"]


def parse_only(text: str | None) -> list[int] | None:
    """``--only 1,4`` -> [1, 4]; one-line ImtuneError naming a bad id."""
    if not text:
        return None
    out = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        try:
            i = int(part)
        except ValueError:
            raise ImtuneError(f"--only {text!r}: {part!r} is not a finding id (ids 1-{len(FINDINGS)})") from None
        if i not in BY_ID:
            raise ImtuneError(f"--only {text!r}: no finding {i} (ids 1-{len(FINDINGS)})")
        if i not in out:
            out.append(i)
    if not out:
        raise ImtuneError(f"--only {text!r}: no finding id given (ids 1-{len(FINDINGS)})")
    return out


def check_settings(fs: FindingsSettings) -> None:
    """The Python caller's values, checked (and normalised in place) before any study, as the CLI's options are: a
    one-line ImtuneError naming the FindingsSettings field. Without it ``only=[]`` ran all twelve findings,
    ``only=[99]`` was a KeyError, ``trials=0`` / ``budget=-1`` / ``jobs=0`` left every study "not run", ``trials=2.5``
    ran, ``n_resamples=0`` failed in scipy after every study, and ``val_scenes="fountain-P11"`` was read letter by
    letter."""
    import math

    from tuner.argtypes import MAX_RESAMPLES, MIN_RESAMPLES

    def bad(field: str, want: str, v) -> ImtuneError:
        return ImtuneError(f"FindingsSettings.{field} must be {want}, got {v!r}")

    if fs.only is not None:
        if isinstance(fs.only, str):
            fs.only = parse_only(fs.only) or None
        else:
            ids = list(fs.only) if isinstance(fs.only, (list, tuple, set, frozenset)) else None
            if not ids or any(isinstance(i, bool) or not isinstance(i, int) or i not in BY_ID for i in ids):
                raise bad("only", f"None (every finding) or a non-empty list of finding ids 1-{len(FINDINGS)}",
                          fs.only)
            fs.only = list(dict.fromkeys(ids))
    for k in ("trials", "max_pairs", "test_runs", "jobs"):
        v = getattr(fs, k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise bad(k, f"None ({'the default' if k == 'jobs' else 'the mode' + chr(39) + 's value'}) or an integer "
                      ">= 1", v)
    for k in ("budget", "test_budget"):
        v = getattr(fs, k)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise bad(k, "a finite number of seconds per pair > 0", v)
    from tuner.replicates import MAX_REPLICATES
    v = fs.replicates
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_REPLICATES:
        raise bad("replicates", f"an integer from 1 to {MAX_REPLICATES}", v)
    v = fs.n_resamples
    if isinstance(v, bool) or not isinstance(v, int) or not MIN_RESAMPLES <= v <= MAX_RESAMPLES:
        raise bad("n_resamples", f"an integer from {MIN_RESAMPLES} to {MAX_RESAMPLES:,}", v)
    for k in ("val_scenes", "test_scenes"):
        v = getattr(fs, k)
        if isinstance(v, str):  # "a,b" as on the command line, not the letters of one name
            setattr(fs, k, [n.strip() for n in v.split(",") if n.strip()] or None)
        elif v is not None and (not isinstance(v, (list, tuple)) or not all(isinstance(n, str) for n in v)):
            raise bad(k, "None (the data's split) or a list of scene names", v)
    fs.data_root = Path(fs.data_root)


def resolved_splits(fs: FindingsSettings) -> tuple[list, list, str]:
    """(validation scenes, test scenes, where they come from) as the studies will use them: --val-scenes /
    --test-scenes, else the data folder's split (``splits.yaml``, or the default one: see
    :func:`pipeline.data.default_splits`)."""
    from pipeline.data import SPLITS_FILE, default_splits
    splits = default_splits(fs.data_root)
    val = list(fs.val_scenes or splits.get("val") or [])
    test = list(fs.test_scenes or splits.get("test") or [])
    split = SPLITS_FILE if (Path(fs.data_root) / SPLITS_FILE).is_file() else "the default split"
    given = [f for f, v in (("--val-scenes", fs.val_scenes), ("--test-scenes", fs.test_scenes)) if v]
    source = " and ".join(given) + (f", else {split}" if len(given) == 1 else "") if given else split
    return val, test, source


def check_scenes(fs: FindingsSettings) -> str | None:
    """Why no finding can run on this data (no validation or no test scene), else None. A folder that holds no
    data set, or an unreadable ``splits.yaml``, is the user's error: its ImtuneError propagates (one line, exit 2),
    it is not twelve findings "not run"."""
    val, test, _ = resolved_splits(fs)
    if not val:
        return f"too few scenes: {fs.data_root} has no validation scene to tune on"
    if not test:
        from pipeline.data import default_splits
        every = {n for names in default_splits(fs.data_root).values() for n in names}
        if len(every) <= 1:  # a split cannot help: nothing is left to test on
            return (f"too few scenes: {fs.data_root} holds one scene ({', '.join(val)}); the findings tune on one "
                    "scene and measure on another: add a second scene folder beside it (for pairs lists, a second "
                    "folder with its own pairs file), or point --data at a folder of several scenes")
        return (f"too few scenes: {fs.data_root} has no test scene to measure on (validation: {', '.join(val)}); "
                "add a splits.yaml with 'test', or --test-scenes NAME[,...]")
    return None


def preflight(fs: FindingsSettings) -> None:
    """Fail fast, before any study, on what would stop every one of them (a user's error, not a limit of the data:
    a one-line ImtuneError naming the culprit and the fix): the studies folder cannot be created, the storage
    cannot be opened, the cache folder cannot be created or written (every study would be "not run"), a
    ``--val-scenes`` / ``--test-scenes`` name is unknown, or a scene is both a validation and a test scene (tuning
    on the scenes a finding is measured on would overstate every tuned number)."""
    import os

    from tuner.evaluate import load_scenes
    from tuner.storage import open_storage
    d = Path(fs.studies_dir)
    try:
        d.mkdir(parents=True, exist_ok=True)
        if not os.access(d, os.W_OK):
            raise PermissionError(13, "Permission denied")
    except OSError as e:
        raise ImtuneError(f"cannot create the studies folder {d}: {e.strerror or e}; choose another with "
                          "--studies-dir (or $IMTUNE_STUDIES)") from None
    st = open_storage(fs.storage, heartbeat=None, studies_dir=d)  # ImtuneError: unreachable, malformed, ...
    engine = getattr(st, "engine", None)
    if engine is not None:
        engine.dispose()
    from pipeline.cache import H5Cache
    H5Cache(fs.cache_dir).check_writable()  # ImtuneError naming the folder: a file in the way, no permission, ...
    for flag, split, names in (("--val-scenes", "val", fs.val_scenes), ("--test-scenes", "test", fs.test_scenes)):
        if names:
            try:
                load_scenes(Path(fs.data_root), list(names), split=split, ground_truth=False)
            except ImtuneError as e:
                raise ImtuneError(f"{flag}: {e}") from None
    val, test, _ = resolved_splits(fs)
    both = [n for n in test if n in val]
    if both:
        raise ImtuneError(f"scene {', '.join(both)} is both a validation and a test scene: the findings tune on the "
                          "validation scenes and measure on the test scenes; choose disjoint --val-scenes and "
                          "--test-scenes")
    # every finding tunes stereo studies on the validation scenes and tests them on the test scenes: a scene the
    # stereo task cannot evaluate (no ground truth: a folder of images before `tune data build-gt`) stops them all
    from pipeline.tasks import make_task
    from tuner.preflight import check_task_scene
    stereo = make_task("stereo")
    for role, flag, split, names in (("validation", "--val-scenes", "val", val), ("test", "--test-scenes", "test", test)):
        for sc in load_scenes(Path(fs.data_root), list(names), split=split):
            check_task_scene(stereo, sc, role, f"or choose other {role} scenes with {flag}")


def _reuse_outcomes(f, fs: FindingsSettings, cache, done: dict, reused: dict) -> dict:
    """role -> outcome of a finding this run does not select: a study this run ran (``done``), else
    :func:`reuse_study` (once per study and need)."""
    needs_regions = f.rule == "regions"
    outcomes = {}
    for role, spec in f.studies.items():
        name = study_name(spec, fs)
        o = done.get(name)
        if o is None or (needs_regions and o.ok and o.val_ci is None):
            key = (name, needs_regions)
            if key not in reused:
                reused[key] = reuse_study(spec, fs, cache, need_regions=needs_regions)
            o = reused[key]
        outcomes[role] = o
    return outcomes


def run_findings(fs: FindingsSettings, write: bool = True) -> dict:
    """Run (or resume) the studies of the selected findings (``fs.only``; None: all), analyse them and write the
    report. Every finding is reported: one not selected is re-analysed from its studies in the storage when all
    of them are finished (:func:`reuse_study`: no trial, no test run), and is otherwise "not run yet" with the
    command that runs it. Returns ``{"findings": [{"id", "claim", "paper", "measured", "difference", "ci",
    "p_value", "verdict", "studies", "this_run"}], "report": PATH}`` (the object findings.json holds), the
    findings in id order; ``this_run``: "ran" (selected), "reused" (not selected, from its finished studies) or
    "not run yet"."""
    from pipeline.cache import H5Cache
    from tuner.storage import default_studies_dir
    t0 = time.perf_counter()
    fs.studies_dir = Path(fs.studies_dir) if fs.studies_dir else default_studies_dir()
    check_settings(fs)
    selected = [BY_ID[i] for i in (fs.only or [f.id for f in FINDINGS])]
    if isinstance(fs.seed, bool) or not isinstance(fs.seed, int) or fs.seed < 0:
        # numpy's generators (the bootstrap) take no negative seed: found only after every study had run
        raise ImtuneError(f"seed must be an integer >= 0, got {fs.seed!r}")
    from pipeline.config import check_seed
    check_seed("seed", fs.seed)  # <= SEED_MAX: a larger one repeats a smaller one's runs
    if write:
        from tuner.findings.report import check_outputs
        check_outputs(fs.studies_dir)
    no_data = check_scenes(fs)
    if no_data is None:
        preflight(fs)
    cache = H5Cache(fs.cache_dir)
    done: dict[str, StudyOutcome] = {}  # study name -> outcome (studies shared between findings run once)
    ran: dict[int, dict] = {}  # finding id -> role -> outcome, for the findings this run runs
    for f in selected:
        fs.say(f"finding {f.id}: {f.title}")
        outcomes = {}
        if no_data is None:
            needs_regions = f.rule == "regions"
            for role, spec in f.studies.items():
                name = study_name(spec, fs)
                o = done.get(name)
                if o is None or (needs_regions and o.ok and o.val_ci is None):
                    o = run_study(spec, fs, cache, need_regions=needs_regions)
                    done[name] = o
                    if not o.ok:
                        fs.say(f"  {name}: not run ({o.reason})")
                outcomes[role] = o
        ran[f.id] = outcomes
    # every finding is reported: those not selected from their studies when all are finished (reuse only)
    reused: dict[tuple, StudyOutcome] = {}
    results = []
    for f in FINDINGS:
        outcomes, this_run = ran.get(f.id), THIS_RUN_RAN
        if outcomes is None:
            this_run = THIS_RUN_REUSED if no_data is None else NOT_RUN_YET
            outcomes = _reuse_outcomes(f, fs, cache, done, reused) if no_data is None else {}
        if no_data is not None:
            a = {"measured": {"reason": no_data}, "difference": None, "ci": None, "p_value": None, "verdict": NOT_RUN}
        elif any(o.pending for o in outcomes.values()):
            this_run = NOT_RUN_YET
            waiting = {role: o.pending for role, o in outcomes.items() if o.pending}
            cmd = findings_command(fs, [f.id])
            a = {"measured": {"reason": "not run yet: " + "; ".join(f"{r}: {w}" for r, w in waiting.items())
                                        + f"; run it with: {cmd}", "pending": waiting, "command": cmd},
                 "difference": None, "ci": None, "p_value": None, "verdict": NOT_RUN_YET}
        else:
            a = analyse(f, outcomes, n_resamples=fs.n_resamples, seed=fs.seed)
        a["measured"]["rule"] = f.rule
        if f.notes:
            a["measured"]["notes"] = f.notes
        ok = a["verdict"] != NOT_RUN_YET and outcomes
        results.append({"id": f.id, "claim": f.claim, "paper": f.paper, "measured": a["measured"],
                        "difference": a["difference"], "ci": a["ci"], "p_value": a["p_value"],
                        "verdict": a["verdict"],
                        "studies": [r.name for o in outcomes.values() if o.ok for r in o.replicates()] if ok else [],
                        "this_run": this_run})
        if f.id in ran or a["verdict"] != NOT_RUN_YET:
            fs.say(f"finding {f.id}{'' if f.id in ran else ' (not selected: from its finished studies)'} "
                   f"-> {a['verdict']}")
    out = {"findings": results, "report": None}
    if write:
        from tuner.findings.report import write_report
        out["report"] = str(write_report(out, fs, seconds=time.perf_counter() - t0))
    return out
