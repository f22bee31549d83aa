"""Where studies live and the default storage in it: ``$IMTUNE_STUDIES``, the checkout's ``studies/``,
``sqlite:///<studies dir>/optuna.db``."""
from __future__ import annotations

import os
from pathlib import Path


def project_root() -> Path | None:
    """The source checkout this package runs from (has pyproject.toml), or None when installed."""
    root = Path(__file__).resolve().parents[2]  # tuner/storage/locations.py -> the checkout
    return root if (root / "pyproject.toml").is_file() else None


def default_studies_dir() -> Path:
    """Where studies live: ``$IMTUNE_STUDIES``, else ``<project root>/studies`` for a source checkout
    (so `tune` finds the same studies from any working directory), else ``./studies``."""
    env = os.environ.get("IMTUNE_STUDIES")
    if env:
        return Path(env).expanduser().resolve()
    root = project_root()
    return (root / "studies") if root is not None else (Path.cwd() / "studies").resolve()


STUDIES_DIR_FIX = "give a writable folder with --studies-dir DIR (or the IMTUNE_STUDIES environment variable)"


def check_studies_dir(studies_dir: Path | str | None = None) -> Path:
    """The studies folder (default :func:`default_studies_dir`) if it can be written (or created): commands that
    write there (`tune run`, `tune calibrate`) call this first. One-line ImtuneError naming the folder and
    suggesting --studies-dir otherwise (read-only, a file in the way, full); nothing is created."""
    from pipeline.fileio import check_writable_folder
    d = Path(studies_dir) if studies_dir is not None else default_studies_dir()
    return check_writable_folder(d, "studies folder", STUDIES_DIR_FIX)


def default_storage_url(studies_dir: Path | str | None = None) -> str:
    """``sqlite:///<studies dir>/optuna.db`` (absolute path)."""
    d = Path(studies_dir) if studies_dir is not None else default_studies_dir()
    return f"sqlite:///{(d / 'optuna.db').resolve()}"
