"""Optuna journal files checked before Optuna opens them: a regular file of log records, its last record complete."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from pipeline.errors import ImtuneError


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
