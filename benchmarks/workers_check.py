"""The many-workers check: three `tune` workers on one PostgreSQL study, one killed with SIGKILL mid-trial.

A PostgreSQL server is started on 127.0.0.1 (tests/pgserver.py). Worker 2 starts alone and is killed with SIGKILL
during its first trial; it records another machine (IMTUNE_MACHINE), so its trial is found dead by the heartbeat's
grace period (30 s by default), as on a real second machine. Workers 1 and 3 then run the study to the end, each
with its own studies folder and cache. Printed: the study's trial states, the killed trial's fate, the test.json
files written, and each survivor's exit code and frozen settings.

    python benchmarks/workers_check.py [--data DIR] [--n-trials 9]
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
PASSWORD = "Acc3pt-secret"


def main(argv=None) -> int:
    import optuna

    from tests.pgserver import PgServer
    from tuner.storage import open_storage
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="a Strecha folder (default: the one tune finds)")
    ap.add_argument("--n-trials", type=int, default=9)
    opts = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="imtune-workers-check-"))
    pg = PgServer(password=PASSWORD)

    def trials():
        st = open_storage(pg.url, heartbeat=None, must_exist=True)
        try:
            return optuna.load_study(study_name="check", storage=st).get_trials(deepcopy=False)
        finally:
            st.engine.dispose()

    def start(i, **env):
        args = [sys.executable, "-m", "tuner", *(["--data", opts.data] if opts.data else []), "--feature", "sift",
                "--num-features", "512", "--ransac", "degensac", "--scenes", "fountain-P11", "--test-scenes",
                "Herz-Jesus-P8", "--max-pairs", "4", "--chunk-pairs", "4", "--calibration-pairs", "2",
                "--fix", "max_iters=150000", "--fix", "threshold=0.2", "--budget", "5",
                "--studies-dir", str(tmp / f"studies{i}"), "--study", "check", "--n-trials", str(opts.n_trials),
                "--seed", "1", "--test-runs", "1"]
        e = dict(os.environ, IMTUNE_STORAGE=pg.url, IMTUNE_CACHE=str(tmp / f"cache{i}"), PYTHONPATH=str(ROOT), **env)
        return subprocess.Popen(args, cwd=ROOT, env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)

    try:
        t0 = time.time()
        w2 = start(2, IMTUNE_MACHINE="machine-2")
        killed = None
        while killed is None and w2.poll() is None:
            time.sleep(0.2)
            try:
                running = [t for t in trials() if t.state.name == "RUNNING" and t.params]
            except Exception:  # noqa: BLE001 - the study does not exist yet
                continue
            killed = running[0] if running else None
        if killed is None:
            raise SystemExit(f"worker 2 ended before it could be killed: {w2.communicate()[1][-2000:]}")
        os.killpg(w2.pid, signal.SIGKILL)
        w2.communicate()
        print(f"worker 2 killed (exit {w2.returncode}) in trial {killed.number} {killed.params} "
              f"at {time.time() - t0:.1f} s")
        w1, w3 = start(1), start(3)
        outs = {i: p.communicate() for i, p in ((1, w1), (3, w3))}
        print(f"workers 1 and 3 done at {time.time() - t0:.1f} s: exit codes {w1.returncode}, {w3.returncode}")
        ts = trials()
        states: dict[str, int] = {}
        for t in ts:
            states[t.state.name] = states.get(t.state.name, 0) + 1
        print(f"trial states: {states}; finished (COMPLETE + PRUNED) "
              f"{states.get('COMPLETE', 0) + states.get('PRUNED', 0)} of {opts.n_trials}, "
              f"RUNNING {states.get('RUNNING', 0)}")
        retry = [t for t in ts if t.system_attrs.get("failed_trial") == killed.number]
        print(f"killed trial {killed.number}: {ts[killed.number].state.name}; retried as {[t.number for t in retry]} "
              f"{[t.state.name for t in retry]}, same parameters: {bool(retry) and retry[0].params == killed.params}, "
              f"by pid {retry[0].system_attrs['imtune:worker']['pid'] if retry else None} "
              f"(workers 1, 3: {w1.pid}, {w3.pid})")
        print("test.json files:", sorted(str(p.relative_to(tmp)) for p in tmp.rglob("test.json")))
        keep = ("frozen:", "| ratio", "| threshold", "| max_iters", "test phase")
        for i, (so, se) in outs.items():
            print(f"worker {i} stdout (frozen settings):", *[ln for ln in so.splitlines() if ln.startswith(keep)],
                  sep="\n  ")
            print(f"worker {i}: password in its output: {PASSWORD in so + se}")
    finally:
        pg.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
