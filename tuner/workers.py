"""Many workers on one study: an exact study-wide trial count, dead workers' trials retried, one test phase.

Every worker is the same ``tune`` command pointed at one storage. Optuna provides the parts: the storage hands out
trial ids and WAITING trials atomically (two workers never pop the same waiting trial), RDB heartbeats let
``optuna.storages.fail_stale_trials`` mark a dead worker's RUNNING trial FAIL after the grace period, and
``RetryHeartbeatStaleTrialCallback`` re-enqueues its parameters (once here). Study user attributes carry what the
workers tell each other.

What Optuna does not do is stop N workers at exactly n finished trials: ``MaxTrialsCallback`` checks after each
trial, so N workers that each start a trial while the study holds n - 1 end with up to n - 1 + N
(``benchmarks/workers.py`` measures it). Here a worker claims a trial's place before it evaluates anything
(:func:`run_to_target`):

- before asking for a trial, the places in use (finished, running and waiting trials, and a trial failed in the
  last seconds whose retry is due) must be fewer than the target; where a WAITING trial is there (a retry), the
  worker only takes it and never creates another;
- after asking, before evaluating, the trial's rank among the places by trial id (the storage's order of
  creation) must be below the target. Two workers that passed the first check at the same moment both created a
  trial; the later one is marked FAIL unevaluated (user attribute ``surplus``) and never counts.

A worker never leaves while the study is short of its target: it waits for the trials running elsewhere, and fails
and retries them if their worker dies. The first worker to see the study complete runs the test phase
(:class:`TestPhase`): a lease in the study's user attribute ``test_phase``, renewed while it runs, taken over by a
waiting worker when it is not renewed in time.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import threading
import time
from collections.abc import Callable

from tuner.storage.trials import SURPLUS_ATTR, retried_numbers  # SURPLUS_ATTR: created in a race, never evaluated

#: seconds a just-failed trial keeps its place while its retry is enqueued (the dead-trial check fails the trial,
#: then enqueues the retry: two storage writes; a worker counting in between would otherwise take the place)
RETRY_SETTLE_S = 5.0

#: study user attribute of the test phase
PHASE_ATTR = "test_phase"

#: study user attribute holding the frozen settings the test phase froze (what waiting workers print)
FROZEN_ATTR = "frozen"


class NoPlace(Exception):
    """Raised by the guarded ``create_new_trial`` when the worker may only take a waiting trial."""


class SurplusTrial(Exception):
    """A trial created in a race between two workers' checks: failed unevaluated, never counted."""


def _finished(t) -> bool:
    return t.state.name in ("COMPLETE", "PRUNED")


def places(trials, now: _dt.datetime | None = None) -> list:
    """The trials that hold one of the study's places: finished, running, waiting, and a failed trial that is
    about to be retried (failed less than :data:`RETRY_SETTLE_S` ago, not itself a retry, no retry yet, not a
    surplus trial). Optuna records a trial's times in the local time of the worker that wrote them: a failure
    time ahead of this worker's clock (another time zone) holds no place, so no place is ever held for long."""
    from tuner.storage.trials import MAX_RETRY
    now = now or _dt.datetime.now()
    retried = retried_numbers(trials)
    out = []
    for t in trials:
        s = t.state.name
        if s in ("COMPLETE", "PRUNED", "RUNNING", "WAITING"):
            out.append(t)
        elif s == "FAIL" and not t.user_attrs.get(SURPLUS_ATTR) and t.number not in retried \
                and len(t.system_attrs.get("retry_history") or []) < MAX_RETRY and t.datetime_complete is not None \
                and 0 <= (now - t.datetime_complete.replace(tzinfo=None)).total_seconds() < RETRY_SETTLE_S:
            out.append(t)
    return out


def holds_place(trials, trial_id: int, target: int) -> bool:
    """Whether the trial of storage id ``trial_id`` is among the first ``target`` places (by trial id)."""
    before = [t for t in places(trials) if t._trial_id < trial_id]
    return len(before) < target


class _CreateGuard:
    """Wraps the study storage's ``create_new_trial`` (the one call that adds a trial; waiting trials are taken by
    ``set_trial_state_values``): while ``take_only`` is set it raises :class:`NoPlace` instead, so ``study.ask``
    takes a waiting trial or fails without creating one."""

    def __init__(self, storage) -> None:
        self.take_only = False
        inner = storage.create_new_trial

        def create_new_trial(study_id, template_trial=None):
            if self.take_only and template_trial is None:
                raise NoPlace()
            return inner(study_id, template_trial)

        storage.create_new_trial = create_new_trial


