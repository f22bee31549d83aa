"""Worker processes for the stereo pairs of an evaluation (``--jobs``): a persistent pool that keeps the
evaluated scenes' features and k-NN tables in memory, and a short-lived pool that runs one function in every
worker at once (the budget calibration times the estimator with all cores busy).

    from pipeline.tasks.pool import pair_pool, resolve_jobs
    pool = pair_pool(jobs, spec)                 # reused while the same data is evaluated (a whole study)
    for index, result in pool.imap(items):       # completion order; ``WORKER_DIED`` for a killed worker's item
        ...

Why processes and not threads: OpenCV's and pydegensac's estimators hold the GIL for parts of their work, and a
trial's cost is the estimator's; each worker runs BLAS / OpenMP / OpenCV with one thread, so ``jobs`` workers use
``jobs`` cores and an estimator's measured seconds are those of one core.

What a worker holds: the ``PairSpec`` (scenes, their pairs, the feature and matching configuration, the cache
folder) arrives once, as the pool initializer's argument (pickled once per worker at spawn); on its first pair a
worker reads those scenes' features and k-NN tables from the h5 cache (:func:`load_pair_data`) and keeps them for
the pool's life. The pool lives as long as the same data is evaluated (``PairSpec.key``): every trial of a study
reuses it; evaluating other data (the test scenes after a study) replaces it. ``shutdown_pools`` (also at exit)
stops it.

Faults: a worker that dies (killed by the OS, kill -9, a crash in a library) breaks the executor. The pair it was
evaluating (each worker writes the item it runs into a shared array) comes back as :data:`WORKER_DIED`, every other
unfinished item is resubmitted to a fresh pool, and the evaluation goes on. Ctrl-C (``KeyboardInterrupt``) kills
the workers at once (they ignore SIGINT themselves, so a terminal's Ctrl-C reaches only the parent, which stops
them; no traceback per worker and no wait for the pairs in flight).
"""
from __future__ import annotations

import atexit
import contextlib
import hashlib
import json
import os
import signal
import threading
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

from pipeline.cpus import available_cpus
from pipeline.errors import ImtuneError

if TYPE_CHECKING:
    from pipeline.config import PipelineConfig

#: the failure recorded for the item a dead worker was evaluating
WORKER_DIED = "worker process died"
#: what a worker returns for an item of an abandoned evaluation (a pruned trial) that had reached its queue
SKIPPED = "skipped: its evaluation was abandoned"
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                "VECLIB_MAXIMUM_THREADS")


#: the environment variable giving the default of ``--jobs`` (a batch job's share of a node, a shared machine)
JOBS_VAR = "IMTUNE_JOBS"


def resolve_jobs(jobs: int | None) -> int:
    """``jobs`` as a process count: None -> ``$IMTUNE_JOBS``, else every usable CPU; below 1 -> ImtuneError (a
    malformed ``$IMTUNE_JOBS`` too, naming it: never silently every CPU)."""
    if jobs is None:
        raw = os.environ.get(JOBS_VAR, "").strip()
        if not raw:
            return available_cpus()
        try:
            return resolve_jobs(int(raw))
        except (ValueError, ImtuneError):
            raise ImtuneError(f"{JOBS_VAR}={raw!r}: expected an integer >= 1 (the default of --jobs); unset it to "
                              "use every CPU") from None
    try:
        n = int(jobs)
    except (TypeError, ValueError):
        raise ImtuneError(f"jobs must be an integer >= 1, got {jobs!r}") from None
    if n < 1:
        raise ImtuneError(f"jobs must be >= 1 (worker processes evaluating pairs), got {n}")
    return n


