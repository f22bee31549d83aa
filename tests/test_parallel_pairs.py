"""Stereo pairs in a pool of worker processes (``--jobs``, pipeline.tasks.pool) on real Strecha images: the same
records and pruning steps for any number of jobs, a `tune` study with the same trial values under --jobs 1 and 2,
a worker killed with SIGKILL mid-pair (a recorded failure, the evaluation goes on), Ctrl-C stopping the pool, the
bad-input lines, and the budget calibrated with as many estimators running at once. Real processes and signals."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import DATA, ROOT, copy_strecha_subset

STRECHA = DATA / "strecha"
pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")
TIMING = ("seconds",)  # record keys that are measurements of time (they differ run to run, whatever the jobs)


def _untimed(records):
    return [{k: v for k, v in r.items() if not any(t in k for t in TIMING)} for r in records]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("pool-cache")


@pytest.fixture(scope="module")
def data4(tmp_path_factory):
    return copy_strecha_subset(tmp_path_factory.mktemp("pool-data4"), ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"])


def _conf(max_iters=5000, threshold=0.5, ratio=0.85, strategy="both"):
    from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
    return PipelineConfig(feature=FeatureConfig(name="sift", num_features=2048),
                          matching=MatchConfig(ratio=ratio, strategy=strategy),
                          geometry=GeometryConfig(ransac="degensac", threshold=threshold, max_iters=max_iters, seed=3))


def _scenes(root=STRECHA):
    from tuner.evaluate import load_scenes
    return load_scenes(Path(root), ["fountain-P11"])


def _env(cache):
    return dict(os.environ, IMTUNE_CACHE=str(cache), PYTHONUNBUFFERED="1")


def tune(*args, cache, timeout=900):
    return subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], capture_output=True, text=True, cwd=ROOT,
                          env=_env(cache), timeout=timeout)


def test_same_records_and_steps_for_jobs_1_and_2(cache):
    from pipeline.cache import H5Cache
    from pipeline.tasks.pool import shutdown_pools
    from pipeline.tasks.stereo import StereoTask
    scenes, conf, h5 = _scenes(), _conf(), H5Cache(cache)
    out = {}
    for jobs in (1, 2):
        steps = []
        task = StereoTask(max_pairs=10, step_pairs=4, jobs=jobs)
        res = task.evaluate(scenes, conf, h5, on_step=lambda k, n, s, steps=steps: steps.append(
            (k, n, s["pairs"], s["mAA10"], s["units_total"], len(s["budget_seconds_units"]))))
        again = task.evaluate(scenes, conf, h5)  # the second trial reuses the pool and the data in memory
        out[jobs] = (res, steps, again)
    shutdown_pools()
    (r1, s1, a1), (r2, s2, a2) = out[1], out[2]
    assert len(r1.records) == 10 and [r["pair"] for r in r1.records] == [r["pair"] for r in r2.records]
    assert _untimed(r1.records) == _untimed(r2.records) == _untimed(a2.records) == _untimed(a1.records)
    assert s1 == s2 and [s[0] for s in s1] == [0, 1, 2] and s1[-1][2] == 10 and s1[0][4] == 10
    assert r1.summary["mAA10"] == r2.summary["mAA10"] and math.isfinite(r2.summary["mAA10"])
    assert all(r["ransac_seconds"] > 0 for r in r2.records if r["failure"] is None)  # measured in the workers
    print(f"POOL jobs 1 vs 2: {len(r1.records)} records identical (timings aside), steps {s1}")


def test_no_more_workers_than_pairs(cache):
    """--jobs above the pair count starts one worker per pair (each holds the scenes' data in memory; --jobs 64 on
    6 pairs started 64), with the records of a serial run."""
    from pipeline.cache import H5Cache
    from pipeline.tasks import pool as pool_mod
    from pipeline.tasks.stereo import StereoTask
    scenes, conf, h5 = _scenes(), _conf(), H5Cache(cache)
    serial = StereoTask(max_pairs=3, jobs=1).evaluate(scenes, conf, h5)
    wide = StereoTask(max_pairs=3, jobs=8).evaluate(scenes, conf, h5)
    try:
        p = pool_mod._POOLS["stereo"]
        assert p.jobs == 3 and len(p._procs) == 3, (p.jobs, len(p._procs))
    finally:
        pool_mod.shutdown_pools()
    assert len(wide.records) == 3 and _untimed(wide.records) == _untimed(serial.records)


def test_a_worker_killed_mid_pair_is_a_recorded_failure(cache):
    from pipeline.cache import H5Cache
    from pipeline.tasks import pool as poolmod
    from pipeline.tasks.stereo import StereoTask
    scenes, h5 = _scenes(), H5Cache(cache)
    # no ratio test, one direction, eta 0.05 px: DEGENSAC runs all 150k iterations (~1.5 s a pair), so a worker
    # found busy is still inside its pair when the signal lands
    conf = _conf(max_iters=150_000, threshold=0.05, ratio=1.0, strategy="uni")
    clean = StereoTask(max_pairs=6, step_pairs=2, jobs=1).evaluate(scenes, conf, h5)
    killed = []

    def on_step(k, n, summary):
        if killed:
            return
        killed.append(None)  # one attempt
        p = poolmod._POOLS["stereo"]
        deadline = time.time() + 20
        while time.time() < deadline:
            st = p._status
            busy = [(int(st[2 * s]), int(st[2 * s + 1])) for s in range(p.jobs) if int(st[2 * s + 1]) >= 0]
            if busy:
                os.kill(busy[0][0], signal.SIGKILL)
                killed[0] = busy[0]
                return
            time.sleep(0.01)

    task = StereoTask(max_pairs=6, step_pairs=2, jobs=2)
    res = task.evaluate(scenes, conf, h5, on_step=on_step)
    pool = poolmod._POOLS["stereo"]
    assert killed[0] is not None and pool.restarts == 1
    died = [r for r in res.records if r["failure"] == poolmod.WORKER_DIED]
    assert len(res.records) == len(clean.records) == 6  # nothing lost, nothing dropped
    # the killed worker's pair is a recorded failure, never run again in silence (before the fix the parent read
    # no exit code while the executor's manager thread was reaping the workers, and resubmitted the pair)
    assert len(died) == 1 and died[0]["err"] == math.inf, [r["failure"] for r in res.records]
    others = [r for r in res.records if r["failure"] != poolmod.WORKER_DIED]
    assert _untimed(others) == _untimed([r for r in clean.records if r["pair"] != died[0]["pair"]])
    was_failed = not math.isfinite(next(r for r in clean.records if r["pair"] == died[0]["pair"])["err"])
    assert res.summary["failed"] == clean.summary["failed"] + (0 if was_failed else 1)  # counts as a failure
    # and the pool works again for the next trial
    again = task.evaluate(scenes, conf, h5)
    assert _untimed(again.records) == _untimed(clean.records)
    poolmod.shutdown_pools()
    print(f"POOL kill -9 of worker {killed[0][0]} mid-pair: {len(died)} pair(s) recorded '{poolmod.WORKER_DIED}', "
          f"the others identical to the serial run, next evaluation complete")


def _children(pid):
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid and "spawn_main" in cmd and "resource_tracker import main" not in cmd:
            out.append(int(d.name))
    return out


def wait_for_workers(p, n: int, timeout: float = 300.0, interval: float = 0.2) -> list:
    """The pids of the ``n`` spawned worker processes of ``p`` once all run (fewer: ``p`` exited or time ran out),
    looking every ``interval`` s (0: as soon as they exist)."""
    deadline = time.time() + timeout
    workers = []
    while time.time() < deadline and p.poll() is None and len(workers) < n:
        time.sleep(interval)
        workers = _children(p.pid)
    return workers


def _alive(pid):
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _start_slow_evaluation(tmp_path, cache):
    """`tune evaluate --jobs 2` on 4 fountain images with pairs of 1e6 iterations each (seconds per pair), in its
    own session: a pool busy long enough to be signalled mid-pair."""
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"])
    args = ["evaluate", "--data", data, "--scenes", "fountain-P11", "--num-features", "2048", "--jobs", "2",
            "--ratio", "1", "--strategy", "uni", "--max-iters", "1000000", "--threshold", "0.05", "--json"]
    return subprocess.Popen([sys.executable, "-m", "tuner", *map(str, args)], cwd=ROOT, env=_env(cache),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def test_ctrl_c_stops_the_pool_at_once(tmp_path, cache):
    p = _start_slow_evaluation(tmp_path, cache)
    try:
        workers = wait_for_workers(p, 2)
        assert len(workers) == 2, "the pool never started"
        time.sleep(2.0)  # the workers are inside their pairs (1e6 iterations each)
        os.killpg(p.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole foreground group
        _, err = p.communicate(timeout=60)  # a hang fails here
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    assert p.returncode == 130, err[-2000:]
    # exactly the one interrupted line (the resource tracker's leak report is kept quiet:
    # pipeline.tasks.pool.quiet_resource_tracker)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err and lines == ["tune: interrupted"], err[-2000:]
    deadline = time.time() + 30
    while time.time() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.1)
    assert not any(_alive(w) for w in workers)
    print(f"POOL Ctrl-C: exit 130, workers {workers} gone, stderr {err.strip()!r}")


def test_tune_evaluate_json_records_identical_for_jobs_1_and_2(data4, cache):
    outs = []
    for jobs in (1, 2):
        r = tune("evaluate", "--data", data4, "--scenes", "fountain-P11", "--num-features", "2048", "--jobs", jobs,
                 "--seed", "5", "--pairs", "--json", cache=cache)
        assert r.returncode == 0, r.stderr[-2000:]
        outs.append(json.loads(r.stdout)["stereo"])
    a, b = outs
    assert len(a["pair_records"]) == 6
    assert _untimed(a["pair_records"]) == _untimed(b["pair_records"])
    assert a["mAA10"] == b["mAA10"] and a["NI"] == b["NI"]


def quick(data, studies, storage, name, *extra):
    return ["--data", data, "--feature", "sift", "--num-features", "2048", "--ransac", "degensac",
            "--scenes", "fountain-P11", "--max-pairs", "6", "--chunk-pairs", "2", "--studies-dir", studies,
            "--storage", storage, "--study", name, "--no-test", "--quiet", *extra]


def test_study_same_trial_values_with_jobs_1_and_2(tmp_path, data4, cache):
    import optuna

    from tuner.storage import open_storage
    got = []
    for jobs in (1, 2):
        storage = f"sqlite:///{tmp_path}/j{jobs}.db"
        # Gamma pinned and a generous budget: the trials' values depend on their parameters only (a calibrated
        # Gamma_max and the over-budget rule depend on timings, which no two runs share)
        r = tune(*quick(data4, tmp_path / f"s{jobs}", storage, "same", "--n-trials", "5", "--sampler", "random",
                        "--seed", "11", "--fix", "max_iters=3000", "--budget", "10", "--jobs", jobs), cache=cache)
        assert r.returncode == 0, r.stderr[-2000:]
        study = optuna.load_study(study_name="same", storage=open_storage(storage, heartbeat=None))
        got.append([(t.number, t.state.name, t.params, t.value, t.intermediate_values, t.user_attrs.get("sampler_seed"),
                     t.user_attrs.get("NI")) for t in study.trials])
    assert len(got[0]) == 5 and got[0] == got[1]
    assert len({tuple(sorted(t[2].items())) for t in got[0]}) == 5
    print(f"POOL study --jobs 1 vs 2: {len(got[0])} trials, identical parameters, values, intermediate values")


def test_jobs_bad_input_and_note(data4, cache):
    for bad in ("0", "-2", "x"):
        r = tune("evaluate", "--data", data4, "--jobs", bad, cache=cache)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2 and len(lines) == 1 and "--jobs" in lines[0], r.stderr
    from pipeline.cpus import available_cpus
    n = available_cpus() + 1
    r = tune("evaluate", "--data", data4, "--scenes", "fountain-P11", "--num-features", "2048", "--jobs", n,
             "--json", cache=cache)
    assert r.returncode == 0, r.stderr[-2000:]
    notes = [ln for ln in r.stderr.splitlines() if ln.startswith("note: --jobs")]
    assert len(notes) == 1 and f"more than the {n - 1} CPUs" in notes[0]
    from pipeline.errors import ImtuneError
    from pipeline.tasks.stereo import StereoTask
    with pytest.raises(ImtuneError, match="jobs must be >= 1"):
        StereoTask(jobs=0)


def test_imtune_jobs_sets_the_default_and_a_bad_value_is_one_line(tmp_path, data4, cache, monkeypatch):
    """$IMTUNE_JOBS is --jobs' default (the tests set it to 1, conftest); unset, the default is every usable CPU;
    --jobs overrides it; a malformed value stops `tune` with one line naming the variable (exit 2), never silently
    every CPU."""
    from pipeline.cpus import available_cpus
    from pipeline.errors import ImtuneError
    from pipeline.tasks.stereo import StereoTask
    monkeypatch.delenv("IMTUNE_JOBS")
    assert StereoTask().jobs == available_cpus()
    monkeypatch.setenv("IMTUNE_JOBS", "3")
    assert StereoTask().jobs == 3 and StereoTask(jobs=2).jobs == 2
    for bad in ("0", "-1", "two", "1.5"):
        monkeypatch.setenv("IMTUNE_JOBS", bad)
        with pytest.raises(ImtuneError, match="IMTUNE_JOBS"):
            StereoTask()
        r = tune("evaluate", "--data", data4, "--scenes", "fountain-P11", "--num-features", "2048", "--max-iters",
                 "1000", "--quiet", cache=cache)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2 and len(lines) == 1 and f"IMTUNE_JOBS={bad!r}" in lines[0], r.stderr[-2000:]
    monkeypatch.setenv("IMTUNE_JOBS", "2")  # the pool, started by the variable alone: the calibration says 2 jobs
    r = tune("calibrate", "--data", data4, "--scenes", "fountain-P11", "--num-features", "2048", "--pairs", "3",
             "--budget", "0.05", "--studies-dir", tmp_path, "--json", "--quiet", cache=cache)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout)["calibration"]["jobs"] == 2


def test_calibration_times_as_many_estimators_as_jobs(tmp_path, data4, cache):
    cals = {}
    for jobs in (1, 2):
        r = tune("calibrate", "--data", data4, "--scenes", "fountain-P11", "--num-features", "2048", "--pairs", "3",
                 "--budget", "0.05", "--studies-dir", tmp_path, "--jobs", jobs, "--json", "--quiet", cache=cache)
        assert r.returncode == 0, r.stderr[-2000:]
        cals[jobs] = json.loads(r.stdout)["calibration"]
    assert cals[1]["jobs"] == 1 and cals[2]["jobs"] == 2
    store = json.loads((tmp_path / "budgets.json").read_text())
    assert len(store) == 2 and sum(k.endswith("|jobs=2") for k in store) == 1  # two calibrations, kept apart


def test_slot_folders_of_dead_parents_are_removed(tmp_path):
    """A parent killed with kill -9 leaves its pool's slot folder; the next pool removes it, and keeps the folders
    of live processes (real processes: one that has exited, one still running)."""
    from pipeline.tasks.pool import SLOT_PREFIX, remove_stale_slot_dirs
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        dead_dir = tmp_path / f"{SLOT_PREFIX}{gone.pid}-abc"
        live_dir = tmp_path / f"{SLOT_PREFIX}{alive.pid}-def"
        other = tmp_path / "imtune-pool-notapid"
        for d in (dead_dir, live_dir, other):
            d.mkdir()
            (d / "0").write_text("")
        removed = remove_stale_slot_dirs(str(tmp_path))
        assert removed == [dead_dir.name]
        assert not dead_dir.exists() and live_dir.is_dir() and other.is_dir()
    finally:
        alive.kill()
        alive.wait()


def test_a_ctrl_c_while_workers_start_is_not_lost():
    """A Ctrl-C that arrives while the parent spawns or feeds workers (SIGINT held back there so that workers never
    inherit the terminal's Ctrl-C) still interrupts the parent. It used to be ignored there, and lost: a study sent
    Ctrl-C right after a trial, as its next pairs were submitted, ran on."""
    import threading

    from pipeline.tasks.pool import sigint_held
    assert threading.current_thread() is threading.main_thread()
    with pytest.raises(KeyboardInterrupt):
        with sigint_held():
            os.kill(os.getpid(), signal.SIGINT)  # the real signal, to this process
            time.sleep(0.2)
        time.sleep(2.0)  # delivered at the latest when the mask is restored
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())  # the mask is restored


@pytest.mark.parametrize("when", ["mid-pair", "while-workers-start"])
def test_a_parent_killed_with_kill_9_leaves_no_pair_workers(tmp_path, cache, when):
    """kill -9 of `tune` (or the OOM killer) mid-evaluation: its pair workers exit within seconds on their own.
    They used to wait forever on their call queue, orphaned (every worker holds the queue's write end, so its pipe
    never reaches EOF), each holding the scene's data. "while-workers-start": killed as soon as the worker
    processes exist, before they have imported anything; they used to read their parent's pid themselves, got
    init's, and stayed forever."""
    p = _start_slow_evaluation(tmp_path, cache)
    try:
        workers = wait_for_workers(p, 2, interval=0.2 if when == "mid-pair" else 0.0)  # 0: as soon as they exist
        assert len(workers) == 2, "the pool never started"
        if when == "mid-pair":
            time.sleep(2.0)  # inside their pairs
        os.kill(p.pid, signal.SIGKILL)  # the parent alone
        p.wait(timeout=60)  # (not communicate: its pipes stay open in the workers until they exit)
        # a pair in flight finishes first (the estimator holds the GIL; alone ~2.5 s a pair, minutes on a loaded
        # machine): the bound is generous, a worker that never leaves is what fails
        deadline = time.time() + 180
        while time.time() < deadline and any(_alive(w) for w in workers):
            time.sleep(0.2)
        left = [w for w in workers if _alive(w)]
    finally:
        for w in _children(p.pid) + workers:
            try:
                os.kill(w, signal.SIGKILL)
            except OSError:
                pass
        p.communicate()
    assert not left, f"pair workers {left} outlived their parent"


def test_a_worker_whose_parent_died_before_it_started_leaves_at_once():
    """``exit_with_parent`` is told its parent's pid: a process whose parent is already gone when it starts
    watching (reparented to init) exits at once instead of watching init. A starts B and exits; B, a second later,
    watches A."""
    code_b = ("import sys, time; time.sleep(1.0); from pipeline.tasks.pool import exit_with_parent; "
              "exit_with_parent(int(sys.argv[1])); time.sleep(60)")
    code_a = ("import os, subprocess, sys; "
              f"b = subprocess.Popen([sys.executable, '-c', {code_b!r}, str(os.getpid())]); print(b.pid)")
    a = subprocess.run([sys.executable, "-c", code_a], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert a.returncode == 0, a.stderr
    b = int(a.stdout.strip())
    try:
        deadline = time.time() + 30  # B sleeps 1 s, imports, and must leave; the bug kept it 60 s
        while time.time() < deadline and _alive(b):
            time.sleep(0.1)
        assert not _alive(b), "an orphan took init for its parent and stayed"
    finally:
        try:
            os.kill(b, signal.SIGKILL)
        except OSError:
            pass
