"""Stopping worker pools: no worker outlives a Ctrl-C, even one its caller never recorded. Real processes
(spawn), real ProcessPoolExecutor; no mocks."""
import argparse
import multiprocessing as mp
import time
from concurrent.futures import ProcessPoolExecutor

from pipeline.tasks.pool import kill_executor, kill_processes


def _dead(pid: int) -> bool:
    """Gone or a zombie, read from /proc: ``Process.is_alive()`` can say True for a killed worker while the
    executor's manager thread is reaping it (two threads waiting on one child)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def test_kill_executor_kills_the_workers_its_caller_never_recorded():
    """A Ctrl-C landing inside ``submit`` after the executor spawned a worker, before the caller recorded it
    (multiview's ``_pool_pass``, the pair pool's ``_submit``): kill_executor was given the stale record and killed
    only those, the unrecorded worker ran its bag on and the exit waited for it (CI: a multiview study's SIGINT
    still running 60 s after "tune: interrupted")."""
    ex = ProcessPoolExecutor(max_workers=2, mp_context=mp.get_context("spawn"))
    for _ in range(4):
        ex.submit(time.sleep, 120)
    procs = list(ex._processes.values())
    try:
        assert [p.is_alive() for p in procs] == [True, True]  # spawned by the submits, working or starting
        kill_executor(ex, [])  # the caller's record: empty, as when the interrupt came before it was updated
        deadline = time.time() + 30  # left alive, a worker sleeps its 120 s
        while time.time() < deadline and not all(_dead(p.pid) for p in procs):
            time.sleep(0.1)
        assert [_dead(p.pid) for p in procs] == [True, True]
    finally:
        kill_processes(procs)


def test_an_interruption_leaves_no_child_process_behind():
    """Whatever child a pool could not know of (CPython records a spawned worker a moment after starting it), the
    CLI's interruption handling kills: the interpreter's exit would otherwise join it, waiting for its work."""
    from tuner.cli import _interrupted
    p = mp.get_context("spawn").Process(target=time.sleep, args=(120,))
    p.start()
    try:
        assert p.is_alive()
        assert _interrupted(KeyboardInterrupt(), argparse.Namespace(on_interrupt="x")) == 130
        assert _dead(p.pid)
    finally:
        kill_processes([p])


_CLOSED_WAKEUP = """
import multiprocessing as mp, threading, time
from concurrent.futures import ProcessPoolExecutor
import concurrent.futures.process as cfp
from pipeline.tasks.pool import kill_executor, quiet_exit_wakeups
if __name__ == "__main__":
    ex = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"))
    ex.submit(time.sleep, 60)
    time.sleep(0.5)
    kill_executor(ex, [])
    # what the race leaves: a wake-up the exit hook still lists whose pipe its manager thread has closed
    w = cfp._ThreadWakeup()
    w._writer.close()
    gone = threading.Thread(target=int)  # an ended thread, held: the hook's registry holds its threads weakly
    gone.start()
    gone.join()
    cfp._threads_wakeups[gone] = w
    quiet_exit_wakeups()  # the last thing the CLI's interruption path does
    print("exiting", flush=True)
"""


def test_an_exit_after_kill_executor_prints_no_traceback_from_a_closed_wakeup(tmp_path):
    """CI: `tune` terminated by SIGTERM with a pair pool printed "tune: terminated ..." and then a traceback from
    Python 3.11's pool exit hook ("OSError: [Errno 9] Bad file descriptor": the manager thread's wake-up pipe closed
    as the hook wrote to it). A real spawn pool, the pipe closed for real, the real interpreter exit."""
    import subprocess
    import sys
    from pathlib import Path
    script = tmp_path / "closed_wakeup.py"
    script.write_text(_CLOSED_WAKEUP)
    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=root,
                       env={**__import__("os").environ, "PYTHONPATH": str(root)})
    assert r.stdout.strip() == "exiting", (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and "Bad file descriptor" not in r.stderr, r.stderr


def test_a_worker_killed_whose_exit_code_comes_late_is_still_the_culprit():
    """A broken pool's futures fail before the executor's manager thread has reaped its workers: the killed worker's
    exit code may not be readable yet when the parent asks which item died. Here two real spawned workers, one on
    item 5 (killed with SIGKILL) and one on item 6 (terminated with SIGTERM, as the executor stops survivors), both
    signalled 0.3 s after the question: item 5 is the dead worker's, 6 is not. Before the fix the parent read
    'no exit code', found no culprit, and the item was silently evaluated again instead of recorded as failed."""
    import signal
    import threading
    from types import SimpleNamespace

    from pipeline.tasks.pool import PairPool
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=time.sleep, args=(60,)) for _ in range(2)]
    for p in procs:
        p.start()
    try:
        pool = PairPool(2, SimpleNamespace(key="k"))
        pool._status = ctx.RawArray("q", [procs[0].pid, 5, procs[1].pid, 6])
        pool._procs = {p.pid: p for p in procs}
        threading.Timer(0.3, lambda: (procs[0].kill(), procs[1].terminate())).start()
        dead = pool._dead_items()
        assert dead == {5}, (dead, [p.exitcode for p in procs])
        assert procs[0].exitcode == -signal.SIGKILL and procs[1].exitcode == -signal.SIGTERM
    finally:
        for p in procs:
            p.kill()
            p.join()
