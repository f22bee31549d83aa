"""benchmarks/reconstruction_spread.py reads a real Optuna study (sqlite, as `tune` writes it): the defaults' trial
apart, pruned trials counted and never scored, one row per dataset, mapper and search space, the table saying each (in that order); bad options
are one line with exit 2. Figures expected here are computed by hand from the trials written."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import optuna
import pytest
from optuna.distributions import FloatDistribution
from optuna.trial import TrialState, create_trial

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "reconstruction_spread.py"


def _load():
    spec = importlib.util.spec_from_file_location("reconstruction_spread", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _study(tmp_path: Path) -> Path:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="s", storage=f"sqlite:///{tmp_path / 'optuna.db'}", direction="maximize")
    dist = {"ratio": FloatDistribution(0.6, 1.0)}

    def add(r, score, state=TrialState.COMPLETE, **attrs):
        ua = dict(attrs)
        if score is not None:
            ua["scenes"] = {"d": {"score": score}}
        study.add_trial(create_trial(params={"ratio": r}, distributions=dist, state=state, user_attrs=ua,
                                     value=score if state == TrialState.COMPLETE else None))

    add(0.8, 0.9, start="task defaults")
    for r, x in [(0.61, 0.0), (0.7, 0.2), (0.75, 0.4), (0.9, 0.6)]:
        add(r, x)
    add(0.97, None, state=TrialState.PRUNED, pruned_reason="trial timeout: mapping stopped over the bound of 120 s")
    return tmp_path


def test_pruned_trials_are_counted_not_scored(tmp_path):
    mod = _load()
    row = mod.measure("d", [(str(_study(tmp_path)), "s")], "global")
    assert row["mapper"] == "global" and row["defaults"] == 0.9
    assert row["n_random"] == 4 and row["pruned"] == 1 and row["zero"] == 1
    assert row["min"] == 0.0 and row["max"] == 0.6 and row["median"] == pytest.approx(0.3)
    assert row["pruned_reasons"][0].startswith("trial timeout")


def test_rows_are_kept_per_dataset_and_mapper(tmp_path):
    mod = _load()
    base = {"dataset": "d", "n_random": 4, "defaults": 0.9, "min": 0.0, "q25": 0.15, "median": 0.3, "q75": 0.45,
            "max": 0.6, "sd": 0.258, "zero": 1, "command": "c", "date": "2026-12-07"}
    old = {"rows": [dict(base), dict(base, mapper="global", pruned=2),  # the first: an old row, no mapper nor count
                    dict(base, mapper="global", pruned=0, space="search_spaces/g.yaml")]}
    md = tmp_path / "t.md"
    mod.write_md(old, md)
    lines = [x for x in md.read_text().splitlines() if x.startswith("| `d`")]
    assert lines == ["| `d`, global | 4 | 2 | 0.900 | 0.000 (1) | 0.150, 0.300, 0.450 | 0.600 | 0.258 |",
                     "| `d`, global (`g.yaml`) | 4 | 0 | 0.900 | 0.000 (1) | 0.150, 0.300, 0.450 | 0.600 | 0.258 |",
                     "| `d`, incremental | 4 | ? | 0.900 | 0.000 (1) | 0.150, 0.300, 0.450 | 0.600 | 0.258 |"]


@pytest.mark.parametrize("bad", [["--trial-timeout", "soon"], ["--trial-timeout", "-5"], ["--mapper", "glomap"],
                                 ["--space", "no-such.yaml"]])
def test_bad_options_are_one_line_and_exit_2(tmp_path, bad):
    p = subprocess.run([sys.executable, str(SCRIPT), "--data", str(tmp_path), "--dataset", "d",
                        "--studies-dir", str(tmp_path), *bad], capture_output=True, text=True)
    assert p.returncode == 2
    assert bad[0] in p.stderr.strip().splitlines()[-1]
