"""Trials left RUNNING by an interruption or a dead worker: tracked, failed, re-enqueued once."""
from __future__ import annotations

#: trial user attribute of a trial created in a race and never evaluated (:mod:`tuner.workers`)
SURPLUS_ATTR = "surplus"


def retried_numbers(trials) -> set[int]:
    """Numbers of the trials some later trial retries (Optuna's retry history ends with the trial retried)."""
    out = set()
    for t in trials:
        hist = t.system_attrs.get("retry_history")
        if isinstance(hist, list) and hist:
            out.add(int(hist[-1]))
    return out


def track_created_trials(storage) -> list[int]:
    """The ids of the trials this process creates on ``storage`` (or takes from its waiting queue), appended as
    the storage hands them out; the same list on every call for one storage object.

    Written by hand because Optuna has no hook between creating a trial and calling the objective: a Ctrl-C in
    that window (the trial's first read, the sampler's ``before_trial``) left a RUNNING trial that the objective
    never saw (seen in CI, Dec 2026). Wraps the public ``create_new_trial`` and ``set_trial_state_values`` of the
    storage object the study calls (``study._storage``: Optuna wraps an RDB storage in a cache that calls the RDB
    storage's private ``_create_new_trial``, so wrapping the RDB storage itself would see nothing)."""
    from optuna.trial import TrialState
    ids = getattr(storage, "_imtune_created_trials", None)
    if ids is not None:
        return ids
    ids = []
    create, set_state = storage.create_new_trial, storage.set_trial_state_values

    def create_new_trial(study_id, template_trial=None):
        trial_id = create(study_id, template_trial)
        ids.append(trial_id)
        return trial_id

    def set_trial_state_values(trial_id, state, values=None):
        taken = set_state(trial_id, state, values)
        if taken and state == TrialState.RUNNING:  # a waiting (enqueued) trial this process popped
            ids.append(trial_id)
        return taken

    storage.create_new_trial = create_new_trial
    storage.set_trial_state_values = set_trial_state_values
    storage._imtune_created_trials = ids
    return ids


def fail_interrupted_trials(study, numbers, trial_ids=()) -> list[int]:
    """Mark FAIL the trials of this process still RUNNING after an interruption, and retry once those that had
    drawn their parameters (:func:`retry_failed`: the next run of the study, in any worker, evaluates the same
    parameters first, as it does a dead worker's trial). The trials are those among ``numbers`` (the objective's)
    and among ``trial_ids`` (storage ids, see :func:`track_created_trials`: a trial interrupted before the objective
    saw it, which has no parameters to retry). One interrupted while Optuna recorded it (see
    :func:`interrupt_in_chain`) is left RUNNING too, and would wait for the heartbeat's grace period before a
    resume could see it stale. Best effort (the storage may be the thing that failed); returns the numbers
    marked."""
    from optuna.trial import TrialState
    marked = []
    try:
        numbers = set(numbers)
        for tid in list(trial_ids)[-2:]:  # one trial at a time: only the last can be running
            numbers.add(study._storage.get_trial(tid).number)
        running = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
        for n in sorted(numbers):
            if n in running:
                study.tell(n, state=TrialState.FAIL)
                marked.append(n)
        # the interrupted trial, failed here or by Optuna (whose _run_trial fails a trial on KeyboardInterrupt)
        trials = study.get_trials(deepcopy=False)
        retried = retried_numbers(trials)
        for t in trials:
            if t.number in numbers and t.state == TrialState.FAIL and t.params and t.number not in retried \
                    and not t.user_attrs.get(SURPLUS_ATTR):  # a surplus trial was never evaluated
                retry_failed(study, study._storage.get_trial(t._trial_id))
    except Exception:  # noqa: BLE001 - the interruption is what gets reported
        pass
    return marked


def fail_stale_trials(study) -> list[int]:
    """Fail (and re-enqueue once) the RUNNING trials of dead workers; returns their numbers.

    First the trials of dead processes of this host (:func:`fail_dead_local_trials`: at once, any storage), then
    Optuna's own check (``optuna.storages.fail_stale_trials``, RDB storages with heartbeats), which only sees
    trials that recorded a heartbeat; a worker killed between creating a trial and its first heartbeat (while the sampler
    runs) leaves a RUNNING trial without one, which is failed here once it is older than the grace
    period. Other hosts' trials in a storage without heartbeats (journal files) are left alone."""
    import datetime as _dt

    import optuna
    from optuna.trial import TrialState
    before = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
    try:
        fail_dead_local_trials(study)  # this host's dead processes: at once, any storage (journal files too)
    except Exception:  # noqa: BLE001 - best effort; the heartbeat check below still runs
        pass
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "experimental" since Optuna 2.9
        optuna.storages.fail_stale_trials(study)
    backend = getattr(study._storage, "_backend", study._storage)
    interval = getattr(backend, "heartbeat_interval", None)
    if not interval:
        after = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
        return sorted(before - after)
    grace = getattr(backend, "grace_period", None) or 2 * interval
    try:
        from optuna.storages._rdb import models
        running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
        session = backend.scoped_session()
        try:
            beating = {hb.trial_id for hb in session.query(models.TrialHeartbeatModel).all()}
        finally:
            backend.scoped_session.remove()
        cb = backend.get_heartbeat_stale_trial_callback()
        for t in running:
            start = t.datetime_start.replace(tzinfo=None) if t.datetime_start else None
            if t._trial_id in beating or start is None:
                continue
            # datetime_start is the creating worker's local time (Optuna's datetime.now())
            if (_dt.datetime.now() - start).total_seconds() <= grace:
                continue
            try:
                if backend.set_trial_state_values(t._trial_id, state=TrialState.FAIL):
                    if cb is not None:
                        cb(study, study._storage.get_trial(t._trial_id))
            except optuna.exceptions.UpdateFinishedTrialError:
                pass
    except Exception:  # noqa: BLE001 - best effort beyond Optuna's own check
        pass
    after = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
    return sorted(before - after)


