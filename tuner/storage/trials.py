"""Trials left RUNNING by an interruption or a dead worker: tracked, failed, re-enqueued once."""
from __future__ import annotations


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
    """Mark FAIL the trials of this process still RUNNING after an interruption: those among ``numbers`` (the
    objective's) and among ``trial_ids`` (storage ids, see :func:`track_created_trials`: a trial interrupted
    before the objective saw it). One interrupted while Optuna recorded it (see :func:`interrupt_in_chain`) is
    left RUNNING too, and would wait for the heartbeat's grace period before a resume could see it stale. Best
    effort (the storage may be the thing that failed); returns the numbers marked."""
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
    except Exception:  # noqa: BLE001 - the interruption is what gets reported
        pass
    return marked


def fail_stale_trials(study) -> list[int]:
    """Fail (and re-enqueue once) the RUNNING trials of dead workers; returns their numbers.

    Optuna's own check (``optuna.storages.fail_stale_trials``) only sees trials that recorded a
    heartbeat; a worker killed between creating a trial and its first heartbeat (while the sampler
    runs) leaves a RUNNING trial without one, which is failed here once it is older than the grace
    period. Storages without heartbeats (journal files) are left alone."""
    import datetime as _dt

    import optuna
    from optuna.trial import TrialState
    before = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
    optuna.storages.fail_stale_trials(study)
    backend = getattr(study._storage, "_backend", study._storage)
    interval = getattr(backend, "heartbeat_interval", None)
    if not interval:
        return []
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