@contextlib.contextmanager
def single_thread_env():
    """BLAS / OpenMP limited to one thread in processes started inside the block (a spawned worker inherits the
    environment and imports numpy before any initializer runs, so the variables must be set here). Restored
    afterwards. (The multiview task's bag workers use it too.)"""
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def one_thread_here():
    """BLAS, OpenMP, OpenCV and torch limited to one thread in *this* process inside the block, restored afterwards:
    an estimator run in-process (``--jobs 1``, a calibration timed alone) is then measured as in a pool worker.
    Without it, the idle threads of a BLAS pool spin-wait after a product (the k-NN matching, a calibration's
    matching) and their CPU seconds count against the estimator in ``time.process_time``: measured +20-55% over the
    calling thread's own CPU time for pydegensac right after a numpy product on 2 cores. threadpoolctl (the
    library scikit-learn uses for this) sets the loaded BLAS / OpenMP libraries at run time, where the environment
    variables of :func:`single_thread_env` come too late."""
    import sys

    from threadpoolctl import threadpool_limits
    cv2 = sys.modules.get("cv2")
    torch = sys.modules.get("torch")
    n_cv = cv2.getNumThreads() if cv2 is not None else None
    n_torch = torch.get_num_threads() if torch is not None else None
    with threadpool_limits(limits=1):
        if n_cv is not None:
            cv2.setNumThreads(1)
        if n_torch is not None and n_torch != 1:
            torch.set_num_threads(1)
        try:
            yield
        finally:
            if n_cv is not None:
                cv2.setNumThreads(n_cv)
            if n_torch is not None and n_torch != 1:
                torch.set_num_threads(n_torch)


TRACKER_WARNING = "ignore::UserWarning:multiprocessing.resource_tracker"


@contextlib.contextmanager
def quiet_resource_tracker():
    """Keep multiprocessing's resource-tracker process from printing "There appear to be N leaked semaphore
    objects to clean up at shutdown" after Ctrl-C has killed a pool: the semaphores are the executor's own queue
    locks, and the tracker unlinks them itself right after that message, so nothing leaks. The tracker is a
    separate process started with the first semaphore (inside the block: the executor's queues), inheriting the
    environment: the filter must be in PYTHONWARNINGS then (Python's own warning filters do not reach it).
    The caller's environment is restored afterwards."""
    cur = os.environ.get("PYTHONWARNINGS")
    if TRACKER_WARNING not in (cur or "").split(","):
        os.environ["PYTHONWARNINGS"] = ",".join(x for x in (cur, TRACKER_WARNING) if x)
    try:
        yield
    finally:
        if cur is None:
            os.environ.pop("PYTHONWARNINGS", None)
        else:
            os.environ["PYTHONWARNINGS"] = cur


@contextlib.contextmanager
def sigint_held():
    """SIGINT held back (blocked, not ignored) in the main thread while workers are started. A process spawned here
    inherits the blocked mask across exec, and its initializer ignores SIGINT before unblocking it
    (:func:`ignore_sigint_here`), so a worker never sees the terminal's Ctrl-C (the parent stops it). The parent
    loses no Ctrl-C: another thread's handler or the unblock delivers it (ignoring SIGINT here dropped a Ctrl-C that
    arrived during a submit, and the study ran on). Only the main thread runs Python's handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def ignore_sigint_here() -> None:
    """In a worker, first thing: SIGINT ignored, then unblocked (a Ctrl-C pending since the spawn is discarded)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def exit_with_parent(parent: int, period: float = 1.0) -> None:
    """In a worker: exit within ``period`` seconds of the death of ``parent`` (the pid of the process that started
    the pool, passed by it: kill -9, the OOM killer). Its call queue's pipe never reaches EOF, since every worker
    holds the queue's write end too, so it would otherwise wait there forever, orphaned, holding the scene's data
    in memory. The pid comes from the parent, not from ``os.getppid()`` here: a parent killed while its workers
    were still starting (importing) has already left them to init, and a worker that read its parent then took
    init for it and never left. (A thread polling the parent pid: portable and bound to the process, where Linux's
    PR_SET_PDEATHSIG is bound to the spawning thread. It runs between the estimator's calls, which hold the GIL.)"""
    import time
    if os.getppid() != parent:
        os._exit(1)

    def watch():
        while True:
            time.sleep(period)
            if os.getppid() != parent:
                os._exit(1)
    threading.Thread(target=watch, name="imtune-parent-watch", daemon=True).start()


