"""Errors that the CLI turns into a one-line message and a non-zero exit (never a traceback)."""


class ImtuneError(Exception):
    """A user-facing error: bad input, unknown name, unreadable file. ``str(e)`` is one line naming the culprit."""


class UnavailableError(ImtuneError):
    """A known method that cannot run on this machine (missing package, missing weights, non-free)."""


class EvaluationStopped(ImtuneError):
    """An evaluation stopped before its end by a bound it was given (a reconstruction trial's mapping time:
    ``--trial-timeout``). A study's objective records the trial as pruned with ``str(e)`` as its reason; anywhere
    else it is a one-line error."""
