"""``--storage`` values parsed: which kind of storage (SQLite, a database server, a journal file) and its normalised
URL."""
from __future__ import annotations

import os
import re
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.storage.locations import default_storage_url
from tuner.storage.masking import _repair_at, mask_url, scrub

JOURNAL_SUFFIXES = (".log", ".journal", ".jsonl")


SQLITE_SUFFIXES = (".db", ".sqlite", ".sqlite3")


EXPECTED = "expected sqlite:///PATH, postgresql://USER:PASS@HOST:PORT/DB, mysql://..., or journal:PATH"


_SCHEME_ONLY_RE = re.compile(r"^(?P<scheme>[A-Za-z][A-Za-z0-9+.\-]*):(?!//)")


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
        m = _SCHEME_ONLY_RE.match(url)
        if m and len(m.group("scheme")) > 1:  # a URL scheme without "//" (a typo), not a path
            scheme, rest = m.group("scheme"), url[m.end():]
            hint = ""
            if scheme.lower() == "sqlite" and rest:
                r = rest.lstrip("/")
                hint = (f"; did you mean sqlite:///{r} (relative to the current folder) or sqlite:////{r} "
                        "(absolute)?" if rest.startswith("/") else f"; did you mean sqlite:///{r}?")
            raise ImtuneError(f"malformed storage URL {mask_url(url)!r}: a URL needs '://' after "
                              f"{scheme + ':'!r}, nothing was created{hint or ' (' + EXPECTED + ')'}")
        p = Path(url).expanduser()
        if p.suffix in JOURNAL_SUFFIXES:
            return "journal", str(p)
        if p.suffix in SQLITE_SUFFIXES:
            return "sqlite", f"sqlite:///{p.resolve()}"
        raise ImtuneError(f"malformed storage URL {mask_url(url)!r} ({EXPECTED})")
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError
    try:
        u = make_url(_repair_at(url))  # an unencoded '@' in the password is percent-encoded
    except (ArgumentError, ValueError) as e:
        raise ImtuneError(f"malformed storage URL {mask_url(url)!r}: {scrub(str(e), url)} ({EXPECTED})") from None
    backend = u.get_backend_name()
    if backend == "sqlite":
        if not u.database or u.database == ":memory:":
            raise ImtuneError(f"storage {mask_url(url)!r}: an SQLite storage needs a file path, after three "
                              "slashes (sqlite:///studies/optuna.db, sqlite:////abs/optuna.db); an in-memory "
                              "database is not shared between workers")
        return "sqlite", url
    if backend == "postgres":
        raise ImtuneError(f"unsupported storage {mask_url(url)!r}: SQLAlchemy spells the scheme postgresql:// "
                          "(not postgres://)")
    if backend in ("postgresql", "mysql", "mariadb", "oracle", "mssql"):
        if not u.host and "host" not in u.query and "unix_socket" not in u.query:
            raise ImtuneError(f"malformed storage URL {mask_url(url)!r}: no host ({EXPECTED})")
        if not u.database:
            raise ImtuneError(f"malformed storage URL {mask_url(url)!r}: no database name ({EXPECTED})")
        if "+" not in u.drivername:  # no driver named: use one that is installed
            for mod, driver in _DRIVERS.get(backend, ()):
                if _importable(mod):
                    u = u.set(drivername=f"{backend}+{driver}")
                    break
        return "rdb", u.render_as_string(hide_password=False)
    raise ImtuneError(f"unsupported storage {mask_url(url)!r} (scheme {u.drivername!r}; {EXPECTED})")


def _sqlite_path(url: str) -> Path:
    from sqlalchemy.engine import make_url
    return Path(make_url(url).database).expanduser()


def storage_absent(url: str | None, studies_dir: Path | str | None = None) -> bool:
    """True when ``url`` (default: the studies folder's SQLite file) is a SQLite or journal file that does not exist:
    no storage at all, as against one that is there but cannot be read (damaged, not a database, a server down)."""
    try:
        kind, norm = classify(url or default_storage_url(studies_dir))
    except ImtuneError:
        return False
    if kind == "rdb":
        return False
    return not os.path.lexists(_sqlite_path(norm) if kind == "sqlite" else Path(norm))


def storage_label(url: str | None, studies_dir: Path | str | None = None) -> str:
    """The masked URL as shown to users (the default expanded)."""
    return mask_url(url or default_storage_url(studies_dir))
