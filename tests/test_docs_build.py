"""The documentation site builds with `mkdocs build --strict` (the venv's mkdocs, as a user runs it): a broken
link, a missing page or anchor, or a failing docstring render is a warning, and a warning fails the build. The
CLI reference page is generated from tuner.cli's parsers during this build (docs_hooks/generated_pages.py)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
MKDOCS = Path(sys.executable).parent / "mkdocs"


def build(project: Path, site: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(project), NO_MKDOCS_2_WARNING="1")
    return subprocess.run([str(MKDOCS), "build", "--strict", "--site-dir", str(site)], cwd=project, env=env,
                          capture_output=True, text=True, timeout=300)


def needs_mkdocs():
    if not MKDOCS.exists():
        pytest.skip(f"no mkdocs beside {sys.executable}: install the lint extra (bash .ci/install.sh --test)")


def test_docs_build_strict(docs_build):
    r, site = docs_build  # the build the other docs tests read too (tests/conftest.py)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "WARNING" not in r.stderr, r.stderr[-3000:]
    cli = (site / "cli" / "index.html").read_text()
    assert "tune data download" in cli and "--num-features" in cli  # generated from the parsers


def test_docs_build_fails_on_a_broken_link(tmp_path):
    # the same build on a copy whose page links to a page that does not exist: it must fail, or the test above
    # proves nothing
    needs_mkdocs()
    copy = tmp_path / "copy"
    copy.mkdir()
    for name in ("mkdocs.yml", "CHANGELOG.md", "CONTRIBUTING.md"):
        shutil.copy(ROOT / name, copy / name)
    for name in ("docs", "docs_hooks", "pipeline", "tuner", "search_spaces", "benchmarks/results"):
        shutil.copytree(ROOT / name, copy / name, ignore=shutil.ignore_patterns("__pycache__"))
    page = copy / "docs" / "budgets.md"
    page.write_text(page.read_text() + "\nSee [the old page](no-such-page.md).\n")
    r = build(copy, tmp_path / "site")
    assert r.returncode != 0
    assert "no-such-page.md" in r.stderr
