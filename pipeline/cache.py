"""Content-addressed h5 cache for features, k-NN tables and matches.

Every entry is keyed by a hash of (input file identity, stage config, stage code version); input files
are identified by the SHA-1 of their bytes, so a copied data folder hits the same entries and an edited
image misses. Entries are written atomically (temp name in the same folder, fsync, rename) and carry a
SHA-1 of their arrays; an entry that cannot be opened or whose checksum disagrees is deleted and
recomputed, never trusted. Arrays only: no pickle.

Location: ``$IMTUNE_CACHE`` or ``~/.cache/imtune``.
"""
from __future__ import annotations

import hashlib
import os
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from pipeline.config import config_hash

_FILE_DIGESTS: dict[tuple, str] = {}


def default_cache_dir() -> Path:
    return Path(os.environ.get("IMTUNE_CACHE") or Path.home() / ".cache" / "imtune")


def file_digest(path: Path) -> str:
    """SHA-1 of a file's bytes, memoised on (path, size, mtime)."""
    st = os.stat(path)
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _FILE_DIGESTS:
        h = hashlib.sha1()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        _FILE_DIGESTS[key] = h.hexdigest()
    return _FILE_DIGESTS[key]


def make_key(*parts) -> str:
    """Cache key from any JSON-able parts (configs, digests, versions)."""
    return config_hash(list(parts), n=32)


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha1()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


class H5Cache:
    """One h5 file per entry under ``root/<stage>/<key[:2]>/<key>.h5``, with an in-process LRU of the
    most recent entries (so tuning trials read each k-NN table from memory after the first)."""

    def __init__(self, root: Path | str | None = None, memory_items: int = 4096):
        self.root = Path(root) if root is not None else default_cache_dir()
        self._mem: OrderedDict[tuple[str, str], dict[str, np.ndarray]] = OrderedDict()
        self._mem_items = memory_items
        self._lock = threading.Lock()
        self.stats = {"hit": 0, "miss": 0, "corrupt": 0}

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key[:2] / f"{key}.h5"

    def get(self, stage: str, key: str) -> dict[str, np.ndarray] | None:
        with self._lock:
            if (stage, key) in self._mem:
                self._mem.move_to_end((stage, key))
                self.stats["hit"] += 1
                return self._mem[(stage, key)]
        p = self.path(stage, key)
        if not p.exists():
            self.stats["miss"] += 1
            return None
        try:
            with h5py.File(p, "r") as f:
                arrays = {k: f[k][()] for k in f.keys()}
                expected = f.attrs.get("sha1")
            if expected is None or _checksum(arrays) != (expected.decode() if isinstance(expected, bytes) else expected):
                raise OSError("checksum mismatch")
        except Exception:  # unreadable, truncated or tampered: drop it and recompute
            self.stats["corrupt"] += 1
            try:
                p.unlink()
            except OSError:
                pass
            return None
        self.stats["hit"] += 1
        self._remember(stage, key, arrays)
        return arrays

    def put(self, stage: str, key: str, arrays: dict[str, np.ndarray]) -> None:
        p = self.path(stage, key)
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{key}.", suffix=".tmp", dir=p.parent)
        os.close(fd)
        try:
            with h5py.File(tmp, "w") as f:
                for k, v in arrays.items():
                    f.create_dataset(k, data=np.asarray(v))
                f.attrs["sha1"] = _checksum({k: np.asarray(v) for k, v in arrays.items()})
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, p)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        self._remember(stage, key, {k: np.asarray(v) for k, v in arrays.items()})

    def get_or_compute(self, stage: str, key: str, compute: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        got = self.get(stage, key)
        if got is None:
            got = compute()
            self.put(stage, key, got)
        return got

    def _remember(self, stage, key, arrays):
        with self._lock:
            self._mem[(stage, key)] = arrays
            self._mem.move_to_end((stage, key))
            while len(self._mem) > self._mem_items:
                self._mem.popitem(last=False)
