"""Two `tune` workers vs one on the same machine: completed trials per minute (target ratio >= 1.7).

Each configuration is a fresh study in a fresh SQLite storage, run by real `tune` processes (the
command users run, `python -m tuner ... --no-test`); the throughput of a study is its finished trials
divided by the time from its first trial's start to its last trial's end (as recorded in the storage,
so process start-up and data loading are not counted). Trials are made comparable by pinning eta and
Gamma (``--fix``) and searching r only, with the random sampler: every trial costs about the same.
Features and k-NN tables are computed once beforehand (the cache is shared by the workers).

    python benchmarks/workers.py                       # sift 8000, degensac, 24 pairs, 8 trials per worker
    python benchmarks/workers.py --num-features 2048 --trials-per-worker 12

The machine should be otherwise idle: with 2 cores, anything else running halves the second worker.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def run_study(n_workers: int, n_trials: int, common: list[str], tmp: Path, env: dict) -> dict:
    import optuna
    from optuna.trial import TrialState

    from tuner.storage import open_storage
    d = tmp / f"w{n_workers}"
    storage = f"sqlite:///{d}/optuna.db"
    args = [sys.executable, "-m", "tuner", *common, "--studies-dir", str(d), "--storage", storage,
            "--n-trials", str(n_trials), "--study", f"workers-{n_workers}", "--no-test", "--quiet"]
    t0 = time.perf_counter()
    procs = [subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(n_workers)]
    outs = [p.communicate() for p in procs]
    wall = time.perf_counter() - t0
    for p, (_, err) in zip(procs, outs):
        if p.returncode != 0:
            raise SystemExit(f"worker failed: {err.strip().splitlines()[-1] if err.strip() else p.returncode}")
    st = optuna.load_study(study_name=f"workers-{n_workers}", storage=open_storage(storage, heartbeat=None))
    done = [t for t in st.trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]
    first = min(t.datetime_start for t in done)
    last = max(t.datetime_complete for t in done)
    span = (last - first).total_seconds()
    return {"workers": n_workers, "trials": len(done), "span_seconds": span, "process_wall_seconds": wall,
            "trials_per_minute": 60.0 * len(done) / span,
            "mean_trial_seconds": sum((t.datetime_complete - t.datetime_start).total_seconds() for t in done) / len(done)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--feature", default="sift")
    ap.add_argument("--num-features", type=int, default=8000)
    ap.add_argument("--ransac", default="degensac")
    ap.add_argument("--max-pairs", type=int, default=24)
    ap.add_argument("--trials-per-worker", type=int, default=8)
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--max-iters", type=int, default=20000)
    ap.add_argument("--cache", default=None, help="default $IMTUNE_CACHE or ~/.cache/imtune")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    common = ["--feature", args.feature, "--num-features", str(args.num_features), "--ransac", args.ransac,
              "--max-pairs", str(args.max_pairs), "--sampler", "random", "--pruner", "none", "--budget", "100",
              "--fix", f"threshold={args.threshold}", "--fix", f"max_iters={args.max_iters}"]
    if args.data:
        common += ["--data", args.data]
    env = dict(os.environ)
    if args.cache:
        env["IMTUNE_CACHE"] = args.cache
    tmp = Path(tempfile.mkdtemp(prefix="imtune-workers-"))
    try:
        # warm the cache (features, k-NN) so that no worker computes them
        warm = subprocess.run([sys.executable, "-m", "tuner", *common, "--studies-dir", str(tmp / "warm"),
                               "--n-trials", "1", "--no-test", "--quiet"], cwd=ROOT, env=env, capture_output=True,
                              text=True)
        if warm.returncode != 0:
            raise SystemExit(f"warm-up failed: {warm.stderr.strip()}")
        load = os.getloadavg()[0]
        one = run_study(1, args.trials_per_worker, common, tmp, env)
        two = run_study(2, 2 * args.trials_per_worker, common, tmp, env)
        ratio = two["trials_per_minute"] / one["trials_per_minute"]
        out = {"feature": args.feature, "num_features": args.num_features, "ransac": args.ransac,
               "pairs": args.max_pairs, "cpus": os.cpu_count(), "load_before": load,
               "one": one, "two": two, "ratio": ratio, "target": 1.7}
        if args.json:
            print(json.dumps(out, indent=2))
            return 0
        print(f"{args.feature} {args.num_features}, {args.ransac}, {args.max_pairs} pairs per trial, eta and Gamma "
              f"pinned, random r; {os.cpu_count()} CPUs, 1-min load average before: {load:.2f}")
        for r in (one, two):
            print(f"  {r['workers']} worker(s): {r['trials']} trials in {r['span_seconds']:.1f} s "
                  f"-> {r['trials_per_minute']:.2f} trials/min (mean trial {r['mean_trial_seconds']:.2f} s)")
        print(f"two workers / one worker = {ratio:.2f} x  -> target >= 1.7: {'met' if ratio >= 1.7 else 'NOT met'}")
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())
