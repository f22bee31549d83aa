"""Errors that the CLI turns into a one-line message and a non-zero exit (never a traceback)."""


class ImtuneError(Exception):
    """A user-facing error: bad input, unknown name, unreadable file. ``str(e)`` is one line naming the culprit."""


class UnavailableError(ImtuneError):
    """A known method that cannot run on this machine (missing package, missing weights, non-free)."""
