"""A throw-away PostgreSQL cluster on 127.0.0.1 that a test can stop and restart (the fault suite's server).

Like the fixture of tests/test_tuner_postgres.py (Debian's postgresql from .ci/install.sh; as root the server
runs as the ``postgres`` user), plus ``stop()`` / ``start()`` on the same data folder and port, ``sql()``
as the superuser, and ``dump()``: every row of every table as text (for the credential grep)."""
from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest

PASSWORD = "pw-Secr3t-imtune"


def pg_bin() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(p.split("/")[4]))
    if found:
        return Path(found[-1]).parent
    w = shutil.which("initdb")
    return Path(w).parent if w else None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PgServer:
    def __init__(self, password: str = PASSWORD, db: str = "optuna"):
        pg = pg_bin()
        if pg is None:
            pytest.skip("PostgreSQL server binaries not found (/usr/lib/postgresql/*/bin; .ci/install.sh installs "
                        "Debian's postgresql)")
        try:
            import psycopg2  # noqa: F401
        except ImportError:
            pytest.skip("psycopg2 is not installed (pip install psycopg2-binary)")
        self.root = os.geteuid() == 0
        if self.root:
            try:
                subprocess.run(["id", "postgres"], check=True, capture_output=True)
            except (subprocess.CalledProcessError, FileNotFoundError):
                pytest.skip("running as root but there is no 'postgres' user to run the server as")
        self.bin, self.password, self.db = pg, password, db
        self.dir = Path(tempfile.mkdtemp(prefix="imtune-pgf-"))
        self.data = self.dir / "data"
        self.port = free_port()
        self.as_pg = ["runuser", "-u", "postgres", "--"] if self.root else []
        pwfile = self.dir / "pw"
        pwfile.write_text(password + "\n")
        if self.root:
            shutil.chown(self.dir, "postgres")
            shutil.chown(pwfile, "postgres")
        try:
            self._run("initdb", "-D", str(self.data), "-U", "imtune", f"--pwfile={pwfile}", "-A", "scram-sha-256",
                      "--no-sync")
            pwfile.unlink()
            self.start()
            self._run("createdb", "-h", "127.0.0.1", "-p", str(self.port), "-U", "imtune", db,
                      env=dict(os.environ, PGPASSWORD=password))
        except subprocess.CalledProcessError as e:
            self.close()
            pytest.fail(f"could not start PostgreSQL: {e.stderr or e.stdout}")

    def _run(self, tool, *args, **kw):
        return subprocess.run(self.as_pg + [str(self.bin / tool), *args], check=True, capture_output=True, text=True,
                              stdin=subprocess.DEVNULL, timeout=120, **kw)

    @property
    def url(self) -> str:
        return f"postgresql://imtune:{self.password}@127.0.0.1:{self.port}/{self.db}"

    def start(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.dir / "log"), "-w", "-t", "60", "-o",
                  f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 -c fsync=off", "start")

    def stop(self, mode: str = "fast") -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "60", "stop")

    def connect(self):
        import psycopg2
        return psycopg2.connect(host="127.0.0.1", port=self.port, user="imtune", password=self.password,
                                dbname=self.db, connect_timeout=10)

    def sql(self, statement: str, params=None) -> None:
        con = self.connect()
        try:
            con.autocommit = True
            with con.cursor() as cur:
                cur.execute(statement, params)
        finally:
            con.close()

    def dump(self) -> str:
        """Every row of every table of the database (all schemas but the catalogs), as text."""
        con = self.connect()
        out = []
        try:
            with con.cursor() as cur:
                cur.execute("SELECT table_schema, table_name FROM information_schema.tables "
                            "WHERE table_schema NOT IN ('pg_catalog', 'information_schema')")
                tables = cur.fetchall()
                for schema, name in tables:
                    cur.execute(f'SELECT * FROM "{schema}"."{name}"')
                    out.append(f"-- {schema}.{name}")
                    out.extend(repr(row) for row in cur.fetchall())
        finally:
            con.close()
        assert len(tables) > 3, "the dump found no Optuna tables"
        return "\n".join(out)

    def close(self) -> None:
        subprocess.run(self.as_pg + [str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop"],
                       capture_output=True, stdin=subprocess.DEVNULL, timeout=60)
        shutil.rmtree(self.dir, ignore_errors=True)


def sqlite_dump(path: Path) -> str:
    """Every statement of an SQLite storage's full dump (schema and every row)."""
    import sqlite3
    con = sqlite3.connect(str(path))
    try:
        return "\n".join(con.iterdump())
    finally:
        con.close()