def _limit_threads_here() -> None:
    try:
        import cv2
        cv2.setNumThreads(1)
    except Exception:  # noqa: BLE001 - OpenCV absent or built without a thread pool
        pass


def kill_processes(procs) -> None:
    for p in list(procs):
        try:
            p.kill()
        except Exception:  # noqa: BLE001 - already gone
            pass
    for p in list(procs):
        try:
            p.join(timeout=5)
        except Exception:  # noqa: BLE001
            pass


def kill_executor(ex, procs=None) -> None:
    """Stop a ProcessPoolExecutor now (Ctrl-C, a broken pool): kill its processes (its own and ``procs``),
    shut it down without waiting for its items, and wait (at most 5 s) for its manager thread.
    That wait: Python 3.11's exit hook wakes every live manager thread through a pipe that the thread closes as it
    ends, without a lock between the two (3.12 added one), so a Ctrl-C that exits while the thread is ending printed
    "Exception ignored in: <module 'threading'> ... OSError: [Errno 9] Bad file descriptor" after
    "tune: interrupted". Once the thread has ended, its wake-up is closed and the hook skips it.

    ``procs`` (the caller's record of the workers, kept because a broken 3.11 executor forgets its own) adds to the
    executor's processes, never replaces them: a Ctrl-C landing inside ``submit`` after it spawned a worker and
    before the caller recorded it left that worker running its bag, and the exit waited for it (over a minute for
    a multiview trial's COLMAP bag on a loaded machine, after "tune: interrupted")."""
    own = list((getattr(ex, "_processes", None) or {}).values())
    kill_processes(own + [p for p in (procs or []) if p not in own])
    try:
        ex.shutdown(wait=False, cancel_futures=True)
    except Exception:  # noqa: BLE001 - a broken executor
        pass
    t = getattr(ex, "_executor_manager_thread", None)  # a private attribute: absent in another Python, no wait
    if t is not None and t.is_alive():
        t.join(5.0)
    if t is not None and t.is_alive():  # still ending (a loaded machine): keep the exit hook off its closing pipe
        import concurrent.futures.process as cfp
        getattr(cfp, "_threads_wakeups", {}).pop(t, None)  # it was woken by shutdown() already; 3.12 needs none
    quiet_exit_wakeups()


def quiet_exit_wakeups() -> None:
    """Make Python 3.11's exit hook for process pools (``concurrent.futures.process._python_exit``) ignore a wake-up
    pipe its manager thread has closed: the thread can close it between kill_executor's check above and the
    interpreter's exit (a race 3.12 closes with a lock), and the hook then printed a traceback ending in "OSError:
    [Errno 9] Bad file descriptor" after "tune: terminated" (once in CI). Hand-written: the standard library offers
    no switch; each registered wake-up's ``wakeup`` is wrapped to drop that OSError (the thread it would wake has
    ended)."""
    import concurrent.futures.process as cfp
    for w in list(getattr(cfp, "_threads_wakeups", {}).values()):
        if getattr(w, "_imtune_quiet", False):
            continue
        def wakeup(orig=w.wakeup):
            try:
                orig()
            except OSError:
                pass
        w.wakeup, w._imtune_quiet = wakeup, True


# ------------------------------------------------------------------------------------- the pair data

@dataclass
class PairSpec:
    """What the pair workers evaluate: the scenes, the pairs of each (``pairs[s]``), the configuration whose
    feature and matching sections made the cached features and k-NN tables, the cache folder, and the function
    evaluating one pair (``evaluate(scene, pair, fi, fj, tables, knn_seconds, conf, estimator)``, a module-level
    function: it is sent by name, so this module imports no task)."""
    scenes: list
    pairs: list
    conf: PipelineConfig
    cache_root: str
    evaluate: object = None  # e.g. pipeline.tasks.stereo.evaluate_pair
    key: str = field(default="")

    def __post_init__(self):
        if not self.key:
            self.key = pair_data_key(self.scenes, self.pairs, self.conf, self.cache_root)