def run_to_target(study, func: Callable, target: int, *, timeout: float | None = None, poll: float = 1.0,
                  callbacks: tuple = (), should_stop: Callable[[], bool] = lambda: False,
                  on_wait: Callable[[str], None] | None = None) -> str:
    """Run ``func`` (an Optuna objective) in trials of ``study`` until the study holds ``target`` finished
    (COMPLETE or PRUNED) trials, whoever runs them; returns why it stopped: ``"target"``, ``"timeout"`` or
    ``"stopped"`` (``should_stop()`` became true after a trial).

    Each trial goes through ``study.optimize(n_trials=1)``, so Optuna's heartbeat thread, stale-trial check and
    callbacks work as usual. While the study's places are all taken by trials running in other workers, this
    worker polls every ``poll`` seconds, failing stale trials (:func:`tuner.storage.fail_stale_trials`) and taking
    their retries; ``on_wait`` is called once with a line saying so."""
    from optuna.trial import TrialState

    from tuner.storage import fail_stale_trials
    from tuner.storage.trials import mark_worker
    guard = getattr(study._storage, "_imtune_create_guard", None)
    if guard is None:
        guard = _CreateGuard(study._storage)
        study._storage._imtune_create_guard = guard
    t0 = time.monotonic()

    def claimed(trial):
        mark_worker(trial)
        if not holds_place(study.get_trials(deepcopy=False), trial._trial_id, target):
            trial.set_user_attr(SURPLUS_ATTR, True)
            if "grid_id" in trial.storage.get_trial(trial._trial_id).system_attrs:  # GridSampler counts a failed trial's grid point as visited: the
                # point this trial drew must stay for a trial that runs (no valid grid id is negative)
                trial.storage.set_trial_system_attr(trial._trial_id, "grid_id", -1)
            raise SurplusTrial(f"trial {trial.number} was created beyond the study's {target} trials; not evaluated")
        return func(trial)

    said = False
    try:
        while True:
            fail_stale_trials(study)
            trials = study.get_trials(deepcopy=False)
            if sum(1 for t in trials if _finished(t)) >= target:
                return "target"
            if timeout is not None and time.monotonic() - t0 >= timeout:
                return "timeout"
            if any(t.state == TrialState.WAITING for t in trials):
                guard.take_only = True
            elif len(places(trials)) < target:
                guard.take_only = False
            else:
                if not said and on_wait is not None:
                    running = sum(1 for t in trials if t.state == TrialState.RUNNING)
                    on_wait(f"the study's last {running} trial(s) run in other workers: waiting for them (a dead "
                            "worker's trial is failed after the heartbeat's grace period and retried here)")
                    said = True
                time.sleep(poll)
                continue
            try:
                study.optimize(claimed, n_trials=1, catch=(SurplusTrial,), callbacks=list(callbacks),
                               gc_after_trial=False, show_progress_bar=False)
            except NoPlace:  # another worker took the waiting trial first
                continue
            if should_stop():
                return "stopped"
    finally:
        guard.take_only = False


# -- the test phase ----------------------------------------------------------------------------------------------

def _now() -> _dt.datetime:
    return _dt.datetime.now(_dt.timezone.utc)


