"""The held-out verdict of reconstruction tuning (issue 44): a study tuned on validation datasets, frozen, and
tested against COLMAP out of the box (``--reference colmap``) on datasets it never saw.

    python benchmarks/reconstruction_heldout.py --data /tmp/imc-all --val imc2023_theather_imc2024_church,strecha-sparse \\
        --test imc2023_heritage --studies-dir /tmp/heldout-studies --write
    python benchmarks/reconstruction_heldout.py --data /tmp/imc-all --studies-dir /tmp/s --study NAME --record-only --write

It runs the main job, ``tune --task reconstruction --data D --scenes VAL --test-scenes TEST --n-trials N --test-runs R
--mapper M`` (no ``--val`` / ``--test``: the folder's own split, see docs/reconstruction.md), prints its output, then
reads the study's ``test.json``: the frozen settings' score and the reference's per test dataset and run (the k-th
seeds of both), and frozen - reference with the task's 95% Student t interval over datasets x runs (one test dataset
and 2 runs: one degree of freedom, so the interval is wide; it holds the run-to-run noise only, not the tuning
variance). ``--record-only`` reads a study that has already been run with the same options. ``--write`` merges the
row into ``benchmarks/results/reconstruction-heldout.{md,json}`` (a row of the same label is replaced), keeping the
command and date that measured it. Studies and caches go where ``--studies-dir`` and ``$IMTUNE_CACHE`` say: keep
them outside the checkout.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"
NAME = "reconstruction-heldout"


def _children_cpu() -> float:
    """CPU seconds (user + system) of the finished child processes so far."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def tune_command(a) -> list[str]:
    cmd = ["--task", "reconstruction", "--data", a.data, "--n-trials", str(a.n_trials), "--test-runs",
           str(a.test_runs), "--num-features", str(a.num_features), "--seed", str(a.seed), "--mapper", a.mapper,
           "--studies-dir", a.studies_dir]
    if a.val:
        cmd += ["--scenes", a.val]
    if a.test:
        cmd += ["--test-scenes", a.test]
    if a.study:
        cmd += ["--study", a.study]
    if a.trial_timeout is not None:
        cmd += ["--trial-timeout", str(a.trial_timeout)]
    if a.replicates > 1:
        cmd += ["--replicates", str(a.replicates)]
    if a.confirm is not None:  # None: tune's default (the reconstruction task confirms its 3 best)
        cmd += ["--confirm", str(a.confirm), "--confirm-seeds", str(a.confirm_seeds)]
    return cmd


def row_of(test: dict, a, command: str) -> dict:
    """The verdict row of a study's test.json."""
    ref = test.get("reference") or {}
    cmp = ref.get("comparison") or {}
    test_sets = list((test.get("data") or {}).get("scenes") or [])
    val_sets = list((test.get("validation") or {}).get("scenes") or [])
    per_run = {ds: {"frozen": [r["scenes"][ds]["score"] for r in test.get("runs", []) if ds in r.get("scenes", {})],
                    "reference": [r["scenes"][ds]["score"] for r in ref.get("runs", []) if ds in r.get("scenes", {})]}
               for ds in test_sets}
    return {"label": a.label or f"{'+'.join(val_sets)} -> {'+'.join(test_sets)} ({a.mapper})",
            "mapper": (test.get("task_options") or {}).get("mapper", a.mapper), "validation": val_sets,
            "test": test_sets, "n_trials": a.n_trials, "test_runs": a.test_runs, "num_features": a.num_features,
            "frozen": (test.get("mean") or {}).get("score"), "reference": (ref.get("mean") or {}).get("score"),
            "difference": cmp.get("difference"), "ci": cmp.get("ci"), "p_value": cmp.get("p_value"),
            "paired": cmp.get("pairs"), "per_dataset": cmp.get("datasets"), "per_run": per_run,
            "validation_score": (test.get("validation") or {}).get("score"),
            "params": test.get("params"), "study": test.get("study"), "command": command, "note": a.note,
            "trials": a.n_trials, "submission": test.get("submission"), "defaults_first": a.defaults_first,
            "folder": a.folder, "froze_defaults": a.froze_defaults, "trial_timeout": a.trial_timeout,
            "confirm": a.confirm, "confirmation": a.confirmation,
            "pruned": a.pruned, "wall_seconds": a.wall_seconds, "cpu_seconds": a.cpu_seconds,
            "trial_seconds": a.trial_seconds, "search_seconds": a.search_seconds,
            "replicated": test.get("replicated"), "replicates": test.get("replicates"),
            "date": _dt.date.today().isoformat()}


def _f(x, fmt="{:.3f}") -> str:
    return "?" if x is None else fmt.format(x)


