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

One module per idea: :mod:`~tuner.storage.urls` (``--storage`` values parsed), :mod:`~tuner.storage.masking`
(credentials masked), :mod:`~tuner.storage.locations` (the studies folder and the default storage),
:mod:`~tuner.storage.sqlite` (WAL, busy timeout, damaged files), :mod:`~tuner.storage.journal` (journal files
checked), :mod:`~tuner.storage.retry` (opening retried), :mod:`~tuner.storage.opening` (:func:`open_storage`),
:mod:`~tuner.storage.faults` (mid-run failures as one line), :mod:`~tuner.storage.trials` (interrupted and stale
trials). Every name is importable from ``tuner.storage`` as before.
"""
from __future__ import annotations

from tuner.storage.faults import THREAD_FAULTS, interrupt_in_chain, quiet_thread_storage_faults, storage_fault
from tuner.storage.locations import (
                                     STUDIES_DIR_FIX,
                                     check_studies_dir,
                                     default_storage_url,
                                     default_studies_dir,
                                     project_root,
)
from tuner.storage.masking import MASK, SECRET_KEY_RE, mask_url, scrub
from tuner.storage.opening import DEFAULT_HEARTBEAT_S, open_storage
from tuner.storage.sqlite import SQLITE_DAMAGED, SQLITE_TIMEOUT_S
from tuner.storage.trials import fail_interrupted_trials, fail_stale_trials, track_created_trials
from tuner.storage.urls import EXPECTED, JOURNAL_SUFFIXES, SQLITE_SUFFIXES, classify, storage_absent, storage_label

__all__ = ["STUDIES_DIR_FIX", "check_studies_dir", "default_storage_url", "default_studies_dir", "project_root", "MASK",
           "SECRET_KEY_RE", "mask_url", "scrub", "EXPECTED", "JOURNAL_SUFFIXES", "SQLITE_SUFFIXES", "classify",
           "storage_absent", "storage_label", "SQLITE_DAMAGED", "SQLITE_TIMEOUT_S", "THREAD_FAULTS",
           "interrupt_in_chain", "quiet_thread_storage_faults", "storage_fault", "fail_interrupted_trials",
           "fail_stale_trials", "track_created_trials", "DEFAULT_HEARTBEAT_S", "open_storage"]
