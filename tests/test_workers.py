"""Many `tune` workers on one study, as on many machines: real processes, real signals (SIGKILL, SIGTERM), a real
PostgreSQL server on 127.0.0.1 (one per module), and SQLite / journal files for one machine.

Checked: the study ends with exactly --n-trials finished trials and no RUNNING or WAITING one; a killed worker's
trial is failed and retried once, with its parameters, by a live worker; exactly one worker freezes and tests,
the others print its frozen settings; a test phase whose worker died is taken over; a RUNNING trial left by a
killed process in an SQLite or journal file is failed and retried at once on resume."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import DATA, ROOT, copy_strecha_subset

pytestmark = [pytest.mark.postgres,
              pytest.mark.skipif(not (DATA / "strecha").is_dir(), reason=f"real data not found at {DATA / 'strecha'}")]

SECRET = "pw-W0rkers-imtune"
IMAGES = ["0003.jpg", "0004.jpg", "0005.jpg"]
# slow-ish trials (Gamma pinned high, eta small: ~0.3 s per pair) so that a signal lands inside a trial; a budget
# every trial meets whatever the load, so that the study always has a feasible optimum
SLOW = ["--fix", "max_iters=150000", "--fix", "threshold=0.2", "--budget", "5"]


@pytest.fixture(scope="module")
def pg():
    from tests.pgserver import PgServer
    srv = PgServer(password=SECRET)
    try:
        yield srv
    finally:
        srv.close()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("workers-data")
    copy_strecha_subset(root, IMAGES, "fountain-P11")
    copy_strecha_subset(root, IMAGES, "Herz-Jesus-P8")
    return root


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("workers-cache")


def _env(cache, **extra):
    env = dict(os.environ, IMTUNE_CACHE=str(cache), PYTHONPATH=str(ROOT), **extra)
    env.pop("IMTUNE_DEBUG", None)
    env.pop("IMTUNE_MACHINE", None)
    env.update(extra)
    return env


def _args(data, studies, study, n, *extra):
    return ["run", "--data", data, "--feature", "sift", "--num-features", "512", "--ransac", "degensac",
            "--scenes", "fountain-P11", "--test-scenes", "Herz-Jesus-P8", "--max-pairs", "4", "--chunk-pairs", "4",
            "--calibration-pairs", "2", "--studies-dir", studies, "--study", study, "--n-trials", n,
            "--seed", "1", "--heartbeat", "1", "--test-runs", "1", "--ci-resamples", "200", "--json", *SLOW, *extra]


def _start(args, env):
    return subprocess.Popen([sys.executable, "-m", "tuner", *map(str, args)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            stdin=subprocess.DEVNULL)


def _study(storage, name):
    import optuna

    from tuner.storage import open_storage
    return optuna.load_study(study_name=name, storage=open_storage(storage, heartbeat=None, must_exist=True))


def _trials(storage, name):
    try:
        st = _study(storage, name)
    except Exception:  # noqa: BLE001 - the storage or the study does not exist yet
        return []
    try:
        return st.get_trials(deepcopy=False)
    finally:
        engine = getattr(st._storage, "_backend", st._storage)
        if hasattr(engine, "engine"):
            engine.engine.dispose()


def _wait_running_in(p, storage, name, timeout=300):
    """Wait until worker ``p`` evaluates a trial (RUNNING, parameters sampled, marked with its pid); returns
    (that trial, the numbers of the trials complete at that moment)."""
    deadline = time.time() + timeout
    while time.time() < deadline and p.poll() is None:
        time.sleep(0.2)
        ts = _trials(storage, name)
        mine = [t for t in ts if t.state.name == "RUNNING" and t.params
                and (t.system_attrs.get("imtune:worker") or {}).get("pid") == p.pid]
        if mine:
            return mine[0], {t.number for t in ts if t.state.name == "COMPLETE"}
    so, se = p.communicate(timeout=60) if p.poll() is not None else ("", "")
    raise AssertionError(f"worker {p.pid} ended (or stalled) before it ran a trial: {se[-2000:]}")


def _kill(p, sig):
    os.killpg(p.pid, sig)
    return p.communicate(timeout=120)


def _kill_mid_trial(p, storage, name, sig, timeout=300):
    """Send ``sig`` to worker ``p`` (its process group) while it evaluates a trial; returns (that trial, the numbers
    complete then, the worker's output). The worker is frozen (SIGSTOP) before the trial's state is read again, so
    a trial that ended between the first read and the signal (a short trial on a loaded machine: seen in CI) is not
    taken for a killed one; the worker then goes on (SIGCONT) to its next trial."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        trial, _ = _wait_running_in(p, storage, name, timeout=max(1.0, deadline - time.time()))
        os.killpg(p.pid, signal.SIGSTOP)
        try:  # a worker stopped inside a write may hold the storage's lock: then read again after it goes on
            ts = _trials(storage, name)
        except Exception:  # noqa: BLE001
            ts = []
        now = next((t for t in ts if t.number == trial.number), None)
        if now is not None and now.state.name == "RUNNING":
            os.killpg(p.pid, sig)
            os.killpg(p.pid, signal.SIGCONT)  # a stopped process handles SIGTERM once continued (SIGKILL at once)
            return now, {t.number for t in ts if t.state.name == "COMPLETE"}, p.communicate(timeout=120)
        os.killpg(p.pid, signal.SIGCONT)
    raise AssertionError(f"worker {p.pid} was never caught inside a trial")


def _finish(procs):
    outs = []
    for p in procs:
        try:
            outs.append(p.communicate(timeout=600))
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
    return outs


def _check_study(storage, name, n):
    """Exactly ``n`` finished trials, none RUNNING or WAITING; returns the trials."""
    ts = _trials(storage, name)
    states = [t.state.name for t in ts]
    assert sum(s in ("COMPLETE", "PRUNED") for s in states) == n, states
    assert "RUNNING" not in states and "WAITING" not in states, states
    return ts


def _test_files(*dirs):
    return sorted(str(f) for d in dirs for f in Path(d).rglob("test.json") if "earlier-" not in str(f))


def test_three_workers_one_killed(pg, data, cache, tmp_path):
    """The issue's check: three workers on one PostgreSQL study, --n-trials 6, one killed with SIGKILL mid-trial.
    The killed worker records another machine (IMTUNE_MACHINE), so its trial is found dead by the heartbeat's
    grace period, as on a real second machine, not by the process table."""
    name, n = "three", 6
    dirs = [tmp_path / f"machine{i}" for i in range(3)]
    procs = []
    for i, d in enumerate(dirs):
        env = _env(cache, IMTUNE_STORAGE=pg.url, **({"IMTUNE_MACHINE": "another-machine"} if i == 1 else {}))
        procs.append(_start(_args(data, d, name, n), env))
    victim = procs[1]
    try:
        killed, complete_before, (so, se) = _kill_mid_trial(victim, pg.url, name, signal.SIGKILL)
        assert victim.returncode == -signal.SIGKILL
        outs = _finish([procs[0], procs[2]])
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
    for p, (so, se) in zip([procs[0], procs[2]], outs):
        assert p.returncode == 0, se[-3000:]
        assert SECRET not in so + se
    ts = _check_study(pg.url, name, n)
    by_number = {t.number: t for t in ts}
    assert by_number[killed.number].state.name == "FAIL"
    retries = [t for t in ts if t.system_attrs.get("failed_trial") == killed.number]
    assert len(retries) == 1 and retries[0].state.name in ("COMPLETE", "PRUNED"), [t.number for t in retries]
    assert retries[0].params == killed.params
    survivors = {procs[0].pid, procs[2].pid}
    assert retries[0].system_attrs["imtune:worker"]["pid"] in survivors  # retried by a live worker
    assert all(by_number[k].state.name == "COMPLETE" for k in complete_before)  # no completed trial lost
    # one test phase: one test.json, both survivors print the same frozen settings
    assert len(_test_files(*dirs)) == 1, _test_files(*dirs)
    res = [json.loads(so) for so, _ in outs]
    assert [r["frozen"]["trial"] for r in res][0] == res[1]["frozen"]["trial"]
    assert res[0]["frozen"]["params"] == res[1]["frozen"]["params"]
    assert sorted(r["test_phase"]["this_worker"] for r in res) == [False, True]
    owner = next(r for r in res if r["test_phase"]["this_worker"])
    waiter = next(r for r in res if not r["test_phase"]["this_worker"])
    assert waiter["test"]["mean"]["mAA10"] == owner["test"]["mean"]["mAA10"]
    assert waiter["test_phase"]["test_json"] == _test_files(*dirs)[0]
    print(f"WORKERS 3 workers, 1 SIGKILLed in trial {killed.number}: {n} finished, retry #{retries[0].number} "
          f"by a survivor, {len(ts)} trials in all, 1 test.json")


def test_sigterm_worker_exact_count_and_test_phase_takeover(pg, data, cache, tmp_path):
    """SIGTERM stops a worker mid-trial (exit 143, its trial FAIL): the other finishes the study at exactly the
    target. Then two workers test it again with other options: the first to claim the test phase is killed while
    it tests, and the other takes the phase over when the lease (3 heartbeats) is not renewed."""
    name, n = "term", 4
    a, b = tmp_path / "a", tmp_path / "b"
    env = _env(cache, IMTUNE_STORAGE=pg.url)
    pa = _start(_args(data, a, name, n), env)
    pb = _start(_args(data, b, name, n), env)
    try:
        _, _, (_, se) = _kill_mid_trial(pa, pg.url, name, signal.SIGTERM)
        assert pa.returncode == 128 + signal.SIGTERM, se[-2000:]
        (so, se), = _finish([pb])
    finally:
        for p in (pa, pb):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
    assert pb.returncode == 0, se[-3000:]
    ts = _check_study(pg.url, name, n)
    assert any(t.state.name == "FAIL" for t in ts)
    # the terminated trial's parameters, when it had drawn them, were queued and evaluated by the live worker
    for f in (t for t in ts if t.state.name == "FAIL" and t.params):
        again = [t for t in ts if (t.system_attrs.get("retry_history") or [None])[-1] == f.number]
        assert [t.params for t in again] == [f.params], [(t.number, t.state) for t in ts]
        assert again[0].state.name in ("COMPLETE", "PRUNED"), again[0].state
    assert _test_files(a) == [] and len(_test_files(b)) == 1

    # the test phase taken over: 2 test runs is another phase (its options differ)
    c, d = tmp_path / "c", tmp_path / "d"
    extra = ["--test-runs", "2"]
    # the first tester records another machine: its death is seen by its lease running out, not the process table
    pc = _start(_args(data, c, name, n, *extra), _env(cache, IMTUNE_STORAGE=pg.url, IMTUNE_MACHINE="machine-c"))
    try:
        deadline = time.time() + 300
        while time.time() < deadline and pc.poll() is None:
            rec = _study(pg.url, name).user_attrs.get("test_phase") or {}
            if rec.get("pid") == pc.pid and rec.get("state") == "running":
                break
            time.sleep(0.2)
        assert pc.poll() is None, "the first worker ended before it was seen testing"
        pd = _start(_args(data, d, name, n, *extra), env)
        time.sleep(0.5)
        _kill(pc, signal.SIGKILL)
        (so, se), = _finish([pd])
    finally:
        for p in (pc, pd):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
    assert pd.returncode == 0, se[-3000:]
    out = json.loads(so)
    assert out["test_phase"]["this_worker"] is True and len(out["test"]["runs"]) == 2
    assert "stopped renewing its lease: taking it over" in se
    rec = _study(pg.url, name).user_attrs["test_phase"]
    assert rec["state"] == "done" and rec["pid"] == pd.pid and rec["took_over"]["pid"] == pc.pid
    assert _test_files(c) == [] and len(_test_files(d)) == 1


@pytest.mark.parametrize("kind", ["sqlite", "journal"])
def test_stale_running_trial_failed_and_retried_on_resume(data, cache, tmp_path, kind):
    """A worker on one machine killed mid-trial leaves its trial RUNNING; the resume fails it at once (its process
    is gone) and retries it once. Heartbeats are off, as a journal file has none: only the process check can tell
    the trial is dead."""
    storage = f"sqlite:///{tmp_path}/optuna.db" if kind == "sqlite" else f"journal:{tmp_path}/optuna.log"
    n = 3
    args = [*_args(data, tmp_path / "studies", "resume", n, "--no-test"), "--storage", storage, "--heartbeat", "0"]
    env = _env(cache)
    p = _start(args, env)
    try:
        killed, before, _ = _kill_mid_trial(p, storage, "resume", signal.SIGKILL)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    r = subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=300, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr[-3000:]
    ts = _check_study(storage, "resume", n)
    assert ts[killed.number].state.name == "FAIL"
    retries = [t for t in ts if t.system_attrs.get("failed_trial") == killed.number]
    assert len(retries) == 1 and retries[0].params == killed.params and retries[0].state.name == "COMPLETE"
    assert before <= {t.number for t in ts if t.state.name == "COMPLETE"}


RACE_WORKER = """
import sys, time, optuna
from tuner.storage import open_storage
from tuner.workers import run_to_target
optuna.logging.set_verbosity(optuna.logging.ERROR)
url, name, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
study = optuna.load_study(study_name=name, storage=open_storage(url, heartbeat=1))
run_to_target(study, lambda t: (t.suggest_float("x", 0, 1), time.sleep(0.05))[0], n, poll=0.1)
"""


def test_four_processes_racing_for_the_last_places_end_at_the_target(pg):
    """The claim loop alone (tuner.workers.run_to_target) with a 50 ms objective: four processes race for every
    place, two studies in a row; each ends with exactly its target finished, none RUNNING or WAITING, and every
    trial beyond the target is a surplus trial that never ran the objective (no parameter sampled into it by the
    objective's suggest: it has none)."""
    import optuna

    from tuner.storage import open_storage
    env = _env(ROOT)
    for r, n in enumerate((9, 13)):
        name = f"race-{r}"
        st = open_storage(pg.url, heartbeat=None)
        optuna.create_study(study_name=name, storage=st)
        st.engine.dispose()
        ps = [subprocess.Popen([sys.executable, "-c", RACE_WORKER, pg.url, name, str(n)], cwd=ROOT, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(4)]
        for p in ps:
            _, err = p.communicate(timeout=300)
            assert p.returncode == 0, err[-2000:]
        ts = _check_study(pg.url, name, n)
        extra = [t for t in ts if t.state.name != "COMPLETE"]
        assert all(t.state.name == "FAIL" and t.user_attrs.get("surplus") and not t.params for t in extra), extra
        print(f"WORKERS race: 4 processes, target {n}: {n} complete, {len(extra)} surplus")



def test_a_trial_created_in_the_race_is_surplus_and_gives_its_grid_point_back(tmp_path):
    """The race, made to happen: another worker's trial is created between this worker's check of the places and
    its own trial's creation (the storage's create_new_trial creates that one first). This worker's trial ranks
    beyond the target of 1: it is failed unevaluated (user attribute surplus, no parameter), and the grid point
    GridSampler drew for it is given back (Optuna's GridSampler counts a failed trial's point as visited)."""
    import optuna

    from tuner.workers import run_to_target
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    study = optuna.create_study(storage=f"sqlite:///{tmp_path}/race.db",
                                sampler=optuna.samplers.GridSampler({"x": [0, 1, 2]}))
    storage = study._storage
    inner, other = storage.create_new_trial, []

    def racing(study_id, template_trial=None):
        if not other:
            other.append(inner(study_id))  # another worker's trial, created first: it gets the smaller id
        return inner(study_id, template_trial)

    storage.create_new_trial = racing
    evaluated = []
    why = run_to_target(study, lambda t: evaluated.append(t.suggest_categorical("x", [0, 1, 2])) or 0.0, 1,
                        timeout=1.0, poll=0.1)
    assert why == "timeout" and evaluated == []  # the other trial holds the only place and never finishes here
    ts = study.get_trials(deepcopy=False)
    assert [t.state.name for t in ts] == ["RUNNING", "FAIL"] and ts[0]._trial_id == other[0]
    assert ts[1].user_attrs.get("surplus") is True and ts[1].params == {}
    assert ts[1].system_attrs["grid_id"] == -1  # drawn (0, 1 or 2) and given back
