"""How many CPUs this process may use (a leaf: the pair pool, the multiview bag pool and torch's thread count all
size themselves by it)."""
from __future__ import annotations

import os


def available_cpus() -> int:
    """CPUs this process may run on (``os.sched_getaffinity``; ``os.cpu_count`` where unavailable)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux, or no affinity to read
        return max(1, os.cpu_count() or 1)