def write(row: dict) -> None:
    jpath, mpath = RESULTS / f"{NAME}.json", RESULTS / f"{NAME}.md"
    old = json.loads(jpath.read_text()) if jpath.is_file() else {"rows": []}
    labels = [r["label"] for r in old["rows"]]
    if row["label"] in labels:  # a row measured again keeps its place
        old["rows"][labels.index(row["label"])] = row
    else:
        old["rows"].append(row)
    jpath.write_text(json.dumps(old, indent=2) + "\n")
    write_md(old, mpath)


#: the 76-image dataset of ../shared/data/imc2025
QUOTED_TEST = "imc2023_theather_imc2024_church"
#: short names of datasets in the tables (the dataset's folder in ../shared/data)
ALIASES = {"imc2023_theather_imc2024_church": "imc2025"}


def write_md(old: dict, mpath: Path) -> None:
    """Sections: ``verdict`` (one line per study), ``runs`` (each test run's scores), ``frozen`` (the frozen
    settings), ``commands``."""
    def short(names, code=True):  # imc2025's dataset by its folder's name; plain text in the verdict table: the
        q = "`" if code else ""   # table fits a page's width
        return ", ".join(f"{q}{ALIASES.get(n, n)}{q}" for n in names)
    v = ["| validated on | tested on | mapper (trials) | frozen | reference | difference [95%] | p |",
         "| --- | --- | --- | ---: | ---: | --- | ---: |"]
    runs = ["| study | test dataset | frozen, run by run | reference, run by run |", "| --- | --- | --- | --- |"]
    frozen, cmds = [], []
    for r in old["rows"]:
        if isinstance(r.get("replicated"), dict):  # its replicates' verdict is the section replicated; its command
            cmds.append(f"- {r['study']} (K = {r['replicated'].get('K')}), {r['date']}: `{r['command']}`"
                        + f"; the data folder holds {short(r.get('folder') or [])}")
            continue
        ci = r.get("ci")
        d = _f(r.get("difference"), "{:+.3f}") + (f" [{ci[0]:+.3f}, {ci[1]:+.3f}]" if ci else " (no interval)")
        p = "?" if r.get("p_value") is None else (f"{r['p_value']:.2g}")
        v.append(f"| {short(r['validation'])} | {short(r['test'])} | {r['mapper']} ({r.get('trials', '?')}"
                 f"{'' if r.get('defaults_first') else '*'}{', confirmed' if r.get('confirm') else ''}) | {_f(r['frozen'])}"
                 f"{' (defaults)' if r.get('froze_defaults') else ''} | "
                 f"{_f(r['reference'])} | {d} | {p} |")
        for ds, pr in r["per_run"].items():
            runs.append(f"| {r['study']} | {short([ds])} | {', '.join(_f(x) for x in pr['frozen'])} | "
                        f"{', '.join(_f(x) for x in pr['reference'])} |")
        ps = ", ".join(f"{k} {_f(x, '{:.4g}') if isinstance(x, float) else x}" for k, x in (r["params"] or {}).items())
        frozen.append(f"- {r['study']} (validation score {_f(r.get('validation_score'))}): {ps}.")
        cmds.append(f"- {r['study']}, {r['date']}: `{r['command']}`" + (f" ({r['note']})" if r.get("note") else "")
                    + f"; the data folder holds {short(r.get('folder') or [])}")
    times = study_times(old["rows"])
    replicated = replicated_section(old["rows"])
    text = ["Reconstruction tuning, held out: each study is tuned on its validation datasets, frozen, and tested on "
            "datasets it never saw against COLMAP out of the box (`--reference colmap`), run by run at the same "
            "seeds; the interval is the task's Student t interval over datasets x runs (run-to-run noise only). "
            "`imc2025` is the dataset `imc2023_theather_imc2024_church` of `../shared/data/imc2025`. The difference is "
            "frozen - reference; \"(defaults)\": the study froze the task's defaults; \"*\": a study whose first "
            "trial was not the defaults.", "",
            "<!-- --8<-- [start:verdict] -->", *v, "<!-- --8<-- [end:verdict] -->", "",
            "<!-- --8<-- [start:runs] -->", *runs, "<!-- --8<-- [end:runs] -->", "",
            "<!-- --8<-- [start:frozen] -->", "Frozen settings:", "", *frozen, "<!-- --8<-- [end:frozen] -->", "",
            *times, *replicated,
            "<!-- --8<-- [start:commands] -->", "Commands (`benchmarks/reconstruction_heldout.py` records the "
            "study's test.json):", "", *cmds, "<!-- --8<-- [end:commands] -->", ""]
    mpath.write_text("\n".join(text))


