"""Shared fixtures: where ../shared/data is, an isolated cache folder, offline weights."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("IMTUNE_SHARED", ROOT.parent / "shared"))
DATA = SHARED / "data"

os.environ.setdefault("TORCH_HOME", str((SHARED / "weights" / "torch").resolve()))


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
