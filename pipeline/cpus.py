"""How many CPUs this process may use (a leaf: the pair pool, the multiview bag pool and torch's thread count all
size themselves by it), and the pair pool's default size."""
from __future__ import annotations

import os


def available_cpus() -> int:
    """CPUs this process may run on (``os.sched_getaffinity``; ``os.cpu_count`` where unavailable)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux, or no affinity to read
        return max(1, os.cpu_count() or 1)


#: the environment variable giving the default of ``--jobs`` (a batch job's share of a node, a shared machine)
JOBS_VAR = "IMTUNE_JOBS"


def default_jobs() -> int:
    """The default number of stereo pair workers: ``$IMTUNE_JOBS`` when set (an integer >= 1), else every CPU this
    process may use. A malformed value is an ImtuneError naming it (never silently every CPU)."""
    from pipeline.errors import ImtuneError
    raw = os.environ.get(JOBS_VAR, "").strip()
    if not raw:
        return available_cpus()
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ImtuneError(f"{JOBS_VAR}={raw!r}: expected an integer >= 1 (the default of --jobs); unset it to use "
                          "every CPU")
    return n
