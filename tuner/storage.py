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
attributes see (every credential form: userinfo password, an unencoded ``@`` in it, secret query
parameters), :func:`scrub` cleans any exception text before it is printed. Commands that only read
open the storage with ``must_exist=True`` (never create one); :func:`storage_fault` turns a storage
that fails mid-run (full disk, server gone) into a one-line message.
"""
from __future__ import annotations

import json
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


# -- credentials ----------------------------------------------------------------------------------
#
# A URL is masked by SQLAlchemy's own rendering (``make_url(url).render_as_string(hide_password=True)``)
# plus the query parameters that carry secrets (libpq reads ``?password=``, ``?sslpassword=``, ``?passfile=``,
# ``?sslkey=``; MySQL drivers ``?passwd=``, ``?ssl_key=``). A regex is used only where SQLAlchemy cannot
# parse the string (it raises ArgumentError / ValueError, e.g. ``u:a@b:c@host:5432`` where it reads
# ``c@host:5432`` as the port) and for free text such as an exception message that may embed a URL or
# a libpq DSN (``host=... password=...``): there is no structure to parse, so every ``scheme://user:...@``
# userinfo (up to the last ``@`` of the token) and every ``secret-ish-key=value`` is masked.

MASK = "***"
#: query / DSN keys whose value is a secret (a password, a key, a file of passwords, a token)
SECRET_KEY_RE = re.compile(r"pass|pwd|secret|token|key|auth|cred", re.I)
_URL_PW_RE = re.compile(r"(?P<pre>\b[A-Za-z][A-Za-z0-9+.\-]*://[^\s:/@]*:)(?P<pw>\S*)@(?P<post>[^\s@]*)")
#: in free text only the key names drivers actually use, so that e.g. "--fix monkey=3" stays readable
_KV_RE = re.compile(r"(?<![A-Za-z0-9_.\-])(?P<k>password|passwd|pwd|pass|sslpassword|passfile|sslkey|ssl_key|secret|"
                    r"token|access_token|api_key|apikey|auth_token|PGPASSWORD)(?P<eq>\s*=\s*)"
                    r"(?P<v>'(?:[^'\\]|\\.)*'|\"[^\"]*\"|[^\s&'\",;)\]]+)", re.I)
_SCHEME_ONLY_RE = re.compile(r"^(?P<scheme>[A-Za-z][A-Za-z0-9+.\-]*):(?!//)")


#: the start of a URL that lost its "//" or ":" (``postgresql:/u:pw@h``, ``postgresql//u:pw@h``, ``postgresql:u:pw@h``)
_LOOSE_PREFIX_RE = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*(?::/*|/+)")


def _loose_password_span(s: str) -> tuple[int, int] | None:
    """Where the password of a malformed URL without ``://`` is: ``(start, end)`` in ``s``, or None.

    ``postgresql:/user:pw@host/db``, ``postgresql//user:pw@host/db``, ``postgresql:user:pw@host/db`` and
    ``user:pw@host/db`` are typos of a URL whose userinfo still carries the password: everything from the first
    ``:`` of the userinfo to the last ``@`` is masked (an ``@`` in a password is not always encoded). A
    journal path or a plain path (no ``:`` before its last ``@``) has none."""
    if s.startswith("journal:") or "@" not in s:
        return None
    at = s.rfind("@")
    head = s[:at]
    start = 0
    m = _LOOSE_PREFIX_RE.match(head)
    if m and (":" in head[m.end():] or "/" in m.group(0)):  # a scheme before the userinfo ("user:" alone is none)
        start = m.end()
    colon = head.find(":", start)
    if colon < 0 or colon + 1 >= at or head[colon + 1:] in ("PASS", "PASSWORD", MASK):
        return None
    return colon + 1, at


def _loose_mask(s: str) -> str:
    """A malformed URL without ``://`` with its password (:func:`_loose_password_span`) and secret query
    parameters masked; other strings unchanged."""
    span = _loose_password_span(s)
    if span is None:
        return s
    return _mask_query(s[:span[0]] + MASK + s[span[1]:])


def _regex_mask(text: str) -> str:
    """Fallback for text SQLAlchemy cannot parse: URL userinfo passwords and secret key=value pairs."""
    text = _URL_PW_RE.sub(lambda m: m.group(0) if m.group("pw") in ("PASS", "PASSWORD", MASK)  # placeholders
                          else m.group("pre") + MASK + "@" + m.group("post"), text)
    return _KV_RE.sub(lambda m: m.group(0) if m.group("v").startswith(MASK) else m.group("k") + m.group("eq") + MASK,
                      text)


def _repair_at(url: str) -> str:
    """``scheme://user:pa@ss@host/db`` -> ``scheme://user:pa%40ss@host/db``.

    SQLAlchemy (like libpq) ends the password at the first ``@``, so an unencoded ``@`` in a password
    makes ``ss@host`` the host name and ``ss`` leaks in every message naming the host. A host name cannot
    contain ``@``: where SQLAlchemy's host does, everything up to its last ``@`` belongs to the password
    (or, with no password, to the user name), which is then percent-encoded. Where SQLAlchemy cannot
    parse the URL at all (e.g. ``u:a@b:c@host:5432``: it reads ``c@host:5432`` as the port), the userinfo
    is taken to run to the last ``@`` of the URL, as ``urllib.parse`` does. URLs with at most one ``@``,
    or whose other ``@`` is elsewhere (a path, a query value), are returned unchanged."""
    from urllib.parse import quote, unquote
    scheme, sep, rest = url.partition("://")
    if not sep or rest.startswith("/") or rest.count("@") < 2:
        return url
    from sqlalchemy.engine import make_url
    try:
        u = make_url(url)
    except Exception:  # noqa: BLE001 - ArgumentError, ValueError (a port that is no number): see below
        u = None
    if u is not None:
        if not u.host or "@" not in u.host:
            return url
        extra, host = u.host.rsplit("@", 1)
        if u.password is not None:
            u = u.set(password=f"{u.password}@{extra}", host=host)
        else:
            u = u.set(username=f"{u.username or ''}@{extra}", host=host)
        return u.render_as_string(hide_password=False)
    at = rest.rfind("@")
    userinfo, after = rest[:at], rest[at + 1:]
    user, colon, pw = userinfo.partition(":")
    if not colon:
        user, pw = userinfo, None
    enc = lambda v: quote(unquote(v), safe="")  # noqa: E731 - idempotent on already-encoded parts
    cred = enc(user) + (":" + enc(pw) if pw is not None else "")
    return f"{scheme}://{cred}@{after}"


def _parse(url: str):
    """SQLAlchemy's URL object for ``url`` (after :func:`_repair_at`), or None if it cannot parse it."""
    from sqlalchemy.engine import make_url
    try:
        return make_url(_repair_at(url))
    except Exception:  # noqa: BLE001 - ArgumentError, ValueError (bad port), ...: not parseable
        return None