def before_seconds(datasets: list[str]) -> float | None:
    """Seconds of one evaluation of ``datasets`` at the configuration before issue 44 (features cached), summed
    from ``results/reconstruction-speed.json``; None unless every dataset was measured there."""
    path = RESULTS / "reconstruction-speed.json"
    rows = json.loads(path.read_text()).get("datasets", {}) if path.is_file() else {}
    if not datasets or any(ds not in rows for ds in datasets):
        return None
    return sum(rows[ds]["before issue 44"]["seconds"] for ds in datasets)


def study_times(rows: list[dict]) -> list[str]:
    """Section ``times``: a timed study's wall time (tune's whole run: features, calibration, search, test runs),
    its search, its trials, beside the search before issue 44 modelled as trials x that configuration's measured
    seconds per evaluation of the same validation datasets (no bound: a trial then ran to its end)."""
    # a study's search timed by the run that did it: not a replicated command (its wall time is in the replicated
    # section's notes) nor a resumed study whose search ran before (a run shorter than its study's search)
    timed = [r for r in rows if r.get("wall_seconds") and not r.get("replicated")
             and r["wall_seconds"] >= (r.get("search_seconds") or 0)]
    if not timed:
        return []
    out = ["<!-- --8<-- [start:times] -->",
           "| study | trials | complete / pruned | median trial (s) | search (min) | whole run (min) | "
           "before issue 44, search (min) |", "| --- | ---: | --- | ---: | ---: | ---: | ---: |"]
    for r in timed:
        ts = sorted(r.get("trial_seconds") or [])
        med = ts[len(ts) // 2] if ts else None
        before = before_seconds(r["validation"])
        n_pruned = len(r.get("pruned") or {})
        out.append(f"| {r['study']} | {r['trials']} | {len(ts) - n_pruned} / {n_pruned} | {_f(med, '{:.0f}')} | "
                   f"{_f(r.get('search_seconds') and r['search_seconds'] / 60, '{:.1f}')} | "
                   f"{r['wall_seconds'] / 60:.1f} | "
                   f"{_f(before and before * r['trials'] / 60, '{:.0f}')} |")
    out += ["", "The last column is a model, not a run: the trial count times one evaluation of the same "
            "validation datasets at the defaults before issue 44, features cached, as "
            "`benchmarks/reconstruction_speed.py` measured it (`reconstruction-speed.md`); a draw that maps for "
            "long makes the real figure larger still.", "<!-- --8<-- [end:times] -->", ""]
    return out


def replicated_section(rows: list[dict]) -> list[str]:
    """Section ``replicated``: rows run with ``--replicates K`` (K studies at independent seeds, each tuned, frozen
    and tested beside the reference): the figure and frozen - reference over the replicates
    (``tuner.replicates.dataset_replicated_summary``: t over the K replicates, tuning and run noise together)."""
    reps = [r for r in rows if isinstance(r.get("replicated"), dict)]
    if not reps:
        return []
    out = ["<!-- --8<-- [start:replicated] -->",
           "| validated on | tested on | K x runs | frozen [95%] | reference | frozen - reference [95%] | p |",
           "| --- | --- | --- | --- | ---: | --- | ---: |"]
    notes = []
    for r in reps:
        b = r["replicated"]
        obj = b.get("objective", "score")
        ref = b.get("reference") or {}
        ci, dci = b.get(f"{obj}_ci"), ref.get("ci")
        listed = r.get("replicates") or b.get("replicates") or []  # test.json keeps the list beside the block
        runs = sorted({x.get("runs") for x in listed if x.get("runs")})
        out.append(f"| {', '.join(ALIASES.get(n, n) for n in r['validation'])} | "
                   f"{', '.join(ALIASES.get(n, n) for n in r['test'])} | {b['K']} x {'/'.join(map(str, runs))} | "
                   f"{_f(b.get(obj))}" + (f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else "") + f" | {_f(ref.get(obj))} | "
                   + _f(ref.get("difference"), "{:+.3f}") + (f" [{dci[0]:+.3f}, {dci[1]:+.3f}]" if dci else "")
                   + f" | {'?' if ref.get('p_value') is None else format(ref['p_value'], '.2g')} |")
        per = ", ".join(f"{x['study']} (trial #{x.get('trial')}) {_f(x.get(obj))}" for x in listed)
        diffs = ", ".join(_f(x, "{:+.3f}") for x in ref.get("per_replicate") or [])
        took = (f" The command took {r['wall_seconds'] / 60:.1f} min ({r['note']})." if r.get("wall_seconds")
                and r.get("note") else "")
        notes.append(f"- {r['study']}: {ref.get('verdict', 'no reference')}. Replicates: {per}; frozen - reference "
                     f"by replicate: {diffs}.{took}")
    return out + ["", *notes, "<!-- --8<-- [end:replicated] -->", ""]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a folder of IMC-format datasets")
    ap.add_argument("--val", default=None, help="comma-separated validation datasets (default: the folder's split)")
    ap.add_argument("--test", default=None, help="comma-separated test datasets (default: the folder's split)")
    ap.add_argument("--mapper", default="incremental", choices=["incremental", "global"])
    ap.add_argument("--n-trials", type=int, default=8)
    ap.add_argument("--test-runs", type=int, default=2)
    ap.add_argument("--num-features", type=int, default=2048)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--studies-dir", required=True, help="where the study is written (outside the checkout)")
    ap.add_argument("--study", default=None, help="study name (default: tune's)")
    ap.add_argument("--trial-timeout", default=None, metavar="SECONDS|auto",
                    help="tune's bound on a trial's mapping (pruned beyond it; default: none)")
    ap.add_argument("--replicates", type=int, default=1, metavar="K",
                    help="tune --replicates K: K studies, the verdict over them (recorded in the section replicated)")
    ap.add_argument("--confirm", type=int, default=None, metavar="N",
                    help="tune --confirm N: the N best trials confirmed at more seeds before freezing (default: "
                         "tune's, 3 for reconstruction)")
    ap.add_argument("--confirm-seeds", type=int, default=2, metavar="S")
    ap.add_argument("--label", default=None, help="the row's label in the results (default: val -> test (mapper))")
    ap.add_argument("--record-only", action="store_true", help="do not run: read the study's test.json")
    ap.add_argument("--wall-seconds", type=float, default=None,
                    help="with --record-only: the wall seconds this script printed when it ran the study")
    ap.add_argument("--cpu-seconds", type=float, default=None, help="with --record-only: the CPU seconds it printed")
    ap.add_argument("--note", default=None, help="a remark recorded with the row (e.g. the code version it ran)")
    ap.add_argument("--write", action="store_true", help=f"merge the row into benchmarks/results/{NAME}.{{md,json}}")
    ap.add_argument("--render", action="store_true", help="only write the .md again from the recorded .json")
    a = ap.parse_args(argv)
    if a.render:
        write_md(json.loads((RESULTS / f"{NAME}.json").read_text()), RESULTS / f"{NAME}.md")
        return 0
    for k in ("n_trials", "test_runs", "num_features", "replicates"):
        if getattr(a, k) < 1:
            ap.error(f"--{k.replace('_', '-')} must be at least 1")
    if not a.record_only:
        a.wall_seconds = a.cpu_seconds = None
    args = tune_command(a)
    command = "tune " + " ".join(args)
    if not a.record_only:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
        t0, c0 = time.perf_counter(), _children_cpu()
        rc = subprocess.call([sys.executable, "-m", "tuner", *args], env=env)
        a.wall_seconds, a.cpu_seconds = time.perf_counter() - t0, _children_cpu() - c0
        print(f"tune took {a.wall_seconds / 60:.1f} min wall, {a.cpu_seconds:.0f} CPU-s", flush=True)
        if rc != 0:
            print(f"tune exited with {rc}", file=sys.stderr)
            return 1
    from tuner.freeze import study_dir
    if a.study is None:
        a.study = f"colmap-sift-{a.num_features}-degensac-reconstruction"
    path = study_dir(a.studies_dir, a.study) / "test.json"
    if not path.is_file():
        print(f"no test result at {path}: run the study first (without --record-only)", file=sys.stderr)
        return 2
    import optuna
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    st = optuna.load_study(study_name=a.study, storage=f"sqlite:///{Path(a.studies_dir) / 'optuna.db'}")
    a.defaults_first = bool(st.trials) and st.trials[0].user_attrs.get("start") == "task defaults"
    trial = json.loads(path.read_text()).get("trial")
    a.froze_defaults = isinstance(trial, int) and st.trials[trial].user_attrs.get("start") == "task defaults"
    a.confirmation = st.user_attrs.get("confirmation")  # what the study did, whatever the options said
    a.confirm = (a.confirmation or {}).get("n", 0) if a.confirm is None else a.confirm
    a.pruned = {t.number: t.user_attrs.get("pruned_reason") for t in st.trials if t.state.name == "PRUNED"}
    ended = [t for t in st.trials if t.datetime_start and t.datetime_complete]
    a.trial_seconds = [round((t.datetime_complete - t.datetime_start).total_seconds(), 1) for t in ended]
    a.search_seconds = (round((max(t.datetime_complete for t in ended) - min(t.datetime_start for t in ended))
                              .total_seconds(), 1) if ended else None)
    from pipeline.data import list_scenes
    a.folder = list_scenes(a.data)
    row = row_of(json.loads(path.read_text()), a, command)
    print(f"{row['label']}: frozen {_f(row['frozen'])}, reference {_f(row['reference'])}, frozen - reference "
          f"{_f(row['difference'], '{:+.3f}')} {row['ci']} p {row['p_value']}")
    if a.write:
        write(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
