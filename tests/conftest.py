"""Shared fixtures: where ../shared/data is, an isolated cache folder, offline weights."""
from __future__ import annotations

import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("IMTUNE_SHARED", ROOT.parent / "shared"))
DATA = SHARED / "data"

os.environ.setdefault("TORCH_HOME", str((SHARED / "weights" / "torch").resolve()))

# Every `tune` and StereoTask a test starts evaluates its pairs in-process (--jobs 1) unless the test names --jobs:
# the README's test command already runs one test file per CPU, and a pool of spawned pair workers per command on
# a few tiny pairs doubled each command's CPU seconds (a 4-trial study: 21 s with --jobs 1, 37 s with the default
# 2, the same wall time alone) and made timed tests share cores with another file's pool. The pool has its own
# tests, which pass --jobs (test_parallel_pairs, test_pool_stop, the kill and signal tests); tests of the default
# itself delete the variable.
os.environ["IMTUNE_JOBS"] = "1"

# A shell with PYTHONDONTWRITEBYTECODE=1 (this machine's, and CI's like it) never writes the .pyc of an editable
# install: every `tune` process a test starts, and every pair worker it spawns, compiled tuner/ and pipeline/ from
# source again (0.35 of the 0.8 CPU-s of a one-line error, 0.5 CPU-s of a 2-trial study; over a thousand such
# processes in a run). The processes started here may cache their bytecode in __pycache__ (git-ignored), as
# Python does by default; what they run is unchanged.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

# A test run started in the background by a non-interactive shell (`bash .ci/run &`, nohup, a CI runner's job)
# inherits SIGINT ignored, and so would every `tune` the tests start and this process itself: the Ctrl-C tests
# (SIGINT -> exit 130) would see their signal ignored, as a background `tune` rightly ignores it. A terminal's
# Ctrl-C reaches a foreground process with the default disposition: give the tests that one (a handled signal is
# reset to the default in a child at exec, so every `tune` started here installs Python's KeyboardInterrupt).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


# The test files that take longest in one process (seconds, from `--durations=0` of a CI run on 2 cores), started
# first: pytest-xdist hands whole files (--dist loadfile) to its processes in collection order (pyproject:
# --no-loadscope-reorder; its own reorder, by number of tests, put these few-test, minute-long files last, and
# the run ended on one of them while the other process idled). Files not listed keep their order after these.
SLOWEST_FILES = ("test_tuner_study.py", "test_workers.py", "test_faults_processes.py", "test_findings.py",
                 "test_export.py", "test_pareto.py", "test_bad_input_files.py",
                 "test_faults_storage.py", "test_intervals_real.py", "test_gt_build.py", "test_warm_start.py",
                 "test_ground_truth_origin.py", "test_evaluate_config.py", "test_cli_evaluate.py",
                 "test_credentials.py", "test_viz_multiview.py", "test_tuner_postgres.py",
                 "test_dashboard_browser.py", "test_parallel_pairs.py", "test_tuner_multiview.py",
                 "test_reconstruction.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(SLOWEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file's tests keep their order


def require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data not found at {path} (expected ../shared beside the project)")
    return path


@pytest.fixture
def strecha() -> Path:
    return require(DATA / "strecha")


@pytest.fixture
def scannet() -> Path:
    return require(DATA / "scannet_sample")


@pytest.fixture
def sacre_coeur() -> Path:
    return require(DATA / "sacre_coeur")


@pytest.fixture
def cache_dir(tmp_path, monkeypatch) -> Path:
    d = tmp_path / "cache"
    monkeypatch.setenv("IMTUNE_CACHE", str(d))
    return d


def copy_strecha_subset(dst_root: Path, images: list[str], scene: str = "fountain-P11") -> Path:
    """Copy some images (and their camera files) of a real Strecha scene into ``dst_root/scene``;
    skips the test when ../shared/data is absent. Returns ``dst_root``."""
    src = DATA / "strecha" / scene
    if not src.exists():
        pytest.skip(f"real data not found at {src} (expected ../shared beside the project)")
    dst = dst_root / scene
    (dst / "images").mkdir(parents=True)
    (dst / "gt_dense_cameras").mkdir()
    for n in images:
        shutil.copy(src / "images" / n, dst / "images" / n)
        shutil.copy(src / "gt_dense_cameras" / f"{n}.camera", dst / "gt_dense_cameras" / f"{n}.camera")
    return dst_root


SQLITE_SIDE_FILES = ("-wal", "-shm", "-journal")


def copy_studies(src: Path, dst: Path) -> Path:
    """Copy a studies folder whose SQLite storages (``*.db``) other processes may have open: every other file with
    shutil, each database through SQLite's backup API (a consistent snapshot taken under SQLite's own locks, no
    -wal / -shm beside it). shutil.copytree opens and closes optuna.db, -wal and -shm in this process, and a close()
    drops every POSIX lock the process holds on the file, including those of this process's open SQLite connections
    (an Optuna storage a test left to the garbage collector): a `tune` run afterwards then deleted the WAL and -shm
    under those connections, which read a stale database (20 trials of 220 in a stress run) or, in CI once,
    'database disk image is malformed'; the copied -wal / -shm were also taken at other moments than the .db."""
    import sqlite3
    dbs = {p.name for p in Path(src).glob("*.db")}

    def skip(folder, names):
        if Path(folder) != Path(src):
            return []
        return [n for n in names if n in dbs or any(n == d + s for d in dbs for s in SQLITE_SIDE_FILES)]

    shutil.copytree(src, dst, ignore=skip)
    for name in sorted(dbs):
        a = sqlite3.connect(str(Path(src) / name), timeout=60)
        b = sqlite3.connect(str(Path(dst) / name))
        try:
            a.backup(b)
        finally:
            b.close()
            a.close()
    return Path(dst)


def look_at(C, target=(0.0, 0.0, 0.0)):
    """World-to-camera (R, t) of a camera at centre C looking at ``target`` (y up)."""
    target = np.asarray(target, dtype=float)
    z = (target - C) / np.linalg.norm(target - C)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ C


@pytest.fixture(scope="session")
def docs_build(tmp_path_factory):
    """The documentation site built once per test process (`mkdocs build --strict`, the venv's mkdocs): the
    finished build (its stderr holds any warning) and the site folder. The docs tests share it."""
    import sys

    from tests.test_docs_build import MKDOCS, build
    if not MKDOCS.exists():
        pytest.skip(f"no mkdocs beside {sys.executable}: bash .ci/install.sh --docs (or --test)")
    out = tmp_path_factory.mktemp("site") / "site"
    return build(ROOT, out), out