def _mask_query(rendered: str) -> str:
    base, q, query = rendered.partition("?")
    if not q:
        return rendered
    from urllib.parse import unquote_plus
    parts = []
    for item in query.split("&"):
        k, eq, _v = item.partition("=")
        parts.append(f"{k}={MASK}" if eq and SECRET_KEY_RE.search(unquote_plus(k)) else item)
    return base + "?" + "&".join(parts)


def mask_url(url: str | None) -> str:
    """The storage URL as shown to users: password and secret query parameters replaced by ``***``.

    Journal files and bare paths (no ``://``) are returned unchanged. Malformed URLs are masked too."""
    if url is None:
        return ""
    s = str(url).strip()
    if "://" not in s:
        return _loose_mask(s)
    u = _parse(s)
    if u is None:
        return _regex_mask(s)
    return _mask_query(u.render_as_string(hide_password=True))


def _secrets(url: str | None) -> list[str]:
    """Every secret value the URL carries, raw and in its percent-encoded forms (longest first)."""
    if not url:
        return []
    from urllib.parse import quote, quote_plus
    s = str(url).strip()
    vals = []
    if "://" not in s:  # a malformed URL (a typo of one) still carries its password
        span = _loose_password_span(s)
        if span is not None:
            vals.append(s[span[0]:span[1]])
    elif (u := _parse(s)) is not None:
        if u.password:
            vals.append(str(u.password))
        for k, v in u.query.items():
            if SECRET_KEY_RE.search(k):
                vals.extend([v] if isinstance(v, str) else list(v))
    else:  # unparseable: what the regex would mask
        m = _URL_PW_RE.search(s)
        if m and m.group("pw"):
            vals.append(m.group("pw"))
    out = set()
    for v in vals:
        if v:
            out.update({v, quote(v, safe=""), quote_plus(v), quote(v)})
    return sorted(out, key=len, reverse=True)


def scrub(text, url: str | None = None) -> str:
    """``text`` (e.g. an exception message from SQLAlchemy or psycopg2) as one line, with the secrets of
    ``url`` and any URL password or ``password=...`` pair it embeds replaced by ``***``."""
    text = " ".join(str(text).split())
    for sec in _secrets(url):
        if len(sec) >= 4:
            text = text.replace(sec, MASK)
        else:  # a very short secret: only where it stands alone, not inside every word
            text = re.sub(rf"(?<![A-Za-z0-9]){re.escape(sec)}(?![A-Za-z0-9])", MASK, text)
    return _regex_mask(text)


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
    low = str(orig).lower()
    hint = ""
    if any(k in low for k in _UNREACHABLE):
        hint = "; is the database server running and reachable there? start it or fix --storage"
    elif "password authentication failed" in low or "access denied" in low:
        hint = "; check the user name and password in --storage"
    elif "does not exist" in low and "database" in low:
        hint = "; create the database first (e.g. `createdb`) or fix --storage"
    else:
        hint = _sqlite_hint(low)
    raise ImtuneError(f"cannot {what} storage {mask_url(url)}: {scrub(first, url)}{hint}") from None


