"""argparse ``type=`` callables for numeric options: finite numbers only, with the option's valid range.

``float("nan")`` and ``float("inf")`` parse, so a plain ``type=float`` lets ``--threshold nan`` through (every pair
then fails silently). Each callable here raises ``argparse.ArgumentTypeError`` with a short reason; argparse turns
it into the one-line ``tune: error: argument --x: ...`` and exit 2.
"""
from __future__ import annotations

import argparse
import math

from pipeline.config import MAX_ITERS, SEED_MAX


def finite_float(s: str) -> float:
    """A finite number (rejects nan, inf and anything that is not a number)."""
    try:
        v = float(s)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {s!r}")
    return v


finite_float.numeric = True


def _ranged(check, what: str):
    def parse(s: str) -> float:
        v = finite_float(s)
        if not check(v):
            raise argparse.ArgumentTypeError(f"must be {what}, got {s!r}")
        return v
    parse.__doc__ = f"A finite number {what}."
    parse.numeric = True
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


def _int_at_least(lo: int, what: str, hi: int | None = None, why_hi: str = ""):
    """An integer >= ``lo`` ("must be {what}" otherwise) and, with ``hi``, <= ``hi`` ("must be at most hi{why_hi}")."""
    def parse(s: str) -> int:
        try:
            v = int(s)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be {what}, got {s!r}")
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f"must be at most {hi}{why_hi}, got {s!r}")
        return v
    parse.numeric = True
    return parse


#: an integer >= 1 (a count of processes, pairs, runs)
positive_int = _int_at_least(1, ">= 1")
positive_int.__name__ = "positive_int"
#: an integer >= 0 where 0 switches the thing off (e.g. --heartbeat)
nonnegative_int = _int_at_least(0, ">= 0 (0 = off)")
nonnegative_int.__name__ = "nonnegative_int"
#: an integer >= 0: how many of something to show (0 = none)
count_int = _int_at_least(0, ">= 0")
count_int.__name__ = "nonnegative_integer"
#: a random seed: an integer in [0, 2**31 - 1] (``pipeline.config.SEED_MAX``). numpy's generators (the bootstrap,
#: the samplers) take no negative seed, and the seeded estimators take 31 bits: a larger seed would silently give
#: the run of a smaller one (2**31 that of 0); one range for every seed option
seed_int = _int_at_least(0, ">= 0", hi=SEED_MAX,
                         why_hi=f" (seeds are 0 to {SEED_MAX}: the estimators take 31 bits, a larger seed would repeat "
                                "a smaller one's run)")
seed_int.__name__ = "seed"
#: an iteration cap Gamma: an integer in [1, 2**31 - 1] (``pipeline.config.MAX_ITERS``, what the estimators take;
#: a larger one was printed as given and clamped)
iters_int = _int_at_least(1, ">= 1", hi=MAX_ITERS, why_hi=" (the largest iteration cap the estimators take)")
iters_int.__name__ = "iterations"


# -- a value typed empty (`--only ""`, `--data=`): an error naming the option, never "the default" ---------------

#: what to give instead of an empty value, by argparse dest (string options; numeric ones say "a number")
EMPTY_HINTS = {
    "only": "ids such as 1,2,4",
    "scenes": "scene names such as fountain-P11,entry-P10",
    "val_scenes": "scene names such as fountain-P11",
    "test_scenes": "scene names such as Herz-Jesus-P8,entry-P10",
    "data": "a data folder",
    "cache": "a folder", "studies_dir": "a folder", "gt_dir": "a folder", "keep_models": "a folder", "dest": "a folder",
    "out": "a path", "gallery": "an HTML file",
    "config": "a configuration file or a study name",
    "reference": "a configuration file, a study name or none",
    "sources": "study names or configuration files", "compare": "study names or configuration files",
    "study": "a study name", "warm_start": "a study name", "pareto": "study names",
    "pairs": "pairs such as '0000.jpg|0004.jpg'",
    "pair": "two image names",
    "bags": "bag sizes such as 5,10,25 or 5:100,10:50,25:25",
    "bag": "SIZE:INDEX such as 5:0",
    "storage": "a storage URL such as sqlite:///studies/optuna.db",
    "host": "an address such as 127.0.0.1 (this machine only) or 0.0.0.0 (every interface)",
    "space": "a search-space YAML file",
    "feature": "a feature name (see `tune list`)", "ransac": "an estimator name (see `tune list`)",
    "fix": "NAME=VALUE such as max_iters=20000", "feature_option": "KEY=VALUE such as edge_threshold=10",
    "prefilter": "a pre-filter name (none, gms, adalam)", "matches": "custom:DIR",
    "base_url": "a URL", "jobs": "a number of processes", "ci_resamples": "a number",
}


def empty_value_message(action: argparse.Action) -> str:
    """The one line for an option given an empty (or blank) value: which option, and what to give instead."""
    if action.option_strings:
        name = max(action.option_strings, key=len)
    else:
        name = str(action.metavar or action.dest).upper()
    numeric = action.type in (int, float) or getattr(action.type, "numeric", False)
    hint = "a number" if numeric else EMPTY_HINTS.get(action.dest, "a value")
    tail = ", or leave the option out" if action.option_strings and not action.required else ""
    return f"{name} is empty: give {hint}{tail}"



def scene_list(s: str) -> str:
    """``--scenes`` / ``--val-scenes`` / ``--test-scenes``: comma-separated scene names, at least one, each once
    (a scene named twice would have its pairs evaluated twice and its interval narrowed). Returns the names
    joined by commas, blanks removed."""
    names = [n.strip() for n in str(s).split(",")]
    names = [n for n in names if n]
    if not names:
        raise argparse.ArgumentTypeError(f"{s!r} names no scene (give comma-separated names such as fountain-P11)")
    seen = set()
    for n in names:
        if n in seen:
            raise argparse.ArgumentTypeError(f"scene {n!r} is named twice in {s!r}: name each scene once")
        seen.add(n)
    return ",".join(names)


#: the most bootstrap / sign-flip resamples an option takes: scipy's bootstrap holds every resample in memory (about
#: 16 bytes per resample and pair: 100,000 resamples of 1,500 pairs are 2.4 GB), and 2,000 (the default) already
#: gives a 95% interval's ends to within a few thousandths
MAX_RESAMPLES = 100_000
RESAMPLES_WHY = "every resample is held in memory"


#: the fewest resamples a 95% interval is drawn from: with fewer, its 2.5% and 97.5% percentiles are one or two
#: resamples (`tune compare --ci-resamples 1` printed mAA10 0.8667 [0.8000, 0.8000] and B - A +0.1000 [+0.2000,
#: +0.2000]: intervals that miss their own estimate)
MIN_RESAMPLES = 100
MIN_RESAMPLES_WHY = "for a 95% interval"


def resamples_int(s: str) -> int:
    """A resample count: an integer in [MIN_RESAMPLES, MAX_RESAMPLES]."""
    v = positive_int(s)
    if v < MIN_RESAMPLES:
        raise argparse.ArgumentTypeError(f"must be >= {MIN_RESAMPLES} {MIN_RESAMPLES_WHY}, got {s!r}")
    if v > MAX_RESAMPLES:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_RESAMPLES:,} ({RESAMPLES_WHY}), got {s!r}")
    return v
