"""Optuna storages for imtune: URL parsing, password masking, SQLite that does not lock up.

Accepted ``--storage`` values:

- ``sqlite:///PATH`` (relative PATH: from the current directory, as SQLAlchemy reads it); the default is
  ``sqlite:///<studies dir>/optuna.db`` (see :func:`default_studies_dir`);
- ``postgresql://user:password@host:port/db`` (psycopg2), ``mysql+pymysql://...`` (any SQLAlchemy
  driver that is installed);
- ``journal:PATH`` (or a bare path ending in ``.log`` / ``.journal`` / ``.jsonl``): Optuna's
  append-only journal file (``JournalStorage`` + ``JournalFileBackend``), for many processes on a
  shared file system without a database server.

SQLite is opened with a 60 s busy timeout and in WAL mode so that several ``tune`` workers and
optuna-dashboard can read and write at the same time without "database is locked" (Optuna issues
820 and 4994, optuna-dashboard 545); opening retries on transient lock / schema-creation races.
RDB storages record a heartbeat per running trial: a worker killed with ``kill -9`` leaves a RUNNING
trial that the next worker marks FAIL after the grace period and re-enqueues once (its parameters
are evaluated again), so no trial is silently lost.

Passwords never leave this module unmasked: :func:`mask_url` is what logs, reports and study
attributes see.
"""
from __future__ import annotations

import os
import re
import sqlite3
import time
import warnings
from pathlib import Path

from pipeline.errors import ImtuneError

SQLITE_TIMEOUT_S = 60.0
JOURNAL_SUFFIXES = (".log", ".journal", ".jsonl")
SQLITE_SUFFIXES = (".db", ".sqlite", ".sqlite3")
DEFAULT_HEARTBEAT_S = 10
EXPECTED = "expected sqlite:///PATH, postgresql://USER:PASS@HOST:PORT/DB, mysql://..., or journal:PATH"


def project_root() -> Path | None:
    """The source checkout this package runs from (has pyproject.toml), or None when installed."""
    root = Path(__file__).resolve().parents[1]
    return root if (root / "pyproject.toml").is_file() else None


def default_studies_dir() -> Path:
    """Where studies live: ``$IMTUNE_STUDIES``, else ``<project root>/studies`` for a source checkout
    (so `tune` finds the same studies from any working directory), else ``./studies``."""
    env = os.environ.get("IMTUNE_STUDIES")
    if env:
        return Path(env).expanduser().resolve()
    root = project_root()
    return (root / "studies") if root is not None else (Path.cwd() / "studies").resolve()


def default_storage_url(studies_dir: Path | str | None = None) -> str:
    """``sqlite:///<studies dir>/optuna.db`` (absolute path)."""
    d = Path(studies_dir) if studies_dir is not None else default_studies_dir()
    return f"sqlite:///{(d / 'optuna.db').resolve()}"


_PW_RE = re.compile(r"(?P<pre>[a-zA-Z][a-zA-Z0-9+.\-]*://[^:/@\s]*:)(?P<pw>[^@\s]*)(?P<post>@)")


def mask_url(url: str | None) -> str:
    """The URL with its password replaced by ``***`` (also for malformed URLs)."""
    if url is None:
        return ""
    return _PW_RE.sub(lambda m: m.group("pre") + "***" + m.group("post"), str(url))


def _password(url: str) -> str | None:
    m = _PW_RE.search(url or "")
    return m.group("pw") if m and m.group("pw") else None


def scrub(text: str, url: str | None) -> str:
    """``text`` with the URL's password (and any URL-embedded password) masked; one line."""
    text = " ".join(str(text).split())
    pw = _password(url or "")
    if pw:
        text = text.replace(pw, "***")
        try:
            from urllib.parse import unquote
            text = text.replace(unquote(pw), "***")
        except Exception:  # noqa: BLE001
            pass
    return mask_url(text)


_DRIVERS = {"postgresql": (("psycopg2", "psycopg2"), ("psycopg", "psycopg"), ("pg8000", "pg8000")),
            "mysql": (("MySQLdb", "mysqldb"), ("pymysql", "pymysql"), ("mysql.connector", "mysqlconnector")),
            "mariadb": (("MySQLdb", "mysqldb"), ("pymysql", "pymysql"))}


def _importable(mod: str) -> bool:
    import importlib.util
    try:
        return importlib.util.find_spec(mod) is not None
    except (ImportError, ValueError):
        return False