#: libpq / MySQL driver messages of a server that cannot be reached or went away
_UNREACHABLE = ("connection refused", "could not connect", "could not translate host name", "no route to host",
                "timeout expired", "timed out", "name or service not known", "can't connect", "network is unreachable")
_LOST = _UNREACHABLE + ("server closed the connection", "terminating connection", "connection already closed",
                        "connection to server", "ssl syscall", "the database system is", "connection reset",
                        "broken pipe", "lost connection", "has gone away", "could not receive data",
                        "could not send data", "connection was closed", "connection is closed")
_FULL = ("database or disk is full", "disk i/o error", "no space left", "file too large", "disk quota")
_FULL_RE = re.compile("|".join(map(re.escape, _FULL)), re.I)


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


def _check_journal_path(p: Path) -> None:
    """A journal path that exists must be a regular file: a device (/dev/null, /dev/full: endless zeros read until
    memory runs out), a folder or a FIFO is refused before Optuna opens it."""
    import stat

    from optuna.storages.journal._file import LOCK_FILE_SUFFIX
    lock = Path(str(p) + LOCK_FILE_SUFFIX)
    try:  # Optuna's lock is a symbolic link it creates and removes (a stale one is released after a grace period);
        lmode = os.lstat(lock).st_mode  # a folder there: 30 s of silent retries, then Optuna renames it away
    except OSError:
        lmode = None
    if lmode is not None and stat.S_ISDIR(lmode):
        raise ImtuneError(f"{lock} is a folder where journal storage {p} takes its lock (a link Optuna creates and "
                          "removes): move it away, or give another journal: path")
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        return
    except OSError as e:  # e.g. a file where a folder of the path should be
        raise ImtuneError(f"cannot open journal storage {p}: {e.strerror or e}") from None
    if not stat.S_ISREG(mode):
        from pipeline.fileio import file_kind
        kind = file_kind(mode)
        raise ImtuneError(f"journal storage {p} is {kind}, not a file; give journal: the path of a journal file "
                          "(a new name creates one)")
    # Optuna skips a last line that is no JSON (a record another worker is still writing), so a one-line text file
    # would pass for an empty journal and then be appended to: its first complete line must be a log record
    import json
    try:
        with open(p, "rb") as f:
            first = f.readline(1 << 24)
    except OSError as e:
        raise ImtuneError(f"cannot open journal storage {p}: {e.strerror or e}") from None
    if not first:
        return  # empty: a new journal
    rec: object = None
    if not first.lstrip().startswith(b"{"):  # every record is a JSON object; binary or text is not
        ok = False
        try:
            first.decode("utf-8")
        except UnicodeDecodeError as e:
            rec = e
    elif not first.endswith(b"\n"):
        return _check_journal_tail(p)  # the first record, still being written by another worker, or cut short
    else:
        try:
            rec = json.loads(first)
            ok = isinstance(rec, dict) and "op_code" in rec
        except ValueError as e:  # UnicodeDecodeError too
            ok, rec = False, e
    if not ok:
        why = _journal_fault(rec) if isinstance(rec, Exception) else "its first line is no Optuna log record"
        raise ImtuneError(f"journal storage {p} is not an Optuna journal file, or is corrupt ({why}); pass the "
                          "journal:PATH the studies were run with, or a new file name")
    _check_journal_tail(p)


def _check_journal_tail(p: Path) -> None:
    """A journal's last record ends with its line end. Cut short (a crash or a full disk mid-write), Optuna skips it
    on reading but appends the next record right after its bytes: the two make one invalid line, the new trial is
    lost (`tune run` died with "AttributeError: ... '_last_created_trial_id_by_this_process'") and every later
    reading of the journal fails. A record another worker is writing ends within moments: looked at again first."""
    for attempt in range(6):
        try:
            with open(p, "rb") as f:
                size = f.seek(0, os.SEEK_END)
                f.seek(max(0, size - 1))
                if size == 0 or f.read(1) == b"\n":
                    return
                keep, pos = 0, size
                while pos > 0:  # the end of the last complete record
                    step = min(1 << 16, pos)
                    pos -= step
                    f.seek(pos)
                    i = f.read(step).rfind(b"\n")
                    if i >= 0:
                        keep = pos + i + 1
                        break
        except OSError as e:
            raise ImtuneError(f"cannot open journal storage {p}: {e.strerror or e}") from None
        time.sleep(0.1 * (attempt + 1))
    raise ImtuneError(f"journal storage {p} ends in a record cut short ({size - keep} bytes without a line end: a "
                      "crash or a full disk mid-write?) that the next record would be glued to, breaking the journal: "
                      f"drop it with `truncate -s {keep} {p}` (the complete records before it are kept), then rerun")


