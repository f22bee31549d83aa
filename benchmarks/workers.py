"""Many workers, one study on PostgreSQL: trials per minute with 1 and 2 workers, and with 2 when one is killed.

One study of the same trial count and seed is run three times by real `tune` processes (the command users run,
`python -m tuner ... --no-test`) on a PostgreSQL server this script starts on 127.0.0.1, each worker with its own
cache and studies folder, as on separate machines:

1. one worker;
2. two workers;
3. two workers, one killed with `kill -9` in the middle of a trial (its trial is failed by the heartbeat check
   after the grace period and retried once by the other worker).

Throughput is finished trials over the span from the study's first trial start to its last trial end (as the
storage records them: process start-up and data loading are not counted). Trials are made comparable by pinning
eta and Gamma (``--fix``) and searching r only, with the random sampler. For the killed run the script checks that
the study ends with exactly the target, no RUNNING trial, and every trial seen complete before the kill still
complete.

It also measures what the scale model needs: the storage's cost per trial (an instant objective through the same
claim loop, ``tuner.workers.run_to_target``), and how far Optuna's ``MaxTrialsCallback`` alone overshoots with
three workers (a 0.2 s sleep as the objective) against the claim loop. The model: M workers (each on its own
machine) finish a study of n trials of T seconds with a storage that serves one trial's calls in c seconds at
speed-up S(M) = min(M, (T + c) / c) x n / (M ceil(n / M)) (the storage taken as fully serialised, the last round
only partly used).

    python benchmarks/workers.py                          # ~4 minutes: sift 2048, 8 trials, 6 pairs
    python benchmarks/workers.py --trials 12 --out benchmarks/results/workers.json

This machine kind has 2 cores, so two workers can reach at most 2x here.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
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


def _pg():
    """A throw-away PostgreSQL cluster on loopback (tests/pgserver.py), or SystemExit saying why not."""
    from _pytest.outcomes import OutcomeException

    from tests.pgserver import PgServer
    try:
        return PgServer(password="bench-pw-not-shown")
    except OutcomeException as e:  # its pytest.skip / fail
        raise SystemExit(f"cannot start PostgreSQL: {e.msg}") from None


def _trials(url: str, name: str):
    import optuna

    from tuner.storage import open_storage
    storage = open_storage(url, heartbeat=None, must_exist=True)
    try:
        return optuna.load_study(study_name=name, storage=storage).get_trials(deepcopy=False)
    finally:
        storage.engine.dispose()


def _span(done) -> float:
    return (max(t.datetime_complete for t in done) - min(t.datetime_start for t in done)).total_seconds()


def run_study(label: str, n_workers: int, n_trials: int, common: list[str], tmp: Path, url: str, caches: list[Path],
              kill: bool = False) -> dict:
    """One study run by ``n_workers`` `tune` processes (worker i with cache ``caches[i]``); with ``kill`` the
    second worker is killed with SIGKILL in the middle of its first trial after the study's second finished one."""
    name = f"bench-{label}"
    procs = []
    t0 = time.perf_counter()
    for i in range(n_workers):
        env = dict(os.environ, IMTUNE_CACHE=str(caches[i]), IMTUNE_STORAGE=url, PYTHONPATH=str(ROOT))
        if kill and i == 1:
            env["IMTUNE_MACHINE"] = "another-machine"  # found dead by its heartbeat, as on a second machine
        args = [sys.executable, "-m", "tuner", *common, "--studies-dir", str(tmp / name / f"w{i}"),
                "--n-trials", str(n_trials), "--study", name, "--no-test", "--quiet"]
        procs.append(subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True, start_new_session=True))
    killed = None
    complete_before: set[int] = set()
    if kill:
        victim = procs[1]
        while victim.poll() is None:
            time.sleep(0.2)
            try:
                ts = _trials(url, name)
            except Exception:  # noqa: BLE001 - the study does not exist yet
                continue
            mine = [t for t in ts if t.state.name == "RUNNING" and t.params
                    and (t.system_attrs.get("imtune:worker") or {}).get("pid") == victim.pid]
            if mine and sum(t.state.name == "COMPLETE" for t in ts) >= 2:
                killed = mine[0]
                complete_before = {t.number for t in ts if t.state.name == "COMPLETE"}
                os.killpg(victim.pid, signal.SIGKILL)
                break
    outs = [p.communicate() for p in procs]
    wall = time.perf_counter() - t0
    for i, (p, (_, err)) in enumerate(zip(procs, outs)):
        if kill and i == 1:
            continue
        if p.returncode != 0:
            raise SystemExit(f"worker failed: {err.strip().splitlines()[-1] if err.strip() else p.returncode}")
    ts = _trials(url, name)
    done = [t for t in ts if t.state.name in ("COMPLETE", "PRUNED")]
    span = _span(done)
    out = {"label": label, "workers": n_workers, "target": n_trials, "finished": len(done),
           "running": sum(t.state.name == "RUNNING" for t in ts), "waiting": sum(t.state.name == "WAITING" for t in ts),
           "failed": sum(t.state.name == "FAIL" for t in ts), "trials": len(ts), "span_seconds": span,
           "process_wall_seconds": wall, "trials_per_minute": 60.0 * len(done) / span,
           "mean_trial_seconds": sum((t.datetime_complete - t.datetime_start).total_seconds() for t in done) / len(done)}
    if kill:
        if killed is None:
            raise SystemExit("the second worker ended before it could be killed mid-trial")
        after = {t.number for t in ts if t.state.name == "COMPLETE"}
        retry = [t for t in ts if t.system_attrs.get("failed_trial") == killed.number]
        out.update(killed_trial=killed.number, killed_state=ts[killed.number].state.name,
                   retried_as=[t.number for t in retry], retry_same_params=bool(retry) and retry[0].params == killed.params,
                   completed_lost=sorted(complete_before - after))
    return out