def pair_data_key(scenes, pairs, conf, cache_root) -> str:
    """Identity of the data a pool holds: cache folder, feature configuration, the k-NN stage's settings, every
    scene's used image files and pair keys (a trial changes none of them; r, eta and Gamma are applied later)."""
    from pipeline.matching import neighbours_needed
    m = conf.matching
    parts = [str(cache_root), asdict(conf.feature), m.method, neighbours_needed(m), str(m.custom_matches)]
    if m.learned:  # its options change its output (the threshold min_confidence is per trial)
        parts.append(sorted(dict(m.matcher_options).items()))
    for sc, ps in zip(scenes, pairs):
        names = sorted({p.i for p in ps} | {p.j for p in ps})
        parts.append([sc.name, [str(sc.images[n].path) for n in names], [p.key for p in ps]])
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:20]


@dataclass
class PairData:
    """Features (``feats[s][image name]``) and k-NN tables (``tables[s][pair key]`` = (tables, seconds)) of the
    scenes of a :class:`PairSpec`, and features per image per scene (``nf``)."""
    feats: list
    tables: list
    nf: dict


def load_pair_data(spec: PairSpec, cache=None, progress: bool = False) -> PairData:
    """Read (or compute and cache) every scene's features and k-NN tables: what a worker keeps in memory."""
    import numpy as np
    from tqdm.auto import tqdm

    from pipeline.cache import H5Cache
    from pipeline.tasks.prepare import image_features, pair_knn
    cache = cache if cache is not None else H5Cache(spec.cache_root)
    conf = spec.conf
    feats, tables, nf = [], [], {}
    for sc, ps in zip(spec.scenes, spec.pairs):  # as pipeline.tasks.stereo.prepare_scene
        names = sorted({p.i for p in ps} | {p.j for p in ps})
        f = {n: image_features(cache, sc.images[n], conf.feature)
             for n in tqdm(names, desc=f"{sc.name}: features", disable=not progress, leave=False)}
        t = {p.key: pair_knn(cache, f[p.i], f[p.j], conf.matching)
             for p in tqdm(ps, desc=f"{sc.name}: matching", disable=not progress, leave=False)}
        feats.append(f)
        tables.append(t)
        nf[sc.name] = float(np.mean([len(x.keypoints) for x in f.values()])) if f else 0.0
    return PairData(feats=feats, tables=tables, nf=nf)


# ------------------------------------------------------------------------------------- in the worker

_W: dict = {}  # the worker's state: spec, data (loaded at its first pair), slot, status array, estimators


