"""SQLite that does not lock up: WAL and a busy timeout, another program's database refused, what to do about a damaged
or full file."""
from __future__ import annotations

import sqlite3
import time
from pathlib import Path

from pipeline.errors import ImtuneError

SQLITE_TIMEOUT_S = 60.0


def _foreign_sqlite(path: Path) -> list[str]:
    """The tables of the SQLite file ``path`` when it is another program's database (tables, not one of them
    Optuna's), else [] (no file, empty, an Optuna storage -- maybe being created by another worker this moment --,
    or no SQLite database: said elsewhere)."""
    try:
        if not path.is_file() or path.stat().st_size == 0:
            return []
        # immutable: no -wal / -shm file is made beside another program's database (a worker creating an Optuna
        # storage this moment shows some of its tables, or none: never "foreign")
        con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1", uri=True, timeout=SQLITE_TIMEOUT_S)
        try:
            tables = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        finally:
            con.close()
    except (OSError, sqlite3.Error):
        return []
    optuna_tables = {"version_info", "alembic_version", "studies", "study_directions", "trials"}
    return sorted(tables) if tables and not optuna_tables & set(tables) else []


def _prepare_sqlite(path: Path, must_exist: bool = False) -> None:
    """Create the folder; switch the file to WAL (persistent per file) so readers never block the writer.

    must_exist: the file must already be there (read-only commands); nothing is created, and the WAL
    switch is best effort (a reader of a read-only file still reads). Another program's SQLite database (a COLMAP
    database.db given by mistake) is refused before anything is written to it: Optuna added its tables to it."""
    if must_exist:
        if not path.is_file():
            what = "a folder, not a file" if path.is_dir() else "no such file"
            raise ImtuneError(f"no SQLite storage at {path.resolve()} ({what}); pass the --storage (or --studies-dir) the "
                              "studies were run with, or run `tune` first")
        if path.stat().st_size == 0:  # an empty file: nothing to switch to WAL, and it is left empty
            return
    foreign = _foreign_sqlite(path)
    if foreign:
        shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
        raise ImtuneError(f"storage {path} is an SQLite database of another program (tables {shown}), not an Optuna "
                          "storage; it is left as it is: pass another --storage (a new file name creates one)")
    else:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ImtuneError(f"cannot create the folder of the SQLite storage {path}: {e.strerror or e}") from None
    for attempt in range(20):
        try:
            con = sqlite3.connect(str(path), timeout=SQLITE_TIMEOUT_S)
            try:
                mode = con.execute("PRAGMA journal_mode").fetchone()[0]
                if str(mode).lower() != "wal":
                    con.execute("PRAGMA journal_mode=WAL")
            finally:
                con.close()
            return
        except sqlite3.DatabaseError as e:
            if "locked" not in str(e) and "busy" not in str(e):
                if must_exist and "readonly" in str(e):
                    return
                hint = _sqlite_hint(str(e))
                raise ImtuneError(f"cannot open SQLite storage {path}: {e}{hint}") from None
            time.sleep(0.1 * (attempt + 1))


    # WAL is an optimisation: the busy timeout alone still prevents lock errors


#: what to do about an SQLite file that is damaged (cut short, overwritten): rerunning on it cannot help
SQLITE_DAMAGED = ("the file is damaged (cut short or overwritten?): restore it from a backup, or pass another "
                  "--storage (a new file starts the studies anew)")


def _sqlite_hint(msg: str) -> str:
    m = msg.lower()
    if "malformed" in m:
        return f"; {SQLITE_DAMAGED}"
    if "full" in m or "disk i/o" in m:
        return "; free disk space (or point --storage elsewhere) and rerun"
    if "not a database" in m:
        return "; the file is not an SQLite database: pass another --storage"
    if "readonly" in m or "unable to open" in m:
        return "; check the file's and its folder's permissions"
    return ""


WAL_CHECKPOINT_PAGES = 256  # pages of write-ahead log between automatic checkpoints (SQLite's default: 1000)
WAL_SIZE_LIMIT = 1 << 20  # bytes the log file is truncated to after a checkpoint (SQLite's default: no limit)


def _sqlite_pragmas(engine) -> None:
    """Per connection: WAL with synchronous=NORMAL (a commit no longer waits for fsync; a killed
    process loses nothing committed, only a power cut could lose the last commits) and the busy timeout
    in SQLite itself as well as in the Python driver. The write-ahead log is checkpointed every 256 pages (1 MiB;
    SQLite's default is 1000, 4 MiB) and truncated to 1 MiB after a checkpoint: every trial's heartbeats and claims
    are commits, and on a nearly full disk a log grown to 4 MiB beside a study of a few hundred KiB failed a rerun
    with "database or disk is full" after the space had been freed (tests/test_faults_storage.py)."""
    from sqlalchemy import event

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_con, _record):
        cur = dbapi_con.cursor()
        try:
            cur.execute(f"PRAGMA busy_timeout={int(SQLITE_TIMEOUT_S * 1000)}")
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.execute(f"PRAGMA wal_autocheckpoint={WAL_CHECKPOINT_PAGES}")
            cur.execute(f"PRAGMA journal_size_limit={WAL_SIZE_LIMIT}")
        finally:
            cur.close()

    engine.dispose()  # connections opened while creating the tables reconnect with the pragmas