def classify(url: str) -> tuple[str, str]:
    """(kind, normalised) where kind is sqlite | rdb | journal. Raises ImtuneError if malformed."""
    if not isinstance(url, str) or not url.strip():
        raise ImtuneError(f"empty storage URL ({EXPECTED})")
    url = url.strip()
    if url.startswith("journal:"):
        path = url[len("journal:"):]
        if path.startswith("//"):
            path = path[2:]
        if not path:
            raise ImtuneError(f"malformed storage URL {url!r}: journal needs a file path ({EXPECTED})")
        return "journal", str(Path(path).expanduser())
    if "://" not in url:
        p = Path(url).expanduser()
        if p.suffix in JOURNAL_SUFFIXES:
            return "journal", str(p)
        if p.suffix in SQLITE_SUFFIXES:
            return "sqlite", f"sqlite:///{p.resolve()}"
        raise ImtuneError(f"malformed storage URL {mask_url(url)!r} ({EXPECTED})")
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError
    try:
        u = make_url(url)
    except (ArgumentError, ValueError) as e:
        raise ImtuneError(f"malformed storage URL {mask_url(url)!r}: {scrub(str(e), url)} ({EXPECTED})") from None
    backend = u.get_backend_name()
    if backend == "sqlite":
        if not u.database or u.database == ":memory:":
            raise ImtuneError(f"storage {mask_url(url)!r}: an SQLite storage needs a file path "
                              "(sqlite:///studies/optuna.db); an in-memory database is not shared between workers")
        return "sqlite", url
    if backend in ("postgresql", "mysql", "mariadb", "oracle", "mssql"):
        if not u.host and backend != "sqlite":
            raise ImtuneError(f"malformed storage URL {mask_url(url)!r}: no host ({EXPECTED})")
        if not u.database:
            raise ImtuneError(f"malformed storage URL {mask_url(url)!r}: no database name ({EXPECTED})")
        if "+" not in u.drivername:  # no driver named: use one that is installed
            for mod, driver in _DRIVERS.get(backend, ()):
                if _importable(mod):
                    u = u.set(drivername=f"{backend}+{driver}")
                    return "rdb", u.render_as_string(hide_password=False)
        return "rdb", url
    raise ImtuneError(f"unsupported storage {mask_url(url)!r} (scheme {u.drivername!r}; {EXPECTED})")


def _sqlite_path(url: str) -> Path:
    from sqlalchemy.engine import make_url
    return Path(make_url(url).database).expanduser()


def _prepare_sqlite(path: Path) -> None:
    """Create the folder; switch the file to WAL (persistent per file) so readers never block the writer."""
    path.parent.mkdir(parents=True, exist_ok=True)
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
        except sqlite3.OperationalError as e:
            if "locked" not in str(e) and "busy" not in str(e):
                raise ImtuneError(f"cannot open SQLite storage {path}: {e}") from None
            time.sleep(0.1 * (attempt + 1))
    # WAL is an optimisation: the busy timeout alone still prevents lock errors


def _sqlite_pragmas(engine) -> None:
    """Per connection: WAL with synchronous=NORMAL (a commit no longer waits for fsync; a killed
    process loses nothing committed, only a power cut could lose the last commits) and the busy timeout
    in SQLite itself as well as in the Python driver."""
    from sqlalchemy import event

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_con, _record):
        cur = dbapi_con.cursor()
        try:
            cur.execute(f"PRAGMA busy_timeout={int(SQLITE_TIMEOUT_S * 1000)}")
            cur.execute("PRAGMA synchronous=NORMAL")
        finally:
            cur.close()

    engine.dispose()  # connections opened while creating the tables reconnect with the pragmas


def _retrying(fn, what: str, url: str, attempts: int = 8):
    from sqlalchemy.exc import DBAPIError, OperationalError, IntegrityError, ProgrammingError
    last = None
    for attempt in range(attempts):
        try:
            return fn()
        except (OperationalError, IntegrityError, ProgrammingError) as e:
            last = e
            msg = str(e).lower()
            transient = ("locked" in msg or "busy" in msg or "already exists" in msg or "duplicate" in msg
                         or "unique" in msg)
            if not transient:
                break
            time.sleep(0.2 * (attempt + 1))
        except DBAPIError as e:
            last = e
            break
    orig = getattr(last, "orig", None) or last
    first = str(orig).strip().splitlines()[0] if str(orig).strip() else type(orig).__name__
    raise ImtuneError(f"cannot {what} storage {mask_url(url)}: {scrub(first, url)}") from None


