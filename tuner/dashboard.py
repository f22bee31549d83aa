"""optuna-dashboard on a study storage, bound to 127.0.0.1 unless told otherwise.

    from tuner.dashboard import serve
    serve("sqlite:///studies/optuna.db", port=8080)   # blocks until Ctrl-C

The storage is opened like the workers open it (SQLite busy timeout + WAL), so the dashboard reads
while workers write without "database is locked" (optuna-dashboard issue 545); it is never created
(a path with no storage is a one-line error) and its URL is shown masked (``tuner.storage.mask_url``).
"""
from __future__ import annotations

import socket
import sys

from pipeline.errors import ImtuneError


def check_port(host: str, port: int) -> None:
    """ImtuneError if (host, port) cannot be bound."""
    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(fam, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, int(port)))
        except OSError as e:
            raise ImtuneError(f"cannot serve the dashboard on {host}:{port}: {e.strerror or e}") from None


LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def exposure_warning(host: str) -> str | None:
    """The warning printed when the dashboard binds beyond this machine (None for a loopback address): the
    address, what it means (every interface for 0.0.0.0 / ::), and how to keep it local."""
    if host in LOCAL_HOSTS:
        return None
    where = (f"every network interface ({host})" if host in ("0.0.0.0", "::") else f"the address {host}")
    return (f"warning: the dashboard listens on {where}: other machines that can reach it can read every study, "
            "with no password; use --host 127.0.0.1 to keep it on this machine")


def serve(storage_url: str | None = None, host: str = "127.0.0.1", port: int = 8080, studies_dir=None,
          quiet: bool = False) -> None:
    """Serve optuna-dashboard for the storage (default: the studies folder's SQLite file)."""
    try:
        from optuna_dashboard import run_server
    except ImportError:
        raise ImtuneError("optuna-dashboard is not installed: pip install optuna-dashboard") from None
    from tuner.storage import classify, default_storage_url, open_storage, storage_label
    if not str(host or "").strip():  # "" binds every interface: never by accident
        raise ImtuneError("--host is empty: give an address such as 127.0.0.1 (this machine only) or 0.0.0.0 "
                          "(every interface), or leave the option out")
    if not (0 < int(port) < 65536):
        raise ImtuneError(f"invalid port {port}")
    classify(storage_url or default_storage_url(studies_dir))  # a malformed URL first: nothing else to try
    check_port(host, port)
    # a dashboard only reads: a missing SQLite / journal file is an error, never a new empty storage
    storage = open_storage(storage_url, heartbeat=None, studies_dir=studies_dir, must_exist=True)
    if not quiet:
        shown = f"[{host}]" if ":" in host else host
        print(f"optuna-dashboard: http://{shown}:{port}/  (storage {storage_label(storage_url, studies_dir)}; "
              "Ctrl-C to stop)", file=sys.stderr, flush=True)
    warning = exposure_warning(host)
    if warning and not quiet:
        print(warning, file=sys.stderr, flush=True)
    run_server(storage, host=host, port=int(port))