# -- the storage's cost per trial, and MaxTrialsCallback's overshoot -------------------------------------------

def storage_cost(url: str, n: int = 40) -> dict:
    """Seconds per trial of an instant objective through the claim loop and through plain ``study.optimize``,
    with heartbeats on (one process; what a trial costs the storage and the client besides its evaluation)."""
    import optuna

    from tuner.storage import open_storage
    from tuner.workers import run_to_target
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    out = {}
    for mode in ("claim", "plain"):
        storage = open_storage(url, heartbeat=10)
        study = optuna.create_study(study_name=f"cost-{mode}", storage=storage,
                                    sampler=optuna.samplers.RandomSampler(seed=0))
        t0 = time.perf_counter()
        if mode == "claim":
            run_to_target(study, lambda t: t.suggest_float("x", 0, 1), n)
        else:
            study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=n)
        out[mode] = (time.perf_counter() - t0) / n
        storage.engine.dispose()
    return out


OVERSHOOT_WORKER = """
import sys, time, optuna
sys.path.insert(0, {root!r})
from optuna.study import MaxTrialsCallback
from optuna.trial import TrialState
from tuner.storage import open_storage
from tuner.workers import run_to_target
optuna.logging.set_verbosity(optuna.logging.ERROR)
url, name, mode, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
study = optuna.load_study(study_name=name, storage=open_storage(url, heartbeat=10))
f = lambda t: (t.suggest_float("x", 0, 1), time.sleep(0.2))[0]
if mode == "optuna":
    study.optimize(f, callbacks=[MaxTrialsCallback(n, states=(TrialState.COMPLETE,))])
else:
    run_to_target(study, f, n)
"""


