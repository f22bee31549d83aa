"""`--terminate auto` (tuner.terminate): Optuna's terminator with the incumbent's validation interval as the error.

Synthetic studies with real Optuna (TPE, the GP regret bound): a smooth objective whose trials carry a wide
interval (every further gain would be a tie) stops at the minimum trial count; the same objective with a narrow
interval runs on. The CLI refuses it for a pareto study in one line."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import optuna
import pytest

from pipeline.errors import ImtuneError
from tuner.terminate import IncumbentIntervalError, make_terminator, min_trials, should_terminate

ROOT = Path(__file__).resolve().parents[1]


def _run(half_width: float, n: int = 40) -> optuna.Study:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    term = make_terminator("auto", n, seed=0)
    st = optuna.create_study(direction="maximize", sampler=optuna.samplers.TPESampler(seed=0))
    rng = np.random.default_rng(0)

    def obj(t):
        x, y = t.suggest_float("x", 0, 1), t.suggest_float("y", 0, 1)
        v = 0.7 - (x - 0.3) ** 2 - (y - 0.6) ** 2 + rng.normal(0, 0.01)
        t.set_user_attr("mAA10_ci", [v - half_width, v + half_width])
        return v
    for _ in range(n):
        st.optimize(obj, n_trials=1)
        if should_terminate(term, st):
            break
    return st


def test_wide_interval_stops_at_the_minimum_narrow_runs_on():
    wide = _run(0.3)
    assert len(wide.trials) == min_trials(40) == 20
    assert wide.user_attrs["terminated"]["trials"] == 20
    narrow = _run(0.0005)
    assert len(narrow.trials) > 30 and "terminated" not in narrow.user_attrs


def test_error_is_the_incumbents_half_width():
    st = optuna.create_study(direction="maximize")
    for v, half in ((0.5, 0.2), (0.8, 0.05), (0.6, 0.1)):
        t = st.ask()
        t.set_user_attr("mAA10_ci", [v - half, v + half])
        st.tell(t, v)
    assert IncumbentIntervalError().evaluate(st.trials, st.direction) == pytest.approx(0.05)


def test_off_is_none_and_pareto_is_refused():
    assert make_terminator("off", 50) is None
    with pytest.raises(ImtuneError, match="pareto"):
        make_terminator("auto", 50, "pareto")
    r = subprocess.run([sys.executable, "-m", "tuner", "run", "--objective", "pareto", "--terminate", "auto",
                        "--data", str(ROOT), "--studies-dir", "/nonexistent-h32"], capture_output=True, text=True,
                       cwd=ROOT, env=dict(os.environ), timeout=120)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "pareto" in r.stderr, r.stderr
