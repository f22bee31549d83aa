"""A storage failing mid-run (full disk, server gone, locked or read-only file) as one line, never a traceback;
interruptions found in an exception chain."""
from __future__ import annotations

import re
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.storage.locations import default_storage_url
from tuner.storage.masking import scrub
from tuner.storage.retry import _UNREACHABLE
from tuner.storage.sqlite import SQLITE_DAMAGED, SQLITE_TIMEOUT_S
from tuner.storage.urls import classify, storage_label

_LOST = _UNREACHABLE + ("server closed the connection", "terminating connection", "connection already closed",
                        "connection to server", "ssl syscall", "the database system is", "connection reset",
                        "broken pipe", "lost connection", "has gone away", "could not receive data",
                        "could not send data", "connection was closed", "connection is closed")


_FULL = ("database or disk is full", "disk i/o error", "no space left", "file too large", "disk quota")


_FULL_RE = re.compile("|".join(map(re.escape, _FULL)), re.I)


def _root_text(exc: BaseException) -> str:
    """The first line of the innermost database error behind ``exc`` (Optuna's StorageInternalError
    only says "invalid data in the commit"; the driver's message says what happened)."""
    chain = _chain(exc)
    dbapi = [e for e in chain if _is_db(e) and getattr(e, "orig", None) is None
             and type(e).__name__ != "StorageInternalError"]
    root = dbapi[0] if dbapi else exc
    text = str(root).strip()
    return text.splitlines()[0] if text else type(root).__name__


def _chain(exc: BaseException | None) -> list[BaseException]:
    """The exception, its causes / contexts, and the DBAPI errors SQLAlchemy wraps (``.orig``)."""
    out, seen = [], set()
    todo = [exc]
    while todo:
        e = todo.pop(0)
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        out.append(e)
        todo.extend([getattr(e, "orig", None), e.__cause__, e.__context__])
    return out


def interrupt_in_chain(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C / SIGTERM (a KeyboardInterrupt) another exception was raised while handling, if any: Optuna's
    ``_run_trial`` masks an interrupt that lands while a trial is recorded with UnboundLocalError('updated_state')."""
    return next((e for e in _chain(exc) if isinstance(e, KeyboardInterrupt)), None)


def storage_fault(exc: BaseException, url: str | None = None, studies_dir: Path | str | None = None) -> str | None:
    """A one-line message for an exception caused by the storage failing mid-run, or None if it is not one.

    Recognised (anywhere in the exception chain, Optuna's own wrappers included): a full disk under
    SQLite ("database or disk is full", Optuna's "invalid data in the commit" wrapper, EFBIG / ENOSPC),
    a lost or refused database connection (psycopg2 / MySQL messages; and Optuna's
    ``UnboundLocalError: ... 'updated_state'``, which is what surfaces when the server went away while a
    trial was being recorded), a locked or read-only SQLite file. Every message names the masked storage,
    says that completed trials are kept and what to do; the text of the underlying error is scrubbed of
    credentials."""
    import errno
    label = storage_label(url, studies_dir)
    try:
        kind = classify(url or default_storage_url(studies_dir))[0]
    except ImtuneError:
        kind = "unknown"
    chain = _chain(exc)
    if interrupt_in_chain(exc) is not None:  # an interruption, reported as one by the CLI
        return None
    keep = "completed trials are kept; rerun the same command to resume"
    for e in chain:
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) and not _is_db(e):
            where = f" writing {e.filename}" if getattr(e, "filename", None) else ""
            return f"out of disk space{where} ({e.strerror}); free space and {keep}"
    # only the database's own errors are read: "connection refused" from elsewhere is no storage fault
    db = [e for e in chain if _is_db(e)]
    texts = [" ".join(str(e).split()).lower() for e in db]
    full = next((m.group(0) for e in db for m in [_FULL_RE.search(str(e))] if m), None)
    if full:
        return (f"the storage {label} cannot be written ({full}: the disk is full or a file-size limit is "
                f"reached); free space (or give --storage a disk with room), then rerun the same command: "
                "completed trials are kept")
    if any("database is locked" in t for t in texts):
        return (f"the storage {label} stayed locked by another process for {SQLITE_TIMEOUT_S:g} s; {keep} "
                "(many machines: use PostgreSQL or journal:PATH)")
    if any("readonly database" in t or "read-only" in t for t in texts):
        return f"the storage {label} is read-only; fix its permissions (or pass another --storage); {keep}"
    if any(k in t for t in texts for k in _LOST):
        return f"lost the connection to the storage {label}; {keep}"
    damaged = next((m for t in texts for m in ("database disk image is malformed", "file is not a database")
                    if m in t), None)
    if damaged and kind == "sqlite":  # "rerun the same command" would meet the same bytes
        return f"the storage {label} cannot be read ({damaged}); {SQLITE_DAMAGED}"
    optuna_storage = any(type(e).__name__ == "StorageInternalError" for e in chain)
    updated_state = any(isinstance(e, UnboundLocalError) and "updated_state" in str(e) for e in chain)
    if updated_state and kind == "rdb":
        return f"lost the connection to the storage {label}; {keep}"
    if optuna_storage or updated_state or db:
        return f"the storage {label} failed ({scrub(_root_text(exc), url)}); {keep}"
    return None


#: storage faults raised in background threads (Optuna's heartbeat thread), kept quiet by the hook below
THREAD_FAULTS: list[str] = []


def quiet_thread_storage_faults(url: str | None = None, studies_dir: Path | str | None = None) -> None:
    """Keep storage faults of background threads off stderr (the CLI calls this once).

    Optuna records a running trial's heartbeat in a thread; when the database goes away that thread dies
    and ``threading.excepthook`` prints its traceback, while the main thread meets the same fault at its
    next storage call and the CLI reports it as one line. Storage faults of other threads are recorded in
    :data:`THREAD_FAULTS` (masked) instead of printed; every other thread exception goes to the previous hook."""
    import threading
    prev = threading.excepthook
    if getattr(prev, "_imtune", False):
        return

    def hook(args):
        exc = args.exc_value
        if exc is not None and not isinstance(exc, (SystemExit, KeyboardInterrupt)):
            try:
                msg = storage_fault(exc, url, studies_dir)
            except Exception:  # noqa: BLE001 - never let the hook itself fail
                msg = None
            if msg:
                THREAD_FAULTS.append(msg)
                return
        prev(args)

    hook._imtune = True
    threading.excepthook = hook


def _is_db(e: BaseException) -> bool:
    mod = type(e).__module__ or ""
    return mod.startswith(("sqlalchemy", "sqlite3", "psycopg", "pymysql", "MySQLdb", "pg8000")) \
        or type(e).__name__ == "StorageInternalError"
