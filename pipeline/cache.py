"""Content-addressed h5 cache for features, k-NN tables and matches.

Every entry is keyed by a hash of (input file identity, stage config, stage code version); input files
are identified by the SHA-1 of their bytes, so a copied data folder hits the same entries and an edited
image misses. Arrays only: no pickle.

An entry is bound to its key: besides its arrays it stores its format, stage name, key, the JSON the key was
hashed from (``make_key``'s parts: input digests, stage config, code version; verified to hash to the key) and a
SHA-1 over all of them. On read, an entry that cannot be opened
(truncated, overwritten bytes, zero length, not an h5 file), whose checksum disagrees, or that holds another
key or stage (e.g. two valid entries swapped on disk) is reported in one warning line naming the file, deleted
and recomputed, never trusted. Entries of the old format (no key inside) are stale: recomputed, with one
warning per process. Entries are written with :func:`pipeline.fileio.atomic_write_h5` (temp name in the same
folder, fsync, rename), so concurrent processes on one cache folder (or machines on a shared file system)
only ever see complete entries.

A cache folder that cannot be used (a file in its place, read-only, full disk) is a one-line
:class:`~pipeline.errors.ImtuneError` naming the folder and what to do, never an OSError traceback.

Location: ``$IMTUNE_CACHE`` or ``~/.cache/imtune``.
"""
from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.config import config_hash
from pipeline.errors import ImtuneError
from pipeline.fileio import (
    FOLDER_ERRNOS,
    FileWriteError,
    arrays_checksum,
    atomic_write_h5,
    check_writable_folder,
    folder_error,
)

#: what to do about an unusable cache folder
CACHE_FIX = "give a usable folder with --cache DIR or the IMTUNE_CACHE environment variable"

log = logging.getLogger(__name__)

#: format tag stored in every entry; entries without it (or with another) are stale and recomputed
FORMAT = "imtune-cache-2"
_WARNED_STALE: set[str] = set()  # cache roots already warned about old-format entries (once per process)
_KEY_SOURCES: OrderedDict[str, str] = OrderedDict()  # key -> the JSON make_key hashed (recent keys of this process)
_KEY_SOURCES_MAX = 1 << 16
_KEY_LOCK = threading.Lock()
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
    """Cache key from any JSON-able parts (configs, digests, versions). The parts are remembered (recent keys of
    this process), so :meth:`H5Cache.put` stores them inside the entry and a reader can check they hash to it."""
    key = config_hash(list(parts), n=32)
    source = json.dumps(list(parts), sort_keys=True, default=str)  # exactly what config_hash hashed
    with _KEY_LOCK:
        _KEY_SOURCES[key] = source
        _KEY_SOURCES.move_to_end(key)
        while len(_KEY_SOURCES) > _KEY_SOURCES_MAX:
            _KEY_SOURCES.popitem(last=False)
    return key


def _source_hash(source: str) -> str:
    return hashlib.sha1(source.encode()).hexdigest()[:32]


_checksum = arrays_checksum  # kept for pipeline.data.ground_truth


def _entry_checksum(stage: str, key: str, meta: str, arrays: dict[str, np.ndarray], source: str = "") -> str:
    """SHA-1 binding the arrays to the entry's format, stage, key, key source and config."""
    h = hashlib.sha1()
    for part in (FORMAT, stage, key, source, meta, arrays_checksum(arrays)):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()


def _attr(f, name: str) -> str | None:
    v = f.attrs.get(name)
    return v.decode() if isinstance(v, bytes) else (None if v is None else str(v))


class _Invalid(Exception):
    """An entry that must not be trusted; ``str`` is the reason."""


class _NotAFile(Exception):
    """Something other than a file or folder at an entry's name (a FIFO, a device); ``str`` says which."""


class _Stale(_Invalid):
    """An entry of the old format (no key inside)."""


