"""The commands issue 49 names fit 100 columns when their output goes into a pipe too (a log, a CI job, a reader's
`| less`), not only on a terminal: `tune data scenes` on each shared data folder and `tune --help`."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


@pytest.mark.parametrize("args", [
    ["data", "scenes", "--data", str(DATA / "imc2025")],
    ["data", "scenes", "--data", str(DATA / "imc2023_heritage")],
    ["data", "scenes", "--data", str(DATA / "strecha")],
    ["--help"],
])
def test_output_fits_100_columns_in_a_pipe(args):
    if args[0] == "data" and not Path(args[-1]).is_dir():
        pytest.skip(f"{args[-1]} is absent (the shared data folder beside the checkout)")
    r = subprocess.run([sys.executable, "-m", "tuner", *args], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    long = [line for line in r.stdout.splitlines() if len(line) > 100]
    assert not long, long