def phase_key(study, extra: dict) -> str:
    """What identifies one test phase: the study's finished trials and the test's options (a study extended with
    more trials, or tested on other scenes, has another phase)."""
    done = sorted(t.number for t in study.get_trials(deepcopy=False) if _finished(t))
    text = json.dumps({"finished": done, **extra}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class TestPhase:
    """The study's one test phase, coordinated through its user attribute :data:`PHASE_ATTR`.

    The record says who runs the phase (a random token, host and pid), when it last renewed its lease (``beat``,
    UTC) and its state: ``running``, ``done`` (with the result), ``failed`` (with the error) or ``abandoned`` (an
    interrupted owner gives it up at once). A worker claims the phase by writing its record, waiting ``settle``
    seconds and reading it back: Optuna's user attributes are last-writer-wins, so after the wait every claimant
    reads the same owner. Written by hand: Optuna has no lock or compare-and-set on attributes."""

    __test__ = False  # not a pytest test class

    def __init__(self, study, key: str, *, lease: float, settle: float) -> None:
        import os
        import secrets
        import socket
        self.study, self.key, self.lease, self.settle = study, key, float(lease), float(settle)
        from tuner.storage.trials import _proc_start, process_space
        self.token = secrets.token_hex(8)
        self.me = {"host": socket.gethostname(), "pid": os.getpid(), "space": process_space(),
                   "proc_start": _proc_start(os.getpid())}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def record(self) -> dict | None:
        """The phase record as the storage holds it now (None: none, or another phase's)."""
        rec = self.study.user_attrs.get(PHASE_ATTR)
        return rec if isinstance(rec, dict) and rec.get("key") == self.key else None

    def stale(self, rec: dict) -> bool:
        """A running phase whose owner did not renew its lease in time, gave it up, or is a process of this
        process space (``tuner.storage.trials.process_space``) that no longer exists."""
        if rec.get("state") == "abandoned":
            return True
        if rec.get("state") != "running":
            return False
        from tuner.storage.trials import _process_dead, process_space
        if rec.get("space") is not None and rec.get("space") == process_space() and _process_dead(rec):
            return True  # its process, in this process space, is gone: no need to wait for the lease
        try:
            beat = _dt.datetime.fromisoformat(rec["beat"])
        except (KeyError, TypeError, ValueError):
            return True
        return (_now() - beat).total_seconds() > float(rec.get("lease", self.lease))

    def _write(self, **fields) -> None:
        rec = {"key": self.key, "owner": self.token, **self.me, "lease": self.lease,
               "beat": _now().isoformat(timespec="milliseconds"), **fields}
        self.study.set_user_attr(PHASE_ATTR, rec)

    def claim(self, previous: dict | None) -> bool:
        """Try to become the owner (``previous``: the record seen, None or stale). True if this worker owns it."""
        takeover = None if previous is None else {k: previous.get(k) for k in ("host", "pid", "state")}
        self._write(state="running", started=_now().isoformat(timespec="seconds"), took_over=takeover)
        time.sleep(self.settle)
        rec = self.record()
        return rec is not None and rec.get("owner") == self.token

    def start_renewing(self) -> None:
        """Renew the lease every third of it, in a thread, while this worker runs the phase."""
        def renew():
            while not self._stop.wait(self.lease / 3):
                try:
                    rec = self.record()
                    if rec is None or rec.get("owner") != self.token or rec.get("state") != "running":
                        return
                    rec["beat"] = _now().isoformat(timespec="milliseconds")
                    self.study.set_user_attr(PHASE_ATTR, rec)
                except Exception:  # noqa: BLE001 - a missed renewal lets another worker take over, nothing worse
                    pass
        self._thread = threading.Thread(target=renew, name="imtune-test-phase-lease", daemon=True)
        self._thread.start()

    def finish(self, state: str, **fields) -> None:
        """Stop renewing and record the phase's end (``done`` / ``failed`` / ``abandoned``)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        rec = self.record() or {}
        if rec.get("owner") not in (None, self.token) and state != "done":
            return  # another worker took it over meanwhile: its record stands
        self._write(state=state, started=rec.get("started"), took_over=rec.get("took_over"),
                    finished=_now().isoformat(timespec="seconds"), **fields)

    def wait(self, timeout: float, poll: float = 1.0) -> tuple[str, dict | None]:
        """Wait for another worker's phase: ``("done" | "failed", record)``, ``("claimable", record or None)``
        when its owner is gone (or there is none), ``("timeout", record)`` after ``timeout`` seconds."""
        t0 = time.monotonic()
        while True:
            rec = self.record()
            if rec is None or self.stale(rec):
                return "claimable", rec
            if rec.get("state") in ("done", "failed"):
                return rec["state"], rec
            if time.monotonic() - t0 >= timeout:
                return "timeout", rec
            time.sleep(poll)


def slim_test_result(result: dict) -> dict:
    """A test result without its per-pair errors (what the phase record keeps where the whole result is too large
    for the storage's attribute column)."""
    def slim_runs(runs):
        return [{k: v for k, v in r.items() if not isinstance(v, (list, dict)) or k == "scenes"} for r in runs or []]
    out = {k: v for k, v in result.items() if k not in ("runs", "reference", "identity", "validation")}
    out["runs"] = slim_runs(result.get("runs"))
    ref = result.get("reference")
    if isinstance(ref, dict):
        out["reference"] = {k: v for k, v in ref.items() if k not in ("runs", "config")}
    return out


__all__ = ["FROZEN_ATTR", "PHASE_ATTR", "RETRY_SETTLE_S", "SURPLUS_ATTR", "NoPlace", "SurplusTrial", "TestPhase",
           "holds_place", "phase_key", "places", "run_to_target", "slim_test_result"]