#: trial system attribute naming the process that evaluates the trial: {"host", "pid", "proc_start", "trial_start"}
WORKER_ATTR = "imtune:worker"

#: how many times a dead worker's trial is retried (Optuna's RetryHeartbeatStaleTrialCallback ``max_retry``)
MAX_RETRY = 1


def _proc_start(pid: int) -> str | None:
    """The start time of process ``pid`` in clock ticks since boot (``/proc/PID/stat`` field 22), or None where
    there is no /proc. With the pid it names one process: a pid reused by a later process has another start."""
    try:
        with open(f"/proc/{int(pid)}/stat", "rb") as f:
            raw = f.read().decode("ascii", "replace")
    except OSError:
        return None
    return raw.rsplit(")", 1)[-1].split()[19]  # fields after "(comm)": state is field 3, starttime field 22


#: environment variable naming this worker's process space (see :func:`process_space`)
MACHINE_ENV = "IMTUNE_MACHINE"


def process_space() -> str | None:
    """Which processes this one can see: the kernel's boot id and this process's pid namespace
    (``$IMTUNE_MACHINE`` when set). Two workers with the same value see each other's pids; a host name is not
    enough (two containers on one host share it, and have separate pid namespaces). None where neither is
    readable (no /proc): then only the heartbeat tells a dead worker."""
    import os
    env = os.environ.get(MACHINE_ENV, "").strip()
    if env:
        return env
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip()
        return f"{boot}/{os.readlink('/proc/self/ns/pid')}"
    except OSError:
        return None


def worker_identity() -> dict:
    """This process as :data:`WORKER_ATTR` records it (no trial_start yet)."""
    import os
    import socket
    return {"host": socket.gethostname(), "space": process_space(), "pid": os.getpid(),
            "proc_start": _proc_start(os.getpid())}


def mark_worker(trial) -> None:
    """Record in ``trial`` (an optuna Trial this process is evaluating) which process runs it, so that a resume on
    the same host can tell a dead process's RUNNING trial from a live one at once (see :func:`fail_dead_local_trials`).
    ``trial_start`` ties the record to this run of the trial: a retry inherits its failed trial's system attributes
    (Optuna's retry callback copies them) and must not be read as the dead process's."""
    ident = dict(worker_identity())
    ident["trial_start"] = trial.datetime_start.isoformat() if trial.datetime_start else None
    trial.storage.set_trial_system_attr(trial._trial_id, WORKER_ATTR, ident)


def _process_dead(ident: dict) -> bool:
    import os
    try:
        pid = int(ident["pid"])
    except (KeyError, TypeError, ValueError):
        return False
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # exists, owned by another user
        pass
    start = ident.get("proc_start")
    now = _proc_start(pid)
    return start is not None and now is not None and now != start  # the pid was reused by another process


def retry_failed(study, trial) -> None:
    """Re-enqueue a failed trial's parameters once, as Optuna's heartbeat does for a stale trial (its own
    RetryHeartbeatStaleTrialCallback, so a retry looks the same whoever found the trial dead)."""
    import warnings

    import optuna
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "experimental"
        optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY)(study, trial)


def fail_dead_local_trials(study) -> list[int]:
    """Fail, and retry once, the RUNNING trials whose process (:data:`WORKER_ATTR`) ran in this process space
    (:func:`process_space`: this host, this pid namespace) and is gone.

    Written by hand because Optuna's heartbeat is the only dead-worker check it has, and it needs a grace period
    (and an RDB storage: a journal file has none): a resume on the machine where a worker was killed knows at once,
    from the process table, that the trial's process no longer exists. Other hosts' trials are left to the
    heartbeat. Returns the failed trials' numbers."""
    import datetime as _dt

    import optuna
    from optuna.trial import TrialState
    space = process_space()
    out: list[int] = []
    if space is None:
        return out
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        ident = t.system_attrs.get(WORKER_ATTR)
        if not isinstance(ident, dict) or ident.get("space") != space or not _process_dead(ident):
            continue
        try:  # the record must be this run's (a retry carries its failed trial's record until it is marked)
            rec = _dt.datetime.fromisoformat(str(ident.get("trial_start")))
            if t.datetime_start is None or abs((rec - t.datetime_start).total_seconds()) > 1.0:
                continue
        except ValueError:
            continue
        try:
            if study._storage.set_trial_state_values(t._trial_id, state=TrialState.FAIL):
                retry_failed(study, study._storage.get_trial(t._trial_id))
                out.append(t.number)
        except optuna.exceptions.UpdateFinishedTrialError:
            pass  # another worker failed it first
    return out
