"""Wall time of a replicated tuning (K = 3) against today's single one (K = 1), side by side in one run.

Each configuration is the real `tune run` command (a subprocess, as a user runs it) on the same small job, each in
its own studies folder, all sharing one feature / k-NN cache that a warm-up run fills first (so no row pays for
features the others reuse: replicates share the cache by design, and a K = 1 run on a warm cache is today's rerun).
Rows: K = 1; K = 3; K = 3 with ``--terminate auto`` (each study stops when more trials cannot beat its incumbent by
more than its validation interval). Printed: wall seconds, ratio to K = 1, trials run, the test mAA(10) (K = 3: the
replicated mean and interval).

    python benchmarks/replicates_wall_time.py                       # 2048 SIFT, 8 pairs per scene, 20 trials
    python benchmarks/replicates_wall_time.py --n-trials 50 --max-pairs 12

Measured: see benchmarks/results/replicated-tunings-run.md. The target: K = 3 within twice the K = 1 time with frozen figures as good.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("IMTUNE_SHARED", ROOT.parent / "shared")) / "data" / "strecha"


def tune(args: list[str], cache: Path) -> tuple[float, dict]:
    env = dict(os.environ, IMTUNE_CACHE=str(cache), PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "tuner", "run", *args, "--json"], capture_output=True, text=True,
                       cwd=ROOT, env=env)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        sys.exit(f"tune failed: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode}")
    return wall, json.loads(r.stdout)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--num-features", default="2048")
    ap.add_argument("--max-pairs", default="8")
    ap.add_argument("--n-trials", default="20")
    ap.add_argument("--scenes", default="fountain-P11")
    ap.add_argument("--test-scenes", default="Herz-Jesus-P8,entry-P10")
    ap.add_argument("--budget", default="0.1")
    ap.add_argument("--seed", default="1")
    a = ap.parse_args(argv)
    if not DATA.is_dir():
        sys.exit(f"no data at {DATA}")
    work = Path(tempfile.mkdtemp(prefix="imtune-walltime-"))
    cache = work / "cache"
    common = ["--data", str(DATA), "--feature", "sift", "--num-features", a.num_features, "--ransac", "degensac",
              "--scenes", a.scenes, "--test-scenes", a.test_scenes, "--max-pairs", a.max_pairs,
              "--budget", a.budget, "--n-trials", a.n_trials, "--seed", a.seed, "--reference", "none"]
    warm, _ = tune(common + ["--studies-dir", str(work / "warm"), "--n-trials", "1", "--test-runs", "1"], cache)
    print(f"warm-up (features, k-NN tables, calibration of the cache): {warm:.0f} s; work folder {work}")
    rows = []
    for label, extra in (("K = 1", []), ("K = 3", ["--replicates", "3"]),
                         ("K = 3, --terminate auto", ["--replicates", "3", "--terminate", "auto"])):
        wall, out = tune(common + ["--studies-dir", str(work / label.replace(" ", "").replace(",", "_")), *extra],
                         cache)
        reps = out.get("replicates") or [out]
        trials = sum(len(o["worker"]["trials_run"]) for o in reps)
        if out.get("replicated"):
            r = out["replicated"]
            fig = f"{r['mAA10']:.4f} [{r['mAA10_ci'][0]:.4f}, {r['mAA10_ci'][1]:.4f}] (each " + ", ".join(
                f"{x['mAA10']:.3f}" for x in r["replicates"]) + ")"
        else:
            m = out["test"]["mean"]
            fig = f"{m['mAA10']:.4f} [{m['mAA10_ci'][0]:.4f}, {m['mAA10_ci'][1]:.4f}]"
        rows.append((label, wall, trials, fig))
    base = rows[0][1]
    print("| run | wall s | x K=1 | trials run | test mAA10 |\n|---|---:|---:|---:|---|")
    for label, wall, trials, fig in rows:
        print(f"| {label} | {wall:.0f} | {wall / base:.2f} | {trials} | {fig} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
