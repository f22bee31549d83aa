"""Ctrl-C in Optuna's window between creating a trial and calling the objective (the trial's first read, the
sampler's ``before_trial``): the trial must end FAIL, not RUNNING. CI hit this window at random in
test_tuner_study.py::test_ctrl_c_keeps_completed_trials (Dec 2026): the trial had no parameters, no attributes,
and stayed RUNNING, so a resume counted it as running until the heartbeat's grace period. Here a real SIGINT is
sent to this process at a chosen point of that window, on a real short study (2048 SIFT, DEGENSAC, real Strecha
images, SQLite storage)."""
from __future__ import annotations

import os
import signal
import time

import pytest

from tests.test_pruners import STRECHA, _settings, cache, data4  # noqa: F401 (fixtures)

pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")


def test_ctrl_c_before_the_objective_sees_its_trial_leaves_no_running_trial(tmp_path, data4, cache, monkeypatch):
    import optuna
    from optuna.trial import TrialState

    import tuner.study as study_mod

    class SigintInThirdTrialsCreation(optuna.samplers.RandomSampler):
        """Optuna's random sampler; at the third trial's ``before_trial`` (the trial exists in the storage, the
        objective has not been called) this process gets a real SIGINT, as from Ctrl-C in the terminal."""
        def before_trial(self, study, trial):
            if trial.number == 2:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(30)  # the signal interrupts this at once (KeyboardInterrupt)
            super().before_trial(study, trial)

    monkeypatch.setattr(study_mod, "make_sampler",
                        lambda name, seed, space, startup=None: SigintInThirdTrialsCreation(seed=seed))
    monkeypatch.setenv("IMTUNE_CACHE", str(cache))
    s = _settings(data4, tmp_path, budget=50.0, study_name="ctrl-c-window", n_trials=5, jobs=1)
    ctx = study_mod.setup_study(s)
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        study_mod.optimize(ctx, s)
    assert time.monotonic() - t0 < 25  # the sleep was interrupted: the SIGINT landed where it was sent
    st = optuna.load_study(study_name="ctrl-c-window", storage=s.storage)
    states = [t.state for t in st.trials]
    assert states == [TrialState.COMPLETE, TrialState.COMPLETE, TrialState.FAIL], states
    assert st.trials[2].params == {}  # interrupted before the objective drew anything


SWALLOWED = r"""
import os, signal, sys, time, weakref
from tuner import cli

class Held:
    pass

def callback(_):
    # what a real signal does when it lands while a weakref callback runs (SQLAlchemy's _collection_gced)
    os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    time.sleep(5)  # the handler raises here, inside the callback: CPython drops it ("Exception ignored")

def command(argv):
    held = Held()
    ref = weakref.ref(held, callback)  # noqa: F841 (kept, so its callback runs when `held` goes)
    try:
        del held
        t0 = time.monotonic()
        while time.monotonic() - t0 < 20:  # a study going on
            sum(range(1000))
    except KeyboardInterrupt as e:  # as cli._main does
        print("interrupted")
        return 143 if isinstance(e, cli.Terminated) else 130
    print("went on")
    return 0

cli._main = command
sys.exit(cli.main([]))
"""


@pytest.mark.parametrize("sig,code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_a_signal_dropped_inside_a_weakref_callback_still_stops_the_command(tmp_path, sig, code):
    """A real Ctrl-C / SIGTERM whose KeyboardInterrupt CPython drops (raised inside a weakref callback, where it
    cannot propagate) still stops the command, once, with its exit code and no "Exception ignored" text."""
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    p = subprocess.run([sys.executable, "-c", SWALLOWED, sig], cwd=root, capture_output=True, text=True, timeout=60,
                       env=dict(os.environ, PYTHONPATH=str(root)))
    assert "went on" not in p.stdout and "interrupted" in p.stdout, (p.stdout, p.stderr)
    assert p.returncode == code, (p.returncode, p.stderr)
    assert "Exception ignored" not in p.stderr and "Traceback" not in p.stderr, p.stderr


HEARTBEAT_WINDOW = r"""
import argparse, os, signal, sys, threading, time
import optuna
from optuna.storages._heartbeat import HeartbeatThread
from tuner import cli

optuna.logging.set_verbosity(optuna.logging.ERROR)
start = HeartbeatThread.start

def start_then_sigint(self):
    start(self)  # the heartbeat thread runs now
    os.kill(os.getpid(), signal.SIGINT)  # a real Ctrl-C before __enter__ returns: Optuna never calls __exit__
    time.sleep(20)

HeartbeatThread.start = start_then_sigint
if sys.argv[2] == "no-stop":  # the watchdog alone
    cli.stop_stray_heartbeats = lambda wait=5.0: 0
    cli.EXIT_GRACE = 3.0

def command(argv):
    storage = optuna.storages.RDBStorage(f"sqlite:///{sys.argv[1]}/hb.db", heartbeat_interval=1, grace_period=2)
    study = optuna.create_study(storage=storage)
    try:
        study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=3)
    except KeyboardInterrupt as e:
        code = cli._interrupted(e, argparse.Namespace())
        alive = [t for t in threading.enumerate() if getattr(t, "_target", None) is HeartbeatThread._record_heartbeat]
        print("heartbeat threads alive:", len(alive), flush=True)
        return code
    print("went on")
    return 0

cli._main = command
sys.exit(cli.main())
"""


@pytest.mark.parametrize("mode", ["stop", "no-stop"])
def test_ctrl_c_inside_optunas_heartbeat_start_still_exits(tmp_path, mode):
    """A real Ctrl-C landing in Optuna's ``HeartbeatThread.__enter__`` after its (non-daemon) thread started: Optuna
    never stops that thread, and the program printed "interrupted" and hung at exit (CI, test_ctrl_c_keeps_completed
    _trials). ``stop``: the interruption stops the stray thread, so none is alive after it. ``no-stop``: with that
    switched off, the program still exits with 130 (the exit watchdog), where it used to hang forever."""
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    p = subprocess.run([sys.executable, "-c", HEARTBEAT_WINDOW, str(tmp_path), mode], cwd=root, capture_output=True,
                       text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(root)))
    assert "went on" not in p.stdout and "interrupted" in p.stderr, (p.stdout, p.stderr)
    assert p.returncode == 130, (p.returncode, p.stderr)
    assert f"heartbeat threads alive: {0 if mode == 'stop' else 1}" in p.stdout, p.stdout
    assert "Traceback" not in p.stderr, p.stderr
