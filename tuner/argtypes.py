"""argparse ``type=`` callables for numeric options: finite numbers only, with the option's valid range.

``float("nan")`` and ``float("inf")`` parse, so a plain ``type=float`` lets ``--threshold nan`` through (every pair
then fails silently). Each callable here raises ``argparse.ArgumentTypeError`` with a short reason; argparse turns
it into the one-line ``tune: error: argument --x: ...`` and exit 2.
"""
from __future__ import annotations

import argparse
import math


def finite_float(s: str) -> float:
    """A finite number (rejects nan, inf and anything that is not a number)."""
    try:
        v = float(s)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {s!r}")
    return v


def _ranged(check, what: str):
    def parse(s: str) -> float:
        v = finite_float(s)
        if not check(v):
            raise argparse.ArgumentTypeError(f"must be {what}, got {s!r}")
        return v
    parse.__doc__ = f"A finite number {what}."
    return parse


positive_float = _ranged(lambda v: v > 0, "> 0")
positive_float.__name__ = "positive_float"
nonnegative_float = _ranged(lambda v: v >= 0, ">= 0")
nonnegative_float.__name__ = "nonnegative_float"
#: a fraction in [0, 1] (co-visibility)
unit_float = _ranged(lambda v: 0.0 <= v <= 1.0, "in [0, 1]")
unit_float.__name__ = "unit_float"
#: Lowe's ratio r in (0, 1]
ratio_float = _ranged(lambda v: 0.0 < v <= 1.0, "in (0, 1]")
ratio_float.__name__ = "ratio_float"
#: a probability in (0, 1) (RANSAC confidence)
probability_float = _ranged(lambda v: 0.0 < v < 1.0, "in (0, 1)")
probability_float.__name__ = "probability_float"


def _int_at_least(lo: int, what: str):
    def parse(s: str) -> int:
        try:
            v = int(s)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be {what}, got {s!r}")
        return v
    return parse


#: an integer >= 1 (a count of processes, pairs, runs)
positive_int = _int_at_least(1, ">= 1")
positive_int.__name__ = "positive_int"
#: an integer >= 0 where 0 switches the thing off (e.g. --heartbeat)
nonnegative_int = _int_at_least(0, ">= 0 (0 = off)")
nonnegative_int.__name__ = "nonnegative_int"
#: an integer >= 0: a random seed (numpy's generators, used by the bootstrap and the samplers, take no negative
#: seed) or how many of something to show (0 = none); two names for one rule
seed_int = count_int = _int_at_least(0, ">= 0")
seed_int.__name__ = "nonnegative_integer"
