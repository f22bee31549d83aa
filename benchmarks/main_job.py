"""The README's main job over several seeds: wall time (min, median, max) and the frozen settings' test mAA(10),
bounded search (today's default, ``--timeout`` 300 s) beside the unbounded one (``--timeout 0``: 50 trials whatever
they cost), with the replicated comparison of the two test figures (each seed one replicate).

Each run is the real command users run, ``tune --feature sift --ransac degensac --seed S --json``, from an empty
cache and an empty studies folder (so features, k-NN tables, calibration, trials and the 3 test runs are all in its
wall time), one run at a time.

    python benchmarks/main_job.py                         # seeds 0 1 2, both modes: ~1 h on 2 cores
    python benchmarks/main_job.py --seeds 0 1 --modes bounded
    python benchmarks/main_job.py --from-json benchmarks/results/main-job.json

Writes ``benchmarks/results/main-job.json`` (``--out``): every run's wall time, phases as the study recorded them,
trials, frozen settings, test mAA(10) with its interval, and the per-pair test records the comparison reads. Read
the load average printed with each run: a machine busy with other work gives a run fewer cores, and a bounded search
fewer trials.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MODES = {"bounded": [], "unbounded": ["--timeout", "0"]}


def one_run(seed: int, mode: str, data: str | None) -> dict:
    """The main job in a fresh cache and studies folder: its JSON output plus wall time and the test records."""
    tmp = Path(tempfile.mkdtemp(prefix=f"imtune-main-{mode}-{seed}-"))
    env = dict(os.environ, IMTUNE_CACHE=str(tmp / "cache"))
    cmd = [sys.executable, "-m", "tuner", "--feature", "sift", "--ransac", "degensac", "--seed", str(seed),
           "--studies-dir", str(tmp / "studies"), "--json", *MODES[mode]] + (["--data", data] if data else [])
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{mode} seed {seed} failed: {(r.stderr.strip().splitlines() or ['?'])[-1]}")
    out = json.loads(r.stdout)
    test = out.get("test") or {}
    runs = test_records(tmp)
    shutil.rmtree(tmp, ignore_errors=True)
    mean = test.get("mean") or {}
    ci = mean.get("mAA10_ci")
    return {"seed": seed, "mode": mode, "wall": wall, "load_before": load,
            "trials_run": len(out["worker"]["trials_run"]), "search_seconds": out["worker"]["seconds"],
            "time_limit": out["worker"].get("time_limit"), "counts": out["counts"],
            "frozen": {k: out["frozen"]["params"].get(k) for k in ("ratio", "threshold", "max_iters")}
            if out.get("frozen") else None,
            "test_mAA10": mean.get("mAA10"), "test_ci": ci, "runs": runs}


def test_records(tmp: Path) -> list:
    """The per-pair records {scene, pair, err} of every test run of the study under ``tmp`` (its test.json's
    ``pair_errors``; an error of None / "inf" is a failed pair)."""
    found = sorted((tmp / "studies").glob("*/test.json"))
    if not found:
        return []
    t = json.loads(found[0].read_text())
    return [[{"scene": sc, "pair": pair, "err": float("inf") if err in (None, "inf") else float(err)}
             for sc, pair, err in run.get("pair_errors") or []] for run in t.get("runs") or []]


def summary(runs: list) -> dict:
    """Per mode: wall min / median / max and the test figures; the ratio of medians; the replicated comparison."""
    from pipeline.metrics.replicates import replicated_records_comparison
    out: dict = {"modes": {}}
    for mode in MODES:
        rs = [r for r in runs if r["mode"] == mode]
        if not rs:
            continue
        walls = [r["wall"] for r in rs]
        out["modes"][mode] = {"seeds": [r["seed"] for r in rs], "wall_min": min(walls),
                              "wall_median": statistics.median(walls), "wall_max": max(walls),
                              "test_mAA10": [r["test_mAA10"] for r in rs], "trials_run": [r["trials_run"] for r in rs]}
    m = out["modes"]
    if "bounded" in m and "unbounded" in m:
        out["wall_ratio"] = m["bounded"]["wall_median"] / m["unbounded"]["wall_median"]
        a = [r["runs"] for r in runs if r["mode"] == "unbounded" and r["runs"]]
        b = [r["runs"] for r in runs if r["mode"] == "bounded" and r["runs"]]
        if a and b:
            try:
                out["comparison"] = replicated_records_comparison(a, b, tau=10)  # bounded - unbounded
            except ValueError as e:
                out["comparison"] = {"error": str(e)}
    return out


def report(data: dict) -> str:
    lines = ["| mode | seed | wall | trials | load | frozen r / eta / Gamma | test mAA(10) [95%] |",
             "|---|---:|---:|---:|---:|---|---|"]
    for r in data["runs"]:
        f = r["frozen"] or {}
        ci = r["test_ci"] or [float("nan")] * 2
        lines.append(f"| {r['mode']} | {r['seed']} | {r['wall'] / 60:.1f} min | {r['trials_run']} | "
                     f"{r['load_before']:.1f} | {f.get('ratio', 0):.3f} / {f.get('threshold', 0):.3f} / "
                     f"{f.get('max_iters', 0)} | {r['test_mAA10']:.3f} [{ci[0]:.3f}, {ci[1]:.3f}] |")
    s = data["summary"]
    for mode, v in s["modes"].items():
        lines.append(f"\n{mode}: wall {v['wall_min'] / 60:.1f}-{v['wall_max'] / 60:.1f} min "
                     f"(median {v['wall_median'] / 60:.1f}) over seeds {v['seeds']}")
    if "wall_ratio" in s:
        lines.append(f"median wall time, bounded / unbounded: {s['wall_ratio']:.2f}")
    c = s.get("comparison")
    if c and "difference" in c:
        lines.append(f"test mAA(10), bounded - unbounded (replicated comparison, K = {c['replicates']}): "
                     f"{c['difference']:+.3f} [{c['ci'][0]:+.3f}, {c['ci'][1]:+.3f}], p {c['p_value']:.3f}, "
                     f"{c['pairs']} pairs")
        worse = c["significant"] and c["difference"] < 0
        mde = c.get("mde")
        could = f"; it could detect |bounded - unbounded| >= {mde:.3f} with 80% power" if mde is not None else ""
        lines.append(("significantly worse" if worse else "not significantly worse") + could)
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--modes", nargs="+", choices=list(MODES), default=list(MODES))
    ap.add_argument("--data", default=None, help="the data set (default: the main job's)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "main-job.json"))
    ap.add_argument("--from-json", default=None, help="print the report of a file written by --out")
    ap.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                    help="runs of several files written by --out (e.g. seeds run apart) into --out, with the summary")
    a = ap.parse_args(argv)
    if a.from_json:
        print(report(json.loads(Path(a.from_json).read_text())))
        return 0
    if a.merge:
        files = [json.loads(Path(f).read_text()) for f in a.merge]
        runs = [r for d in files for r in d["runs"]]
        data = {"command": files[0]["command"], "date": ", ".join(sorted({d["date"] for d in files})),
                "cpus": files[0]["cpus"], "runs": runs, "summary": summary(runs)}
        Path(a.out).write_text(json.dumps(data, indent=1))
        print(report(data))
        return 0
    runs: list = []
    for seed in a.seeds:
        for mode in a.modes:
            runs.append(one_run(seed, mode, a.data))
            r = runs[-1]
            print(f"{mode} seed {seed}: {r['wall'] / 60:.1f} min, {r['trials_run']} trials, test mAA(10) "
                  f"{r['test_mAA10']:.3f}", flush=True)
            data = {"command": "tune --feature sift --ransac degensac --seed S --json",
                    "date": time.strftime("%Y-%m-%d"), "cpus": os.cpu_count(), "runs": runs,
                    "summary": summary(runs)}
            Path(a.out).write_text(json.dumps(data, indent=1))
    print(report(data))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