def overshoot(url: str, rounds: int = 3, workers: int = 3, n: int = 9) -> dict:
    """Finished trials of a study of target ``n`` run by ``workers`` processes: Optuna's MaxTrialsCallback alone
    vs the claim loop, ``rounds`` studies each."""
    import optuna

    from tuner.storage import open_storage
    code = OVERSHOOT_WORKER.format(root=str(ROOT))
    out: dict = {"workers": workers, "target": n}
    for mode in ("optuna", "claim"):
        got = []
        for r in range(rounds):
            name = f"overshoot-{mode}-{r}"
            storage = open_storage(url, heartbeat=None)
            optuna.create_study(study_name=name, storage=storage)
            storage.engine.dispose()
            ps = [subprocess.Popen([sys.executable, "-c", code, url, name, mode, str(n)], cwd=ROOT,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                  for _ in range(workers)]
            for p in ps:
                _, err = p.communicate()
                if p.returncode != 0:
                    raise SystemExit(f"overshoot worker failed: {err.strip().splitlines()[-1:]}")
            got.append(sum(t.state.name == "COMPLETE" for t in _trials(url, name)))
        out[mode] = got
    return out


def model(T: float, c: float, n: int, machines=(1, 2, 4, 8, 16, 32, 64)) -> list[dict]:
    """Speed-up S(M) = min(M, (T + c) / c) x n / (M ceil(n / M)) for a study of n trials, and for n large."""
    rows = []
    for m in machines:
        cap = min(m, (T + c) / c)
        rows.append({"machines": m, "speedup": cap * n / (m * math.ceil(n / m)), "speedup_large_n": cap})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--feature", default="sift")
    ap.add_argument("--num-features", type=int, default=2048)
    ap.add_argument("--ransac", default="degensac")
    ap.add_argument("--scenes", default="fountain-P11")
    ap.add_argument("--max-pairs", type=int, default=6)
    ap.add_argument("--trials", type=int, default=8, help="the study's --n-trials in every setting")
    ap.add_argument("--threshold", type=float, default=0.3)
    ap.add_argument("--max-iters", type=int, default=100000)
    ap.add_argument("--heartbeat", type=int, default=2, help="seconds; the grace period is 3 heartbeats")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=None, help="write the results as JSON here (and a .md beside it)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    common = ["--feature", args.feature, "--num-features", str(args.num_features), "--ransac", args.ransac,
              "--scenes", args.scenes, "--max-pairs", str(args.max_pairs), "--sampler", "random", "--pruner", "none",
              "--budget", "100", "--fix", f"threshold={args.threshold}", "--fix", f"max_iters={args.max_iters}",
              "--seed", str(args.seed), "--heartbeat", str(args.heartbeat), "--jobs", "1"]
    if args.data:
        common += ["--data", args.data]
    tmp = Path(tempfile.mkdtemp(prefix="imtune-workers-"))
    pg = _pg()
    try:
        # each worker its own cache, as on its own machine: one is filled, then copied (no worker computes features)
        warm = tmp / "cache-warm"
        env = dict(os.environ, IMTUNE_CACHE=str(warm), PYTHONPATH=str(ROOT))
        r = subprocess.run([sys.executable, "-m", "tuner", *common, "--studies-dir", str(tmp / "warm"),
                            "--storage", f"sqlite:///{tmp}/warm.db", "--n-trials", "1", "--no-test", "--quiet"],
                           cwd=ROOT, env=env, capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"warm-up failed: {r.stderr.strip()}")
        caches = []
        for i in range(2):
            caches.append(tmp / f"cache{i}")
            shutil.copytree(warm, caches[-1])
        load = os.getloadavg()[0]
        one = run_study("one", 1, args.trials, common, tmp, pg.url, caches)
        two = run_study("two", 2, args.trials, common, tmp, pg.url, caches)
        killed = run_study("killed", 2, args.trials, common, tmp, pg.url, caches, kill=True)
        cost = storage_cost(pg.url)
        over = overshoot(pg.url)
    finally:
        pg.close()
        shutil.rmtree(tmp, ignore_errors=True)
    T = one["mean_trial_seconds"]
    out = {"date": _dt.date.today().isoformat(), "command": "python benchmarks/workers.py " + " ".join(argv or sys.argv[1:]),
           "feature": args.feature, "num_features": args.num_features, "ransac": args.ransac, "scenes": args.scenes,
           "pairs": args.max_pairs, "cpus": os.cpu_count(), "load_before": load, "heartbeat": args.heartbeat,
           "runs": [one, two, killed], "ratio_two": two["trials_per_minute"] / one["trials_per_minute"],
           "ratio_killed": killed["trials_per_minute"] / one["trials_per_minute"],
           "storage_seconds_per_trial": cost, "overshoot": over,
           "model": model(T, cost["claim"], args.trials)}
    text = report(out)
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
        Path(args.out).with_suffix(".md").write_text(text + "\n")
    print(json.dumps(out, indent=2) if args.json else text)
    return 0