class H5Cache:
    """One h5 file per entry under ``root/<stage>/<key[:2]>/<key>.h5``, with an in-process LRU of the
    most recent entries (so tuning trials read each k-NN table from memory after the first).

    ``stats`` counts ``hit``, ``miss`` and ``corrupt`` (entries found invalid or stale and dropped)."""

    def __init__(self, root: Path | str | None = None, memory_items: int = 4096):
        self.root = Path(root) if root is not None else default_cache_dir()
        self._mem: OrderedDict[tuple[str, str], dict[str, np.ndarray]] = OrderedDict()
        self._mem_items = memory_items
        self._lock = threading.Lock()
        self.stats = {"hit": 0, "miss": 0, "corrupt": 0}

    def path(self, stage: str, key: str) -> Path:
        return self.root / stage / key[:2] / f"{key}.h5"

    # -- folder faults -> one line naming the folder and what to do

    def _folder_error(self, err: OSError | FileWriteError, entry: Path) -> ImtuneError:
        """One line for a cache folder that cannot be written (:func:`pipeline.fileio.folder_error`); an errno it
        does not tell apart names the entry that failed."""
        code = errno.ENOTDIR if self.root.is_file() else err.errno
        if code in (errno.ENOTDIR, errno.EEXIST) and not self.root.is_file():  # a file inside the cache, not the cache
            blocker = next((q for q in entry.parents if q != self.root and self.root in q.parents
                            and q.exists() and not q.is_dir()), None)
            if blocker is not None:
                return ImtuneError(f"cache folder {self.root}: {blocker} is a file where a folder of the cache should "
                                   f"be: move it away (the entries it held are recomputed), or {CACHE_FIX}")
        # FileWriteError.reason, or urllib's URLError.reason (an OSError), else the OS's words
        reason = getattr(err, "reason", None) or (err.strerror if isinstance(err, OSError) else None) or str(err)
        if code not in FOLDER_ERRNOS:
            reason = f"{entry}: {reason}"
        return folder_error(self.root, OSError(code, reason), "cache folder", CACHE_FIX)

    def _check_root(self) -> None:
        if self.root.exists() and not self.root.is_dir():
            raise folder_error(self.root, NotADirectoryError(errno.ENOTDIR, f"{self.root} is a file"), "cache folder",
                               CACHE_FIX)

    def check_writable(self) -> None:
        """Create the cache folder if needed and check it can be written
        (:func:`pipeline.fileio.check_writable_folder`): a one-line ImtuneError naming the folder when it cannot
        (a file where it or a parent should be, no permission, a read-only or full disk). For commands that would
        otherwise find out only at their first entry, after the work before it (`tune findings` checks it before
        any study)."""
        blocker = next((p for p in [self.root, *self.root.parents] if p.exists() and not p.is_dir()), None)
        if blocker is not None:
            raise ImtuneError(f"cannot create the cache folder {self.root}: {blocker} is a file, not a folder; "
                              f"{CACHE_FIX}")
        check_writable_folder(self.root, "cache folder", CACHE_FIX)
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise self._folder_error(e, self.root) from None

    # -- reading

    def _read(self, p: Path, stage: str, key: str, ident: list) -> dict[str, np.ndarray]:
        """Arrays of the entry at ``p`` (its (st_dev, st_ino) appended to ``ident``); FileNotFoundError when
        absent; _Invalid when it must not be trusted; other OSErrors (folder unreadable) propagate."""
        import io
        import stat

        import h5py
        # O_NONBLOCK: a FIFO at the entry's name would block this open until a writer came (a hang, unsaid)
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK)
        with os.fdopen(fd, "rb") as fh:  # whole file in memory: one snapshot, no HDF5 file locking on shared folders
            st = os.fstat(fd)
            if stat.S_ISDIR(st.st_mode):
                raise IsADirectoryError(errno.EISDIR, "Is a directory", str(p))
            if not stat.S_ISREG(st.st_mode):
                from pipeline.fileio import file_kind
                raise _NotAFile(file_kind(st.st_mode))
            ident.append((st.st_dev, st.st_ino))
            data = fh.read()
        if not data:
            raise _Invalid("zero length")
        try:
            with h5py.File(io.BytesIO(data), "r") as f:
                fmt, got_stage, got_key = _attr(f, "format"), _attr(f, "stage"), _attr(f, "key")
                meta, expected = _attr(f, "config") or "", _attr(f, "sha1")
                source = _attr(f, "key_source") or ""
                if fmt is None and got_key is None:
                    raise _Stale("old format without its key")
                arrays = {k: f[k][()] for k in f.keys()}
        except _Invalid:
            raise
        except Exception as e:  # h5py/HDF5 raise OSError, KeyError, ValueError... on damaged bytes
            raise _Invalid(f"unreadable: {' '.join(str(e).split())[:100] or type(e).__name__}") from None
        if fmt != FORMAT:
            raise _Stale(f"format {fmt!r}, expected {FORMAT!r}")
        if got_stage != stage or got_key != key:
            raise _Invalid(f"holds the entry of {got_stage}/{got_key}, not this key")
        if expected is None or _entry_checksum(stage, key, meta, arrays, source) != expected:
            raise _Invalid("checksum mismatch")
        if source and _source_hash(source) != key:
            raise _Invalid("its recorded key source does not hash to its key")
        return arrays

    def _drop(self, p: Path, ident: tuple[int, int] | None, stage: str, why: _Invalid) -> None:
        self.stats["corrupt"] += 1
        if isinstance(why, _Stale):
            if str(self.root) not in _WARNED_STALE:
                _WARNED_STALE.add(str(self.root))
                log.warning("warning: old-format cache entries under %s are stale and recomputed (first: %s)",
                            self.root, p)
        else:
            log.warning("warning: cache entry %s (%s) is not valid (%s): recomputing it", p, stage, why)
        try:  # only the file we read: a concurrent writer may have renamed a good entry over it since
            st = os.stat(p)
            if ident is None or (st.st_dev, st.st_ino) == ident:
                p.unlink()
        except OSError:
            pass

    def get(self, stage: str, key: str) -> dict[str, np.ndarray] | None:
        """The entry's arrays, or None when absent or not valid (then dropped, with a warning)."""
        with self._lock:
            if (stage, key) in self._mem:
                self._mem.move_to_end((stage, key))
                self.stats["hit"] += 1
                return self._mem[(stage, key)]
        self._check_root()
        p = self.path(stage, key)
        ident: list = []
        try:
            arrays = self._read(p, stage, key, ident)
        except FileNotFoundError:
            self.stats["miss"] += 1
            return None
        except _Invalid as why:
            self._drop(p, ident[0] if ident else None, stage, why)
            return None
        except _NotAFile as kind:
            raise ImtuneError(f"cache entry {p} ({stage}) is {kind}, not a file: move it away (the entry is "
                              "recomputed), or give another cache folder with --cache DIR or the IMTUNE_CACHE "
                              "environment variable") from None
        except IsADirectoryError:  # an empty folder holds nothing: removed; one with files is not ours to delete
            try:
                p.rmdir()
            except FileNotFoundError:
                pass
            except OSError:
                raise ImtuneError(f"cache entry {p} ({stage}) is a folder with files in it, not a file: move it "
                                  "away (the entry is recomputed), or give another cache folder with --cache DIR or "
                                  "the IMTUNE_CACHE environment variable") from None
            self.stats["corrupt"] += 1
            log.warning("warning: cache entry %s (%s) is not valid (a folder, not a file): recomputing it", p, stage)
            return None
        except OSError as e:
            if e.errno == errno.ENOTDIR:  # a file where a sub-folder of the cache should be
                raise self._folder_error(e, p) from None
            raise ImtuneError(f"cache folder {self.root}: cannot read {p} ({e.strerror or e}): give a readable "
                              "folder with --cache DIR or the IMTUNE_CACHE environment variable") from None
        self.stats["hit"] += 1
        self._remember(stage, key, arrays)
        return arrays

    # -- writing

    def put(self, stage: str, key: str, arrays: dict[str, np.ndarray], config=None) -> None:
        """Store ``arrays`` as the entry (stage, key), atomically. The parts ``key`` was made from (when made by
        :func:`make_key` in this process) and ``config`` (any JSON-able value, for inspection) are stored inside
        the entry, covered by its checksum."""
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        meta = "" if config is None else json.dumps(config, sort_keys=True, default=str)
        with _KEY_LOCK:
            source = _KEY_SOURCES.get(key, "")
        attrs = {"format": FORMAT, "stage": stage, "key": key, "key_source": source, "config": meta,
                 "sha1": _entry_checksum(stage, key, meta, arrays, source)}
        self._check_root()
        p = self.path(stage, key)
        try:
            atomic_write_h5(p, arrays, attrs)
        except FileWriteError as e:
            raise self._folder_error(e, p) from None
        self._remember(stage, key, arrays)

    def get_or_compute(self, stage: str, key: str, compute: Callable[[], dict[str, np.ndarray]],
                       config=None) -> dict[str, np.ndarray]:
        got = self.get(stage, key)
        if got is None:
            got = compute()
            self.put(stage, key, got, config=config)
        return got

    def _remember(self, stage, key, arrays):
        with self._lock:
            self._mem[(stage, key)] = arrays
            self._mem.move_to_end((stage, key))
            while len(self._mem) > self._mem_items:
                self._mem.popitem(last=False)