def _first_bad_journal_line(p: Path, limit: int = 1 << 30) -> int | None:
    """1-based number of the first complete line of a journal that is no JSON object with an ``op_code`` (where a
    user looks first; Optuna's error does not say), or None when every line is one (or the file is over
    ``limit`` bytes: not scanned)."""
    try:
        if p.stat().st_size > limit:
            return None
        with open(p, "rb") as f:
            for n, raw in enumerate(f, 1):
                if not raw.endswith(b"\n"):
                    return None  # a last record still being written: the cut-short check's case
                try:
                    rec = json.loads(raw)
                except ValueError:
                    return n
                if not isinstance(rec, dict) or "op_code" not in rec:
                    return n
    except OSError:
        return None
    return None


def _journal_fault(e: BaseException) -> str:
    """What is wrong with a journal's content, in a few words (Optuna says "Should not reach." for an unknown
    operation code, a KeyError for a missing field)."""
    if isinstance(e, UnicodeDecodeError):
        return "binary data, not JSON lines"
    if isinstance(e, ValueError):  # json.JSONDecodeError, Optuna's "Invalid log format."
        return f"a line that is not an Optuna log record: {' '.join(str(e).split())[:120]}"
    if isinstance(e, AssertionError):
        return "an unknown operation code"
    if isinstance(e, KeyError):
        return f"a log record without {' '.join(str(e).split())[:60]}"
    return f"{type(e).__name__}: {' '.join(str(e).split())[:120]}"


def _root_text(exc: BaseException) -> str:
    """The first line of the innermost database error behind ``exc`` (Optuna's StorageInternalError
    only says "invalid data in the commit"; the driver's message says what happened)."""
    chain = _chain(exc)
    dbapi = [e for e in chain if _is_db(e) and getattr(e, "orig", None) is None
             and type(e).__name__ != "StorageInternalError"]
    root = dbapi[0] if dbapi else exc
    text = str(root).strip()
    return text.splitlines()[0] if text else type(root).__name__


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


def track_created_trials(storage) -> list[int]:
    """The ids of the trials this process creates on ``storage`` (or takes from its waiting queue), appended as
    the storage hands them out; the same list on every call for one storage object.

    Written by hand because Optuna has no hook between creating a trial and calling the objective: a Ctrl-C in
    that window (the trial's first read, the sampler's ``before_trial``) left a RUNNING trial that the objective
    never saw (seen in CI, Dec 2026). Wraps the public ``create_new_trial`` and ``set_trial_state_values`` of the
    storage object the study calls (``study._storage``: Optuna wraps an RDB storage in a cache that calls the RDB
    storage's private ``_create_new_trial``, so wrapping the RDB storage itself would see nothing)."""
    from optuna.trial import TrialState
    ids = getattr(storage, "_imtune_created_trials", None)
    if ids is not None:
        return ids
    ids = []
    create, set_state = storage.create_new_trial, storage.set_trial_state_values

    def create_new_trial(study_id, template_trial=None):
        trial_id = create(study_id, template_trial)
        ids.append(trial_id)
        return trial_id

    def set_trial_state_values(trial_id, state, values=None):
        taken = set_state(trial_id, state, values)
        if taken and state == TrialState.RUNNING:  # a waiting (enqueued) trial this process popped
            ids.append(trial_id)
        return taken

    storage.create_new_trial = create_new_trial
    storage.set_trial_state_values = set_trial_state_values
    storage._imtune_created_trials = ids
    return ids


def fail_interrupted_trials(study, numbers, trial_ids=()) -> list[int]:
    """Mark FAIL the trials of this process still RUNNING after an interruption: those among ``numbers`` (the
    objective's) and among ``trial_ids`` (storage ids, see :func:`track_created_trials`: a trial interrupted
    before the objective saw it). One interrupted while Optuna recorded it (see :func:`interrupt_in_chain`) is
    left RUNNING too, and would wait for the heartbeat's grace period before a resume could see it stale. Best
    effort (the storage may be the thing that failed); returns the numbers marked."""
    from optuna.trial import TrialState
    marked = []
    try:
        numbers = set(numbers)
        for tid in list(trial_ids)[-2:]:  # one trial at a time: only the last can be running
            numbers.add(study._storage.get_trial(tid).number)
        running = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
        for n in sorted(numbers):
            if n in running:
                study.tell(n, state=TrialState.FAIL)
                marked.append(n)
    except Exception:  # noqa: BLE001 - the interruption is what gets reported
        pass
    return marked


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