def report(o: dict) -> str:
    one, two, killed = o["runs"]
    lines = [f"# Many workers on one PostgreSQL study ({o['date']})", "",
             f"`{o['command'].strip()}`: {o['feature']} {o['num_features']}, {o['ransac']}, {o['scenes']} "
             f"({o['pairs']} pairs per trial), eta and Gamma pinned, random r, {one['target']} trials per study, "
             f"each worker its own cache; PostgreSQL on 127.0.0.1; {o['cpus']} CPUs, load before "
             f"{o['load_before']:.2f}.", "",
             "| setting | finished / target | trials in all | span (s) | trials/min | mean trial (s) | vs 1 worker |",
             "|---|---|---|---|---|---|---|"]
    for r, ratio in ((one, 1.0), (two, o["ratio_two"]), (killed, o["ratio_killed"])):
        lines.append(f"| {r['label']}: {r['workers']} worker(s) | {r['finished']} / {r['target']} | {r['trials']} | "
                     f"{r['span_seconds']:.1f} | {r['trials_per_minute']:.2f} | {r['mean_trial_seconds']:.2f} | "
                     f"{ratio:.2f} x |")
    lines += ["", f"Killed run: trial {killed['killed_trial']} ({killed['killed_state']} after the kill), retried as "
              f"{killed['retried_as']} with the same parameters: {killed['retry_same_params']}; RUNNING at the end: "
              f"{killed['running']}, WAITING: {killed['waiting']}; completed trials lost: "
              f"{len(killed['completed_lost'])}.", ""]
    c = o["storage_seconds_per_trial"]
    ov = o["overshoot"]
    lines += [f"Storage and client cost per trial, instant objective, one process: {c['claim'] * 1000:.0f} ms "
              f"through the claim loop, {c['plain'] * 1000:.0f} ms through plain `study.optimize`.", "",
              f"Finished trials for a target of {ov['target']} with {ov['workers']} workers (0.2 s sleep objective): "
              f"Optuna's MaxTrialsCallback alone {ov['optuna']}, the claim loop {ov['claim']}.", "",
              f"Model, T = {one['mean_trial_seconds']:.2f} s per trial, c = {c['claim'] * 1000:.0f} ms per trial "
              "(storage serialised): speed-up with M machines", "",
              "| machines | " + " | ".join(str(r["machines"]) for r in o["model"]) + " |",
              "|---|" + "---|" * len(o["model"]),
              f"| {one['target']} trials | " + " | ".join(f"{r['speedup']:.2f}" for r in o["model"]) + " |",
              "| many trials | " + " | ".join(f"{r['speedup_large_n']:.1f}" for r in o["model"]) + " |"]
    return "\n".join(lines + ["", *page_section(o)])


def page_section(o: dict) -> list[str]:
    """The section the Many machines page includes (``measured``), every figure read from ``o``."""
    one, two, killed = o["runs"]
    c, ov = o["storage_seconds_per_trial"], o["overshoot"]
    T, cost = one["mean_trial_seconds"], c["claim"]
    at_n = next((r for r in o["model"] if r["machines"] >= 2 * one["target"]), o["model"][-1])
    return ["## As the Many machines page quotes it", "", "<!-- --8<-- [start:measured] -->",
            f"Measured on {o['date']} (`{o['command'].strip()}`: {o['feature']} {o['num_features']}, {o['ransac']}, "
            f"{o['pairs']} {o['scenes']} pairs per trial, eta and Gamma pinned, {one['target']} trials; "
            f"{o['cpus']} cores, load average {o['load_before']:.1f} before the run):", "",
            "| setting | finished / target | trials/min | vs 1 worker |", "|---|---|---|---|",
            f"| 1 worker | {one['finished']} / {one['target']} | {one['trials_per_minute']:.1f} | 1.00 x |",
            f"| 2 workers | {two['finished']} / {two['target']} | {two['trials_per_minute']:.1f} | "
            f"{o['ratio_two']:.2f} x |",
            f"| 2 workers, one killed by `kill -9` | {killed['finished']} / {killed['target']} ({killed['trials']} "
            f"trials: {killed['failed']} FAIL, its retry) | {killed['trials_per_minute']:.1f} | "
            f"{o['ratio_killed']:.2f} x |", "",
            f"In the killed run the dead worker's trial was marked {killed['killed_state']} after the grace period "
            f"(3 heartbeats of {o['heartbeat']} s) and retried "
            f"{'with its parameters' if killed['retry_same_params'] else 'WITH OTHER PARAMETERS'} by the other "
            f"worker; {killed['running']} trials were left RUNNING and {len(killed['completed_lost'])} completed "
            f"trials were lost. With {ov['workers']} workers and a target of {ov['target']} (a 0.2 s objective, "
            f"{len(ov['claim'])} studies each), Optuna's `MaxTrialsCallback` alone finished "
            f"{', '.join(map(str, ov['optuna']))} trials; the claim loop {', '.join(map(str, ov['claim']))}.", "",
            f"A trial costs the storage and the client {cost * 1000:.0f} ms besides its evaluation (an instant "
            f"objective through the claim loop, {c['plain'] * 1000:.0f} ms through plain `study.optimize`). Taking "
            f"that cost as fully serialised at the database, trials of {T:.1f} s scale to about ({T:.1f} + "
            f"{cost:.2f}) / {cost:.2f} = {(T + cost) / cost:.0f} machines; below that the speed-up is the number of "
            f"machines, less the last round's idle workers when the trial count is not a multiple of it "
            f"({one['target']} trials on {at_n['machines']} machines: {at_n['speedup']:.1f} x).",
            "<!-- --8<-- [end:measured] -->"]


if __name__ == "__main__":
    raise SystemExit(main())
