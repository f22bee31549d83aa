"""Bad input files and folders through the real `tune` CLI: each cause we can name is one line `tune: error: ...`
naming the culprit, exit 2 — never "internal error", a traceback, or a password.

Covered: malformed storage URLs that carry a password; binary (non-UTF-8) files given as configuration, search
space, reference, comparison source, frozen.yaml or imtune.yaml, and YAML's string ``1e5``; journal storages
that are not Optuna journals (binary, text, unknown operations, a device, a folder, a FIFO); studies folders
that cannot be written; `tune viz --out` on a file or in a folder that cannot be written; an unbounded
``--ci-resamples``; a download base URL that is no URL; unknown COLMAP camera models and non-positive image
sizes for `tune data build-gt`; invalid calibrations in budgets.json; non-finite or negative numbers in a
frozen.yaml.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import DATA, ROOT, copy_strecha_subset

SECRET = "Zq7-secret-pw"
BINARY = bytes(range(128, 256)) * 4 + b"\n\xff\xfe\x00"  # no valid UTF-8 sequence


def tune(*args, env: dict | None = None, cwd: Path | str = ROOT, timeout: float = 120, **kw):
    """`python -m tuner ARGS` in a real process (no IMTUNE_DEBUG; extra environment ``env``)."""
    e = dict(os.environ, PYTHONPATH=str(ROOT))
    e.pop("IMTUNE_DEBUG", None)
    e.update(env or {})
    return subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], cwd=cwd, env=e, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL, **kw)


def one_line_error(r, *needles: str) -> str:
    """The single stderr line of a user error (exit 2), which must contain every needle."""
    assert r.returncode == 2, (r.returncode, r.stdout[-1000:], r.stderr[-3000:])
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("tune: error: "), r.stderr[-3000:]
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def data3(tmp_path_factory):
    """3 real Strecha images of fountain-P11 (3 pairs)."""
    return copy_strecha_subset(tmp_path_factory.mktemp("bad-files-data"), ["0003.jpg", "0004.jpg", "0005.jpg"])


# -- 1. a malformed storage URL never shows its password ---------------------------------------------------

@pytest.mark.parametrize("url", [f"postgresql:/user:{SECRET}@127.0.0.1:1/db", f"postgresql//user:{SECRET}@127.0.0.1:1/db",
                                 f"user:{SECRET}@127.0.0.1:1/db", f"postgresql:user:{SECRET}@127.0.0.1:1/db",
                                 f"postgresql:/user:a@{SECRET}@127.0.0.1:1/db"])
def test_malformed_storage_url_masks_the_password(url, tmp_path):
    r = tune("studies", "--storage", url, "--studies-dir", tmp_path / "studies")
    line = one_line_error(r, "malformed storage URL", "127.0.0.1:1/db", "***")
    assert SECRET not in r.stdout + r.stderr, line
    from tuner.storage import mask_url, scrub
    assert SECRET not in mask_url(url) and SECRET not in scrub(f"error in {url}", url)
    assert not (tmp_path / "studies").exists()