def open_storage(url: str | None = None, *, heartbeat: int | None = DEFAULT_HEARTBEAT_S,
                 grace_period: int | None = None, retry_stale: bool = True,
                 studies_dir: Path | str | None = None):
    """An Optuna storage object for ``url`` (default: the SQLite file in the studies folder).

    heartbeat: seconds between a running trial's heartbeats on RDB storages (None or 0: off);
    grace_period: seconds without a heartbeat after which a RUNNING trial counts as dead (default
    3 x heartbeat); retry_stale: re-enqueue a dead trial's parameters once.
    Raises ImtuneError (one line, password masked) for a malformed URL, a missing driver or an
    unreachable server."""
    import optuna
    url = url or default_storage_url(studies_dir)
    kind, norm = classify(url)
    if kind == "journal":
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalFileBackend
        p = Path(norm)
        p.parent.mkdir(parents=True, exist_ok=True)
        try:
            return JournalStorage(JournalFileBackend(str(p)))
        except OSError as e:
            raise ImtuneError(f"cannot open journal storage {p}: {e.strerror or e}") from None
    hb = int(heartbeat) if heartbeat else None
    kwargs = {}
    if hb:
        kwargs = dict(heartbeat_interval=hb, grace_period=int(grace_period or 3 * hb))
        if retry_stale:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "experimental" since Optuna 2.8
                kwargs["heartbeat_stale_trial_callback"] = optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=1)
    if kind == "sqlite":
        _prepare_sqlite(_sqlite_path(norm))
        engine_kwargs = {"connect_args": {"timeout": SQLITE_TIMEOUT_S}}
    else:
        engine_kwargs = {"pool_pre_ping": True}
        from sqlalchemy.engine import make_url
        backend = make_url(norm).get_backend_name()
        if backend == "postgresql":
            engine_kwargs["connect_args"] = {"connect_timeout": 10}
        elif backend in ("mysql", "mariadb"):
            engine_kwargs["connect_args"] = {"connect_timeout": 10}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # heartbeat_interval is "experimental"
        try:
            storage = _retrying(lambda: optuna.storages.RDBStorage(norm, engine_kwargs=engine_kwargs, **kwargs),
                                "open", url)
            if kind == "sqlite":
                _sqlite_pragmas(storage.engine)
            return storage
        except (ImportError, ModuleNotFoundError) as e:
            raise ImtuneError(f"storage {mask_url(url)}: the database driver is not installed "
                              f"({scrub(str(e.__cause__ or e), url)}); e.g. `pip install psycopg2-binary` "
                              "for PostgreSQL or `pip install pymysql` with mysql+pymysql://") from None
        except ImtuneError:
            raise
        except Exception as e:  # noqa: BLE001 - a storage that cannot be opened is a one-line error
            raise ImtuneError(f"cannot open storage {mask_url(url)}: {scrub(str(e), url)}") from None


def fail_stale_trials(study) -> list[int]:
    """Fail (and re-enqueue once) the RUNNING trials of dead workers; returns their numbers.

    Optuna's own check (``optuna.storages.fail_stale_trials``) only sees trials that recorded a
    heartbeat; a worker killed between creating a trial and its first heartbeat (while the sampler
    runs) leaves a RUNNING trial without one, which is failed here once it is older than the grace
    period. Storages without heartbeats (journal files) are left alone."""
    import datetime as _dt

    import optuna
    from optuna.trial import TrialState
    before = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
    optuna.storages.fail_stale_trials(study)
    backend = getattr(study._storage, "_backend", study._storage)
    interval = getattr(backend, "heartbeat_interval", None)
    if not interval:
        return []
    grace = getattr(backend, "grace_period", None) or 2 * interval
    try:
        from optuna.storages._rdb import models
        running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
        session = backend.scoped_session()
        try:
            beating = {hb.trial_id for hb in session.query(models.TrialHeartbeatModel).all()}
        finally:
            backend.scoped_session.remove()
        cb = backend.get_heartbeat_stale_trial_callback()
        for t in running:
            start = t.datetime_start.replace(tzinfo=None) if t.datetime_start else None
            if t._trial_id in beating or start is None:
                continue
            # datetime_start is the creating worker's local time (Optuna's datetime.now())
            if (_dt.datetime.now() - start).total_seconds() <= grace:
                continue
            try:
                if backend.set_trial_state_values(t._trial_id, state=TrialState.FAIL):
                    if cb is not None:
                        cb(study, study._storage.get_trial(t._trial_id))
            except optuna.exceptions.UpdateFinishedTrialError:
                pass
    except Exception:  # noqa: BLE001 - best effort beyond Optuna's own check
        pass
    after = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
    return sorted(before - after)


def storage_label(url: str | None, studies_dir: Path | str | None = None) -> str:
    """The masked URL as shown to users (the default expanded)."""
    return mask_url(url or default_storage_url(studies_dir))