def _claim_slot(slot_dir: str, n: int) -> int:
    """A slot of the status array for this process: the first of ``slot_dir``/0..n-1 it creates (O_EXCL: atomic,
    and no semaphore, so nothing is left for multiprocessing's resource tracker when the pool is killed)."""
    for k in range(n):
        try:
            os.close(os.open(os.path.join(slot_dir, str(k)), os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
            return k
        except FileExistsError:
            continue
        except OSError:
            break
    return 1 << 30  # no slot: this worker's death cannot be attributed (it is retried, then an error)


def _init_pair_worker(spec: PairSpec, status, slot_dir: str, abandoned, parent: int) -> None:
    ignore_sigint_here()
    exit_with_parent(parent)
    _limit_threads_here()
    slot = _claim_slot(slot_dir, len(status) // 2)
    _W.clear()
    _W.update(spec=spec, data=None, slot=slot, status=status, estimators={}, abandoned=abandoned)
    if 2 * slot + 1 < len(status):
        status[2 * slot] = os.getpid()
        status[2 * slot + 1] = -1


def _pair_item(sub_id: int, si: int, pi: int, conf, keep: bool):
    """One pair in the worker: ``spec.evaluate`` (:func:`pipeline.tasks.stereo.evaluate_pair`) on the data in
    memory. Returns the PairResult (``keep``) or its record."""
    abandoned = _W.get("abandoned")
    if abandoned is not None and sub_id <= abandoned.value:
        return SKIPPED  # a pruned trial's pair already in the executor's call queue: not evaluated
    status, slot = _W["status"], _W["slot"]
    mine = 2 * slot + 1 < len(status)
    if mine:
        status[2 * slot + 1] = sub_id  # what the parent reads if this process dies
    try:
        if _W["data"] is None:
            _W["data"] = load_pair_data(_W["spec"])
        data, spec = _W["data"], _W["spec"]
        name = conf.geometry.ransac
        est = _W["estimators"].get(name)
        if est is None:
            from pipeline.geometry import get_estimator
            est = _W["estimators"][name] = get_estimator(name)
        scene, pair = spec.scenes[si], spec.pairs[si][pi]
        tab, knn_s = data.tables[si][pair.key]
        feats = data.feats[si]
        pr = spec.evaluate(scene, pair, feats[pair.i], feats[pair.j], tab, knn_s, conf, est)
    finally:
        if mine:
            status[2 * slot + 1] = -1
    return pr if keep else pr.record


# ------------------------------------------------------------------------------------- in the parent

SLOT_PREFIX = "imtune-pool-"  # + the parent's pid + "-": the slot folder of one pool


def remove_stale_slot_dirs(tmp: str) -> list[str]:
    """Remove the slot folders left in ``tmp`` by parents that died without clean-up (kill -9, the OOM killer):
    a folder whose parent pid is no longer alive. Returns the folders removed. (No library tracks a folder's
    owner across a SIGKILL; a folder of a live process, or a reused pid, is kept.)"""
    import shutil
    out: list[str] = []
    try:
        names = os.listdir(tmp)
    except OSError:
        return out
    for name in names:
        if not name.startswith(SLOT_PREFIX):
            continue
        pid = name[len(SLOT_PREFIX):].split("-", 1)[0]
        if not pid.isdigit() or os.path.exists(f"/proc/{pid}") or not os.path.isdir("/proc/self"):
            continue
        shutil.rmtree(os.path.join(tmp, name), ignore_errors=True)
        out.append(name)
    return out


class PairPool:
    """``jobs`` spawned worker processes evaluating the pairs of one :class:`PairSpec` (see the module
    docstring). Use :func:`pair_pool` to get the process's pool for some data."""

    def __init__(self, jobs: int, spec: PairSpec):
        self.jobs = int(jobs)
        self.spec = spec
        self.key = spec.key
        self._ex = None
        self._procs: dict = {}
        self._status = None
        self._abandoned = None  # shared: the last submission id of an abandoned evaluation (see _start)
        self._slot_dir = None
        self._sub = 0
        self.restarts = 0  # fresh pools started after a worker died

    # the executor ------------------------------------------------------------------------------
    def _start(self):
        import multiprocessing as mp
        import tempfile
        from concurrent.futures import ProcessPoolExecutor
        ctx = mp.get_context("spawn")
        # the status array: (pid, item being evaluated or -1) per worker; written by one worker each, read by the
        # parent after a break, so no lock (a lock is a semaphore the resource tracker reports when a pool is killed)
        self._status = ctx.RawArray("q", 2 * self.jobs)
        # the last submission id of an abandoned evaluation: Future.cancel() cannot take back an item the executor
        # has already moved to its call queue (up to jobs + 1 of them), so a worker skips such items itself rather
        # than spend a pruned trial's seconds (at a large Gamma, seconds per pair) before the next trial's pairs
        self._abandoned = ctx.RawValue("q", 0)
        remove_stale_slot_dirs(tempfile.gettempdir())
        self._slot_dir = tempfile.mkdtemp(prefix=f"{SLOT_PREFIX}{os.getpid()}-")
        self._procs = {}
        with quiet_resource_tracker():  # the executor's queue locks start the tracker
            self._ex = ProcessPoolExecutor(max_workers=self.jobs, mp_context=ctx, initializer=_init_pair_worker,
                                           initargs=(self.spec, self._status, self._slot_dir, self._abandoned,
                                                     os.getpid()))

    def _submit(self, *args):
        if self._ex is None:
            self._start()
        with single_thread_env(), sigint_held():  # a worker spawned here inherits both
            f = self._ex.submit(_pair_item, *args)
        self._procs.update(getattr(self._ex, "_processes", None) or {})
        return f

    def _drop(self, kill: bool) -> None:
        """Forget the executor; ``kill``: kill its processes now (a broken pool, Ctrl-C, shutdown)."""
        import shutil
        ex, procs = self._ex, list(self._procs.values())
        self._ex, self._procs = None, {}
        if self._slot_dir:
            shutil.rmtree(self._slot_dir, ignore_errors=True)
            self._slot_dir = None
        if ex is None:
            return
        if kill:
            kill_executor(ex, procs)  # Python 3.11's broken executor joins its workers: they must be gone
            return
        try:
            ex.shutdown(wait=True, cancel_futures=True)
        except Exception:  # noqa: BLE001 - a broken executor
            pass

    def shutdown(self) -> None:
        """Stop the workers (idle ones exit at once; the call queue is closed)."""
        self._drop(kill=False)

    def terminate(self) -> None:
        self._drop(kill=True)

    def _dead_items(self, wait: float = 10.0) -> set[int]:
        """Submission ids that a process which died on its own was evaluating (the executor itself terminates the
        survivors with SIGTERM after a break: those are not culprits).

        Waits (at most ``wait`` s) for every worker's exit code first: the futures fail before the executor's
        manager thread has terminated and reaped the workers, and while that thread waits for a process our own
        poll of it reads no exit code, so a killed worker read as 'no exit code' and its pair was silently run
        again instead of recorded as failed."""
        import time
        out: set[int] = set()  # submission ids
        st = self._status
        if st is None:
            return out
        deadline = time.monotonic() + wait
        while any(p.exitcode is None for p in self._procs.values()) and time.monotonic() < deadline:
            time.sleep(0.01)
        for slot in range(len(st) // 2):
            pid, sub = int(st[2 * slot]), int(st[2 * slot + 1])
            p = self._procs.get(pid)
            code = p.exitcode if p is not None else None
            if sub >= 0 and code is not None and code != -signal.SIGTERM:
                out.add(sub)
        return out

    # evaluating --------------------------------------------------------------------------------
    def imap(self, items: list, conf, keep: bool = False, in_flight: int | None = None):
        """Evaluate ``items`` ([(scene index, pair index)]); yields (position in ``items``, PairResult / record, or
        :data:`WORKER_DIED`) in completion order. At most ``in_flight`` (default 2 x jobs) items are submitted
        at a time, in the order given. Closing the generator early (a pruned trial) cancels what has not started;
        an exception (Ctrl-C) kills the workers."""
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool
        cap = int(in_flight or 2 * self.jobs)
        todo = list(range(len(items)))[::-1]  # a stack: pop() gives the next in order
        unexplained = 0  # consecutive breaks with no worker dead inside a pair
        inflight: dict = {}  # future -> (submission id, item position)
        clean = False
        try:
            while todo or inflight:
                try:
                    while todo and len(inflight) < cap:
                        k = todo.pop()
                        self._sub += 1
                        si, pi = items[k]
                        inflight[self._submit(self._sub, si, pi, conf, keep)] = (self._sub, k)
                    done, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
                    for f in done:
                        r = f.result()  # BrokenProcessPool below; a worker's exception (a bug) propagates
                        _, k = inflight.pop(f)
                        yield k, r
                except BrokenProcessPool:
                    dead = self._dead_items()
                    finished, again = [], []
                    for f, (sub, k) in list(inflight.items()):
                        if f.done() and not f.cancelled() and f.exception() is None:
                            finished.append((k, f.result()))
                        elif sub in dead:
                            finished.append((k, WORKER_DIED))
                        else:
                            again.append(k)
                    if dead:
                        unexplained = 0
                    else:  # no worker died inside a pair (at start-up, or sent SIGTERM): retry once, then stop
                        unexplained += 1
                        if unexplained > 1:
                            codes = sorted({str(p.exitcode) for p in self._procs.values() if p.exitcode is not None})
                            self._drop(kill=True)
                            raise ImtuneError(
                                f"the stereo pair workers keep dying before they evaluate a pair (exit codes "
                                f"{', '.join(codes) or 'unknown'}); run with --jobs 1 to see the error (a script "
                                "using jobs > 1 needs the `if __name__ == \"__main__\":` guard: workers are spawned)") from None
                    inflight.clear()
                    self._drop(kill=True)
                    self.restarts += 1
                    todo.extend(sorted(again, reverse=True))
                    for k, r in finished:
                        yield k, r
            clean = True
        except GeneratorExit:  # the consumer stopped (a pruned trial): keep the pool, drop what has not started
            if self._abandoned is not None:
                self._abandoned.value = self._sub
            for f in inflight:
                f.cancel()
            clean = True
            raise
        finally:
            if not clean:  # Ctrl-C or an error: stop at once
                self._drop(kill=True)


_POOLS: dict[str, PairPool] = {}
_POOLS_LOCK = threading.Lock()


def pair_pool(jobs: int, spec: PairSpec) -> PairPool:
    """This process's pool for ``spec``'s data with ``jobs`` workers: the running one when it holds the same data
    (the same key) with as many workers, else a new one (the previous pool is shut down: one pool at a time, so a
    study's workers are replaced by the test run's)."""
    with _POOLS_LOCK:
        p = _POOLS.get("stereo")
        if p is not None and p.key == spec.key and p.jobs == int(jobs):
            p.spec = spec
            return p
        if p is not None:
            p.shutdown()
        p = _POOLS["stereo"] = PairPool(jobs, spec)
        return p


def shutdown_pools() -> None:
    """Stop every pool of this process (called at exit)."""
    with _POOLS_LOCK:
        for p in _POOLS.values():
            try:
                p.shutdown()
            except Exception:  # noqa: BLE001
                pass
        _POOLS.clear()


atexit.register(shutdown_pools)


# ------------------------------------------------------------------------------------- all at once

_C: dict = {}


def _init_concurrent(payload, barrier, parent: int) -> None:
    ignore_sigint_here()
    exit_with_parent(parent)
    _limit_threads_here()
    _C.clear()
    _C.update(payload=payload, barrier=barrier)


def _concurrent_item(fn, args):
    _C["barrier"].wait(timeout=300)  # every worker starts together: the measurement sees all cores busy
    return os.getpid(), fn(_C["payload"], *args)


class ConcurrentRunner:
    """``jobs`` spawned processes that each run ``fn(payload, *args)`` at the same moment (a barrier), so every
    call is measured on a machine whose ``jobs`` cores are all busy. ``payload`` is sent once per worker.

        with ConcurrentRunner(jobs, payload) as run:
            results = run(fn, *args)      # one result per worker
    """

    def __init__(self, jobs: int, payload):
        self.jobs = int(jobs)
        self.payload = payload
        self._ex = None

    def __enter__(self):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor
        ctx = mp.get_context("spawn")
        with quiet_resource_tracker():  # the barrier's semaphores start the tracker
            self._barrier = ctx.Barrier(self.jobs)
        with single_thread_env(), sigint_held():
            self._ex = ProcessPoolExecutor(max_workers=self.jobs, mp_context=ctx, initializer=_init_concurrent,
                                           initargs=(self.payload, self._barrier, os.getpid()))
        return self

    def __call__(self, fn, *args) -> list:
        with single_thread_env(), sigint_held():
            assert self._ex is not None, "a ConcurrentRunner is called inside its `with` block"
            futs = [self._ex.submit(_concurrent_item, fn, args) for _ in range(self.jobs)]
        out = [f.result() for f in futs]
        pids = {pid for pid, _ in out}
        if len(pids) != self.jobs:  # cannot happen with the barrier; a silent overlap would be a wrong figure
            raise ImtuneError(f"concurrent measurement ran on {len(pids)} processes, not {self.jobs}")
        return [r for _, r in out]

    def __exit__(self, exc_type, exc, tb):
        ex, self._ex = self._ex, None
        if ex is None:
            return False
        if exc_type is not None:
            kill_executor(ex)
        else:
            ex.shutdown(wait=True, cancel_futures=True)
        return False
