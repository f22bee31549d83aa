"""An Optuna storage object for a ``--storage`` value: journal file, SQLite or a database server, with heartbeats."""
from __future__ import annotations

import warnings
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.storage.faults import _root_text
from tuner.storage.journal import _check_journal_path, _first_bad_journal_line, _journal_fault
from tuner.storage.locations import default_storage_url
from tuner.storage.masking import mask_url, scrub
from tuner.storage.retry import _retrying
from tuner.storage.sqlite import SQLITE_TIMEOUT_S, _prepare_sqlite, _sqlite_pragmas
from tuner.storage.urls import _sqlite_path, classify

DEFAULT_HEARTBEAT_S = 10


def open_storage(url: str | None = None, *, heartbeat: int | None = DEFAULT_HEARTBEAT_S,
                 grace_period: int | None = None, retry_stale: bool = True,
                 studies_dir: Path | str | None = None, must_exist: bool = False):
    """An Optuna storage object for ``url`` (default: the SQLite file in the studies folder).

    heartbeat: seconds between a running trial's heartbeats on RDB storages (None or 0: off);
    grace_period: seconds without a heartbeat after which a RUNNING trial counts as dead (default
    3 x heartbeat); retry_stale: re-enqueue a dead trial's parameters once; must_exist: for commands
    that only read (``tune studies``, ``table``, ``results``, ``plot``, ``dashboard``): never create a
    storage — a missing SQLite or journal file, or a database without Optuna's tables, is an error.
    Raises ImtuneError (one line, password masked) for a malformed URL, a missing driver or an
    unreachable server."""
    import optuna
    url = url or default_storage_url(studies_dir)
    kind, norm = classify(url)
    if kind == "journal":
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalFileBackend
        p = Path(norm)
        _check_journal_path(p)
        if must_exist and not p.is_file():
            raise ImtuneError(f"no journal storage at {p} (no such file); pass the --storage the studies were run "
                              "with, or run `tune` first")
        try:
            if not must_exist:
                p.parent.mkdir(parents=True, exist_ok=True)
            return JournalStorage(JournalFileBackend(str(p)))
        except OSError as e:
            raise ImtuneError(f"cannot open journal storage {p}: {e.strerror or e}") from None
        except Exception as e:  # noqa: BLE001 - replaying the file failed: its content is no Optuna journal
            line = _first_bad_journal_line(p)
            raise ImtuneError(f"journal storage {p} is not an Optuna journal file, or is corrupt "
                              f"({_journal_fault(e)}{f'; first at line {line}' if line else ''}); pass the "
                              "journal:PATH the studies were run with, or a new file name") from None
    if heartbeat is not None and int(heartbeat) < 0:
        raise ImtuneError(f"heartbeat must be >= 0 seconds (0 = off), got {heartbeat}")
    hb = int(heartbeat) if heartbeat else None
    kwargs = {}
    if hb:
        kwargs = dict(heartbeat_interval=hb, grace_period=int(grace_period or 3 * hb))
        if retry_stale:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "experimental" since Optuna 2.8
                kwargs["heartbeat_stale_trial_callback"] = optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=1)
    if kind == "sqlite":
        _prepare_sqlite(_sqlite_path(norm), must_exist=must_exist)
        engine_kwargs = {"connect_args": {"timeout": SQLITE_TIMEOUT_S}}
    else:
        engine_kwargs = {"pool_pre_ping": True}
        from sqlalchemy.engine import make_url
        backend = make_url(norm).get_backend_name()
        if backend == "postgresql":
            engine_kwargs["connect_args"] = {"connect_timeout": 10}
        elif backend in ("mysql", "mariadb"):
            engine_kwargs["connect_args"] = {"connect_timeout": 10}
    if must_exist:
        kwargs["skip_table_creation"] = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # heartbeat_interval is "experimental"
        try:
            if must_exist:
                _retrying(lambda: _require_tables(norm, engine_kwargs, url), "open", url)
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
            raise ImtuneError(f"cannot open storage {mask_url(url)}: {scrub(_root_text(e), url)}") from None


def _require_tables(norm: str, engine_kwargs: dict, url: str) -> None:
    """ImtuneError unless the database holds Optuna's tables (nothing is created)."""
    import sqlalchemy
    engine = sqlalchemy.create_engine(norm, **engine_kwargs)
    try:
        tables = set(sqlalchemy.inspect(engine).get_table_names())
    finally:
        engine.dispose()
    if "studies" not in tables:
        raise ImtuneError(f"storage {mask_url(url)} holds no Optuna studies (no 'studies' table); pass the "
                          "--storage the studies were run with, or run `tune` first")
