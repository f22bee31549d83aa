"""Opening a storage retried over transient lock and table-creation races; a lasting failure as one line saying what to
do."""
from __future__ import annotations

import time

from pipeline.errors import ImtuneError
from tuner.storage.masking import mask_url, scrub
from tuner.storage.sqlite import _sqlite_hint


def _retrying(fn, what: str, url: str, attempts: int = 8):
    from sqlalchemy.exc import DBAPIError, IntegrityError, OperationalError, ProgrammingError
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
