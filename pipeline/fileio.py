"""Atomic text writes for result files (frozen settings, budgets, galleries, reports)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from pipeline.errors import ImtuneError


def atomic_write(path: Path | str, text: str) -> None:
    """Write text atomically: temp name in the same folder, fsync, rename (readers never see a partial
    file; an interrupted write leaves the old file). One-line ImtuneError when the folder is not writable."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise ImtuneError(f"cannot write {path}: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; results are for everyone to read
        os.replace(tmp, path)
    except OSError as e:
        raise ImtuneError(f"cannot write {path}: {e.strerror or e}") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
