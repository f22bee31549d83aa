"""The budget's clock beside CPU-bound neighbours: per-cap median estimator seconds and Gamma_max(B),
measured quiet and beside CPU hogs in one run, in CPU time (what the budget bounds) and in wall time.

For each estimator and each --jobs setting, the calibration matches (the ones `tune calibrate` times: validation
pairs, r and eta from the search space's calibration section) are timed:

1. quiet: the calibration's adaptive caps (``tuner.budget._measure``: up to the first cap past B);
2. beside ``hogs`` spinning processes (multiprocessing, a busy loop each): the same caps.

It prints per cap the quiet and loaded medians and their ratio, for CPU and wall time, then Gamma_max(B) of each
curve and the ratio. Targets (the issue): CPU-time ratios within 0.8-1.25 for every cap and Gamma_max within 20%;
wall time shows the neighbours (about 2x with two hogs on 2 cores). The machine's load average (`os.getloadavg`)
is printed beside each phase: on a shared machine "quiet" means "without our hogs", not idle.

    python benchmarks/cpu_budget.py                                  # DEGENSAC + cv-usac, fountain-P11, 2048 SIFT
    python benchmarks/cpu_budget.py --estimators degensac --pairs 4 --budget 0.25
    python benchmarks/cpu_budget.py --jobs 1 2 --hogs 2 1            # --jobs 1 with 2 hogs, --jobs 2 with 1 hog
    python benchmarks/cpu_budget.py --thread-check --estimators degensac  # --jobs 1: what our other threads add

``--thread-check``: in-process (``--jobs 1``) the budget's ``process_time`` also counts this process's other threads
(tqdm's monitor, Optuna's heartbeat). It times the estimator on the calibration matches with a tqdm bar and a
thread that wakes 20 times a second doing a little work, and prints process CPU vs the calling thread's CPU
(``time.thread_time``; DEGENSAC is single-threaded, so the difference is what the other threads added). Then the
same after a numpy product before each call (the BLAS pool's idle threads spin for a while after one), once with
the process's own thread pools and once inside ``one_thread_here`` (what an in-process evaluation uses).
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _hog(stop) -> None:
    """Spin (pure Python, one core) until ``stop`` is set."""
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


class Hogs:
    """``n`` spawned processes spinning on a core each while the block runs; reports the CPU they got."""

    def __init__(self, n: int):
        self.n = n

    def __enter__(self):
        ctx = mp.get_context("spawn")
        self.stop = ctx.Event()
        self.procs = [ctx.Process(target=_hog, args=(self.stop,), daemon=True) for _ in range(self.n)]
        for p in self.procs:
            p.start()
        time.sleep(1.5)  # every hog past its imports and spinning
        return self

    def __exit__(self, *exc):
        self.stop.set()
        for p in self.procs:
            p.join(10)
            if p.is_alive():
                p.terminate()
                p.join(5)


def _matches(a):
    from pipeline.cache import H5Cache
    from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
    from pipeline.tasks import make_task
    from tuner.budget import calibration_matches
    from tuner.evaluate import load_scenes
    from tuner.objective import ValidationSet
    from tuner.options import resolve_data
    from tuner.space import load_space
    space = load_space(None, feature="sift", estimator="degensac")
    ratio, eta = float(space.calibration["ratio"]), float(space.calibration["threshold"])
    conf = PipelineConfig(feature=FeatureConfig(name="sift", num_features=a.num_features),
                          matching=MatchConfig(ratio=ratio), geometry=GeometryConfig(ransac="degensac"))
    task = make_task("stereo", min_covisibility=0.1, max_pairs=None)
    vs = ValidationSet.from_scenes(load_scenes(resolve_data(a.data), a.scenes, split="val"), task)
    cache = H5Cache(a.cache) if a.cache else H5Cache(None)
    return calibration_matches(vs.scenes, conf, cache, max_pairs=a.pairs), eta, conf.geometry.confidence


def _curves(time_cap, caps):
    """[(cap, median CPU s, p90), ...] and the same in wall seconds, timing each cap once."""
    import numpy as np
    cpu, wall = [], []
    for g in caps:
        got = time_cap(g)
        for out, i in ((cpu, 0), (wall, 1)):
            xs = [x[i] for x in got]
            out.append((int(g), float(np.median(xs)), float(np.percentile(xs, 90))))
    return cpu, wall


def _gmax(curve, budget: float, name: str) -> int:
    from tuner.budget import Calibration
    return Calibration(estimator=name, feature={}, ratio=0.9, threshold=0.5, pairs=1,
                       curve=[list(c) for c in curve]).gamma_max(budget)


def _load() -> str:
    l1, l5, l15 = os.getloadavg()
    return f"load avg {l1:.2f} {l5:.2f} {l15:.2f}"


def one(a, name: str, matches, eta: float, confidence: float, jobs: int, hogs: int) -> dict:
    from tuner.budget import GAMMA_CEILING, _measure, cap_timer
    with cap_timer(name, matches, eta, confidence, seed=0, jobs=jobs) as time_cap:
        time_cap(100)  # warm up (the workers' imports, first calls)
        load_q = _load()
        t0 = time.perf_counter()
        qw: list = []
        if a.caps:
            qc, qw = _curves(time_cap, a.caps)
        else:
            qc = _measure(name, time_cap, a.budget, GAMMA_CEILING, progress=False, wall_curve=qw)
        caps = [c[0] for c in qc]
        t_q = time.perf_counter() - t0
        with Hogs(hogs):
            load_h = _load()
            t0 = time.perf_counter()
            hc, hw = _curves(time_cap, caps)
            t_h = time.perf_counter() - t0
    return {"name": name, "jobs": jobs, "hogs": hogs, "caps": caps, "quiet": (qc, qw), "hog": (hc, hw),
            "load": (load_q, load_h), "wall": (t_q, t_h)}


def report(r: dict, budget: float) -> bool:
    print(f"\n## {r['name']}, --jobs {r['jobs']}, quiet vs beside {r['hogs']} CPU hog(s)")
    print(f"quiet: {r['load'][0]}, {r['wall'][0]:.1f} s; with hogs: {r['load'][1]}, {r['wall'][1]:.1f} s")
    print("| cap | CPU quiet s | CPU hogs s | CPU ratio | wall quiet s | wall hogs s | wall ratio |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    (qc, qw), (hc, hw) = r["quiet"], r["hog"]
    ok = True
    for i, g in enumerate(r["caps"]):
        rc = hc[i][1] / max(qc[i][1], 1e-12)
        rw = hw[i][1] / max(qw[i][1], 1e-12)
        ok &= 0.8 <= rc <= 1.25
        print(f"| {g:,} | {qc[i][1]:.4f} | {hc[i][1]:.4f} | {rc:.2f} | {qw[i][1]:.4f} | {hw[i][1]:.4f} | {rw:.2f} |")
    gq, gh = _gmax(qc, budget, r["name"]), _gmax(hc, budget, r["name"])
    wq, wh = _gmax(qw, budget, r["name"]), _gmax(hw, budget, r["name"])
    ok &= abs(gh / gq - 1) <= 0.2
    print(f"Gamma_max({budget:g} s): CPU {gq:,} quiet, {gh:,} with hogs (ratio {gh / gq:.2f}); "
          f"wall {wq:,} quiet, {wh:,} with hogs (ratio {wh / wq:.2f})")
    print("CPU-time targets (ratios 0.8-1.25, Gamma_max within 20%):", "met" if ok else "NOT met")
    return ok


def thread_check(name: str, matches, eta: float, confidence: float, cap: int = 20_000, rounds: int = 5,
                 product: bool = False, limited: bool = False) -> None:
    """Process vs calling-thread CPU of the estimator in this process beside a busy waker thread; ``product``: a
    numpy matrix product (what the k-NN matching runs, on every BLAS thread) right before each call; ``limited``:
    the calls inside ``pipeline.tasks.pool.one_thread_here`` (what `--jobs 1` and a calibration alone do now)."""
    import contextlib
    import threading

    import numpy as np
    from tqdm.auto import tqdm

    from pipeline.geometry import get_estimator
    from pipeline.tasks.pool import one_thread_here
    est = get_estimator(name)
    stop = threading.Event()
    big = np.random.default_rng(0).normal(size=(1500, 1500)).astype(np.float32)

    def waker():  # far busier than Optuna's heartbeat thread (one write every heartbeat_interval seconds)
        while not stop.wait(0.05):
            sum(range(1000))
    threading.Thread(target=waker, daemon=True).start()
    proc = thread = 0.0
    with one_thread_here() if limited else contextlib.nullcontext():
        with tqdm(total=rounds * len(matches), mininterval=0.01, desc="thread check") as bar:
            for k in range(rounds):
                for p1, p2, sz, *_ in matches:
                    if product:
                        big @ big
                    c0, t0 = time.process_time(), time.thread_time()
                    est.estimate(p1, p2, eta, confidence, cap, seed=k, sizes=sz)
                    proc += time.process_time() - c0
                    thread += time.thread_time() - t0
                    bar.update(1)
    stop.set()
    what = ("after a BLAS product, " if product else "") + ("one thread (one_thread_here)" if limited else
                                                            "the process's own thread pools")
    print(f"{name}, cap {cap:,}, {rounds * len(matches)} calls in this process, {what}: process CPU {proc:.3f} s, "
          f"calling thread CPU {thread:.3f} s, excess {100 * (proc - thread) / max(thread, 1e-9):.2f}%; {_load()}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=None, help="data root (default: the project's default, ../shared/data/strecha)")
    p.add_argument("--scenes", nargs="+", default=["fountain-P11"])
    p.add_argument("--num-features", type=int, default=2048)
    p.add_argument("--pairs", type=int, default=4, help="calibration pairs timed")
    p.add_argument("--budget", type=float, default=0.5, help="B, median estimator CPU seconds per pair")
    p.add_argument("--caps", type=int, nargs="+", default=None, help="fixed caps instead of the calibration's own")
    p.add_argument("--estimators", nargs="+", default=["degensac", "cv-usac"])
    p.add_argument("--jobs", type=int, nargs="+", default=[1, 2], help="estimator processes timed at once")
    p.add_argument("--hogs", type=int, nargs="+", default=[2, 1], help="hog processes beside each --jobs setting")
    p.add_argument("--cache", default=None, help="feature cache folder (default: imtune's)")
    p.add_argument("--thread-check", action="store_true", help="only the in-process thread check (see the docstring)")
    a = p.parse_args()
    if len(a.hogs) != len(a.jobs):
        p.error("--hogs takes one number per --jobs setting")
    matches, eta, confidence = _matches(a)
    print(f"{len(matches)} pairs of {', '.join(a.scenes)}, SIFT {a.num_features}, eta {eta:g} px; "
          f"{os.cpu_count()} CPUs; {_load()}")
    if a.thread_check:
        for name in a.estimators:
            thread_check(name, matches, eta, confidence)
            thread_check(name, matches, eta, confidence, product=True)
            thread_check(name, matches, eta, confidence, product=True, limited=True)
        return 0
    ok = True
    for name in a.estimators:
        for jobs, hogs in zip(a.jobs, a.hogs):
            ok &= report(one(a, name, matches, eta, confidence, jobs, hogs), a.budget)
    print(f"\nall CPU-time targets met: {ok}; {_load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
