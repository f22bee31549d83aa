"""Atomic writes: text for result files (frozen settings, budgets, galleries, reports), h5 for array files
(cache entries, built ground truth)."""
from __future__ import annotations

import errno as _errno
import hashlib
import io
import os
import shutil
import tempfile
from pathlib import Path

import yaml

from pipeline.errors import ImtuneError


class FileWriteError(ImtuneError):
    """A file could not be written. ``path`` is the file, ``errno`` the OS error number (``errno.ENOSPC`` for a
    full disk, ``EACCES`` / ``EROFS`` for a read-only folder, ``ENOTDIR`` / ``EEXIST`` when a file stands where a
    folder should be; None when unknown), ``reason`` the OS's words."""

    def __init__(self, path: Path | str, err: OSError):
        self.path = Path(path)
        self.errno = err.errno
        self.reason = err.strerror or str(err)
        super().__init__(f"cannot write {self.path}: {self.reason}")

    @property
    def disk_full(self) -> bool:
        return self.errno in (_errno.ENOSPC, _errno.EDQUOT)


def file_kind(mode: int) -> str:
    """What a non-regular file's ``st_mode`` is, for a message: "a folder", "a FIFO", "a socket", "a device", or
    "not a regular file"."""
    import stat
    return ("a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else
            "a socket" if stat.S_ISSOCK(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else
            "not a regular file")


def kind_at(path: Path | str) -> str | None:
    """What is at ``path``, for a message: None (nothing), "a file" (a regular one, or a link to one), "a broken
    link", else :func:`file_kind` of it ("a folder", "a FIFO", ...). Any other OSError (permission, a link loop) is a
    one-line ImtuneError naming ``path``."""
    import os
    import stat
    try:
        os.lstat(path)
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "a broken link" if os.path.islink(path) else None
    except OSError as e:
        raise ImtuneError(f"cannot read {path}: {e.strerror or e}") from None
    return "a file" if stat.S_ISREG(mode) else file_kind(mode)


def read_text(path: Path | str, what: str = "file") -> str:
    """The text of a file the user gave (a configuration, search space, frozen.yaml, imtune.yaml, splits.yaml, ...),
    decoded as UTF-8 (a BOM is dropped). One-line ImtuneError naming ``what`` and the file when it is not a regular
    file (a folder, a device, a FIFO: never read, so /dev/zero cannot fill the memory), cannot be read, or is not
    UTF-8 text (a binary file, a file in another encoding): the one reader of every such file."""
    import stat
    path = Path(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file"
            raise ImtuneError(f"{what} {path} is {kind}; give a text file")
        data = path.read_bytes()
    except OSError as e:
        raise ImtuneError(f"cannot read {what} {path}: {e.strerror or e}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ImtuneError(f"{what} {path} is not a UTF-8 text file (byte 0x{data[e.start]:02x} at offset {e.start} "
                          "cannot be decoded); is it the right file? save it as UTF-8 text") from None


class _UniqueKeysLoader(yaml.SafeLoader):
    """PyYAML's SafeLoader (no arbitrary objects), refusing a key given twice in one mapping; ``where`` names the
    file in the error."""

    where = "YAML"

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *anchor` merges are no duplicates
                continue
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            try:
                if key in seen:
                    raise ImtuneError(f"{self.where}: key {key!r} is given twice (lines {seen[key]} and {line}); "
                                      "YAML would keep only the last: write it once")
                seen[key] = line
            except TypeError:  # an unhashable key: SafeLoader's own error follows
                continue
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str, where: str):
    """``yaml.safe_load`` of ``text``, refusing a key given twice in one mapping (PyYAML keeps the last without a
    word: ``geometry: {threshold: 2}`` then ``geometry: {max_iters: 100}`` lost the threshold): a one-line
    ImtuneError naming ``where``, the key and both lines. YAML errors propagate as ``yaml.YAMLError``."""
    loader = _UniqueKeysLoader(text)  # what yaml.safe_load does, with the SafeLoader subclass above
    loader.where = where
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def load_json(text: str, where: str):
    """``json.loads`` of ``text``, refusing a key given twice in one object (json keeps the last without a word):
    a one-line ImtuneError naming ``where`` and the key. Invalid JSON propagates as ``ValueError``."""
    import json

    def pairs(items):
        out = {}
        for k, v in items:
            if k in out:
                raise ImtuneError(f"{where}: key {k!r} is given twice in one object; JSON would keep only the last: "
                                  "write it once")
            out[k] = v
        return out
    return json.loads(text, object_pairs_hook=pairs)


#: the errnos :func:`folder_error` tells apart (full, not writable, a file in the way)
FOLDER_ERRNOS = frozenset({_errno.ENOSPC, _errno.EDQUOT, _errno.EACCES, _errno.EPERM, _errno.EROFS, _errno.ENOTDIR,
                           _errno.EEXIST})


def folder_error(path: Path | str, err: OSError, what: str, fix: str) -> ImtuneError:
    """One line for a folder that cannot be created or written: ``<what> <path> is not writable / is full / is not
    a folder (a file is in the way)...: <fix>``. A read-only file system (EROFS), a folder without permission
    (EACCES, EPERM) and a file in the way (ENOTDIR, EEXIST) are told apart by the errno, not by the OS's words."""
    path = Path(path)
    reason = err.strerror or str(err)
    if err.errno in (_errno.ENOSPC, _errno.EDQUOT):
        return ImtuneError(f"{what} {path} is full ({reason}): free some space there, or {fix}")
    if err.errno in (_errno.EACCES, _errno.EPERM, _errno.EROFS):
        return ImtuneError(f"{what} {path} is not writable ({reason}): {fix}")
    if err.errno in (_errno.ENOTDIR, _errno.EEXIST):
        return ImtuneError(f"{what} {path} is not a folder (a file is in the way: {reason}): {fix}")
    return ImtuneError(f"{what} {path} cannot be written ({reason}): {fix}")


def check_writable_folder(path: Path | str, what: str, fix: str) -> Path:
    """Fail fast, creating nothing: ``path`` is a folder this process can write, or can be created as one. The
    nearest existing folder on its way (``path`` itself, else its deepest existing ancestor) is probed by making
    and removing a temporary folder in it, so a read-only file system or folder, a file in the way or a full disk
    is a one-line ImtuneError (:func:`folder_error`) before any work, whoever runs (root writes through
    permission bits, not through a read-only mount; a few bytes are written in the temporary folder, as a new
    folder alone may take no block on a full tmpfs). Returns ``path``."""
    path = Path(path)
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    if not p.is_dir():
        raise folder_error(path, NotADirectoryError(_errno.ENOTDIR, f"{p} is a file"), what, fix)
    probe = None
    try:
        probe = tempfile.mkdtemp(prefix=".imtune-write-test-", dir=p)
        with open(os.path.join(probe, "probe"), "wb") as fh:
            fh.write(b"imtune")
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as e:
        raise folder_error(path, e, what, fix) from None
    finally:
        if probe is not None:
            shutil.rmtree(probe, ignore_errors=True)
    return path


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


def arrays_checksum(arrays: dict) -> str:
    """SHA-1 hex digest of named arrays: name, dtype, shape and bytes of each, in sorted name order."""
    import numpy as np
    h = hashlib.sha1()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def atomic_write_h5(path: Path | str, arrays: dict, attrs: dict | None = None) -> Path:
    """Write named arrays (``"a/b"`` names make groups) and root attributes to an h5 file, atomically.

    The file is built in memory, written to a temp name in the destination folder (``.<name>.<random>.tmp``),
    fsync'ed and renamed over ``path``: readers see the old file or the complete new one, never a partial one,
    and concurrent writers of the same path leave one complete file. Raises :class:`FileWriteError` (an
    ImtuneError carrying ``errno``) when the folder cannot be created or written (read-only, a file in the way,
    disk full); the temp file is removed in every failure case. Returns ``path``.
    """
    import h5py
    import numpy as np
    path = Path(path)
    buf = io.BytesIO()  # built in memory so every disk error comes from os calls below, with its errno
    with h5py.File(buf, "w") as f:
        for k, v in arrays.items():
            f.create_dataset(k, data=np.asarray(v))
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
    data = buf.getbuffer()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise FileWriteError(path, e) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; a shared cache is for every user to read
        os.replace(tmp, path)
    except OSError as e:
        raise FileWriteError(path, e) from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
