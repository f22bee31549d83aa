"""The `tune` command. A thin layer over documented Python calls; every error is one line on stderr
and a non-zero exit (set IMTUNE_DEBUG=1 for a traceback).

    tune --feature sift --ransac degensac          # tune on validation, freeze, run the test scenes
    tune evaluate --feature sift --ratio 0.85 ...  # one fixed configuration
    tune list                                      # every method and whether it runs here
    tune data download strecha
"""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading

from pipeline.errors import ImtuneError

# Subcommand modules: each has ``register(subparsers)`` that adds its parser with ``func=run``.
SUBCOMMAND_MODULES = ["tuner.commands.evaluate", "tuner.commands.listing", "tuner.commands.data",
                      "tuner.commands.viz", "tuner.commands.compare", "tuner.commands.findings"]
OPTIONAL_MODULES = ["tuner.commands.study"]  # the Optuna commands (run, calibrate, test, table, ...)
DEFAULT_SUBCOMMAND = "run"
STORAGE_ENV = "IMTUNE_STORAGE"  # --storage when it is not given (every command that opens a storage)


MAIN_JOB = "tune --feature sift --ransac degensac"
EXAMPLES = f"""\
The main job (tune r, eta and Gamma on the validation scenes under a time budget, freeze the
optimum, run the test scenes; downloads the default data set if none is found):
  {MAIN_JOB}

More:
  tune evaluate --feature sift --ratio 0.85 --threshold 0.5   one fixed configuration
  tune data scenes                                            which data is used, and why
  tune data download strecha                                  fetch the default data set
  tune table | tune results | tune dashboard                  read the studies
  tune list                                                   every feature and estimator

`tune COMMAND -h` shows a command's options with their defaults; `tune --version`.
"""


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's help ends with its default, also for options declared without a help text; help that
    already states its default ("(default ...", "default: ...", "(else ...") is left as written."""

    STATED = ("%(default)", "(default", "default:", "(else ")

    def _format_action(self, action):
        if not action.help and action.option_strings and action.default is not argparse.SUPPRESS:
            import copy
            action = copy.copy(action)
            action.help = self._default_text(action) or ""
        return super()._format_action(action)

    def _default_text(self, action) -> str:
        if action.default is argparse.SUPPRESS or action.nargs == 0 and action.const is None:
            return ""
        if action.required:  # `tune test --study`: "(default: none)" read as optional
            return "(required)"
        d = action.default
        if isinstance(d, bool) and action.nargs == 0:
            return "(default: off)" if not d else "(default: on)"
        if d is None or d == []:
            return "(default: none)"
        return "(default: %(default)s)"

    def _get_help_string(self, action):
        h = action.help or ""
        if any(m in h.lower() for m in self.STATED) or not (action.option_strings or
                                                               action.nargs in (argparse.OPTIONAL,
                                                                                argparse.ZERO_OR_MORE)):
            return h
        extra = self._default_text(action)
        return f"{h} {extra}" if extra and h else (extra or h)


class _TopFormatter(argparse.RawDescriptionHelpFormatter, _HelpFormatter):
    """The top-level help keeps the examples' layout."""


class _HelpAllAction(argparse.Action):
    """``--help-all``: the help with every option described, the less used ones included."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.print_help(full=True)
        parser.exit(0)


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)
        self.less_used: list[str] = []  # options `-h` names in one paragraph; `--help-all` describes them

    def set_less_used(self, options: list[str]) -> None:
        """``-h`` describes what most people set and names these options in one paragraph at the end;
        ``--help-all`` describes every option. Every option is accepted either way."""
        known = {s for a in self._actions for s in a.option_strings}
        missing = [o for o in options if o not in known]
        if missing:
            raise ValueError(f"{self.prog}: no such options {missing}")
        self.less_used = list(options)
        self.add_argument("--help-all", action=_HelpAllAction, help="show every option, the less used ones too")

    def format_help(self, full: bool = False) -> str:
        if full or not self.less_used:
            return super().format_help()
        hidden = [a for a in self._actions if set(a.option_strings) & set(self.less_used)]
        saved = [a.help for a in hidden]
        try:
            for a in hidden:
                a.help = argparse.SUPPRESS
            text = super().format_help()
        finally:
            for a, h in zip(hidden, saved):
                a.help = h
        import textwrap
        tail = textwrap.fill(f"less used options (`{self.prog} --help-all` describes them): "
                             + ", ".join(self.less_used), width=min(100, _help_width()), break_on_hyphens=False)
        return text.rstrip("\n") + "\n\n" + tail + "\n"

    def print_help(self, file=None, full: bool = False):
        self._print_message(self.format_help(full=full), file or sys.stdout)

    def error(self, message):  # one line, exit 2 (argparse's own usage dump is noise here)
        sys.stderr.write(f"tune: error: {message}\n")
        raise SystemExit(2)

    def _get_values(self, action, arg_strings):
        # a value typed empty or blank (`--only ""`, `--data=`) is an error naming the option: left to the commands,
        # "" reads as "not given" and silently means the default (`--only ""` ran all twelve findings). Here, once,
        # for every option of every command; environment variables set to "" still mean unset.
        if not isinstance(action, argparse._SubParsersAction) and action.nargs != argparse.REMAINDER:
            for s in arg_strings:
                if isinstance(s, str) and not s.strip():
                    from tuner.argtypes import empty_value_message
                    self.error(empty_value_message(action))
        return super()._get_values(action, arg_strings)

    def _check_value(self, action, value):
        # argparse's own check, plus "did you mean ...?" for a misspelt command or choice
        if action.choices is None or value in action.choices:
            return
        from pipeline.registry import did_you_mean
        names = [str(c) for c in action.choices]
        hint = did_you_mean(str(value), names)
        if isinstance(action, argparse._SubParsersAction):
            cmd = " ".join(self.prog.split()[1:] + [""])  # "data " for `tune data downlod`
            self.error(f"unknown command '{cmd}{value}'{hint} (commands: {', '.join(names)})")
        noun = str(action.metavar or action.dest).lower().replace("_", " ").replace("-", " ")
        where = f"{'/'.join(action.option_strings)}: " if action.option_strings else ""
        self.error(f"{where}unknown {noun} {value!r}{hint} (choose from {', '.join(names)})")


def _help_width() -> int:
    import shutil
    return shutil.get_terminal_size((100, 24)).columns - 2


class _VersionAction(argparse.Action):
    """`tune --version`: the installed package version plus the git commit of a checkout (tuner.study)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from tuner.version import code_version
        print(f"imtune {code_version()}")
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    import importlib
    ap = _Parser(prog="tune", description="Tune and evaluate wide-baseline image matching (the IMC protocol of "
                                          "Jin et al., IJCV 2021).\n\n" + EXAMPLES,
                 formatter_class=_TopFormatter, usage="tune [COMMAND] [OPTIONS]  (no COMMAND: run)")
    ap.add_argument("--version", action=_VersionAction, help="print the version (and git commit) and exit")
    sub = ap.add_subparsers(dest="command", parser_class=_Parser, metavar="COMMAND", prog="tune")
    for m in SUBCOMMAND_MODULES:
        importlib.import_module(m).register(sub)
    for m in OPTIONAL_MODULES:
        try:
            mod = importlib.import_module(m)
        except ModuleNotFoundError as e:
            if e.name != m:
                raise
            continue
        mod.register(sub)
    return ap


def short_help(ap: argparse.ArgumentParser) -> str:
    """What bare `tune` prints: usage, the main job first, the commands."""
    import textwrap
    cmds = ap._subparsers._group_actions[0].choices if ap._subparsers else {}
    commands = textwrap.fill(f"Commands: {', '.join(cmds)}", width=100, subsequent_indent="  ")
    return (f"usage: {ap.usage}\n\n{EXAMPLES}\n{commands}\n")


def route(argv: list[str], ap: argparse.ArgumentParser) -> list[str] | None:
    """argv with the default command made explicit: argv starting with an option (other than -h / --help /
    --version) means `run`; a first word that is no command is left for the parser to reject with a "did you
    mean". None for bare `tune` (print the short help)."""
    if not argv:
        return None
    known = set(ap._subparsers._group_actions[0].choices) if ap._subparsers else set()
    if argv[0].startswith("-") and argv[0] not in ("-h", "--help", "--version") and DEFAULT_SUBCOMMAND in known:
        return [DEFAULT_SUBCOMMAND] + argv
    return argv


#: ``on_interrupt`` of the commands that tune studies (run, findings): rerunning them resumes
RESUME_NOTE = "completed trials are kept, rerun the same command to resume"


class Terminated(KeyboardInterrupt):
    """SIGTERM (`kill PID`, a batch scheduler's time limit) stops a run the way Ctrl-C does: the pair pool is
    killed, the running trial is marked failed, completed trials stay in the storage. A KeyboardInterrupt, so
    every Ctrl-C path (the pool's, Optuna's) handles it."""


def _raise_terminated(signum, frame):
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM, during the clean-up, kills at once
    raise Terminated()


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM raises :class:`Terminated` in the main thread while the command runs (a process started in the
    background by a shell ignores SIGINT, so SIGTERM is how it is stopped; without this it dies at once, its
    pair workers and its running trial left behind)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old if old is not None else signal.SIG_DFL)  # None: a handler set from C


@contextlib.contextmanager
def _no_interrupt_swallowed():
    """A Ctrl-C / SIGTERM that lands while the garbage collector runs a weakref callback or a ``__del__`` (e.g.
    SQLAlchemy's ``_collection_gced``) raises its KeyboardInterrupt there, where CPython cannot propagate it: it
    prints "Exception ignored" and drops it, and the study would go on. ``sys.unraisablehook`` is where CPython
    reports such a drop; this hook delivers the signal again, so the interrupt is raised at the next bytecode of
    the main thread, where the command's handlers see it. (No library does this; CPython documents the drop.)"""
    old_hook = sys.unraisablehook
    pending: list[threading.Timer] = []

    def hook(unraisable):
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            import _thread
            signum = signal.SIGINT
            if issubclass(unraisable.exc_type, Terminated):
                signum = signal.SIGTERM
                if threading.current_thread() is threading.main_thread():
                    signal.signal(signal.SIGTERM, _raise_terminated)  # _raise_terminated had reset it to SIG_DFL
            # not raised here: a signal handled inside this hook would be dropped the same way; 50 ms later the
            # main thread is back in its own code (if it is in another such callback, this hook runs again)
            t = threading.Timer(0.05, _thread.interrupt_main, args=(signum,))
            t.daemon = True
            t.start()
            pending.append(t)
            return
        old_hook(unraisable)

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = old_hook
        for t in pending:  # the command has ended: nothing left to interrupt
            t.cancel()


def main(argv: list[str] | None = None) -> int:
    """The ``tune`` program (``argv`` None: the command line). An interrupted program exits within
    :data:`EXIT_GRACE` seconds whatever a library left running (:func:`exit_within`); a call with ``argv``
    (from Python) never ends its caller's process."""
    with _sigterm_as_interrupt(), _no_interrupt_swallowed():
        code = _main(argv)
    if argv is None and code in (130, 128 + signal.SIGTERM):
        exit_within(EXIT_GRACE, code)
    return code


#: seconds an interrupted command's exit may take before it is forced (:func:`exit_within`)
EXIT_GRACE = 30.0


def _interrupted(e: KeyboardInterrupt, args) -> int:
    """One line and exit 130 (Ctrl-C) / 143 (SIGTERM). What an interruption leaves, as the command says it
    (``on_interrupt`` in its parser's defaults): a study's completed trials are kept and it resumes; a test run
    or a calibration is written only when it finishes."""
    _stop_children()
    note = getattr(args, "on_interrupt", None)
    kept = f"; {note}" if note else ""
    code = 128 + signal.SIGTERM if isinstance(e, Terminated) else 130
    if isinstance(e, Terminated):
        print(f"tune: terminated (SIGTERM){kept}", file=sys.stderr)
    else:
        print(f"tune: interrupted{kept}", file=sys.stderr)
    return code


def _stop_children() -> None:
    """After an interruption, no worker outlives the command: the pools kill theirs as the interrupt passes; this
    kills any they could not know of (a Ctrl-C between CPython's spawn of a pool worker and its recording), which
    the interpreter's exit would otherwise join, waiting for its work to end."""
    import multiprocessing as mp

    from pipeline.tasks.pool import kill_processes, quiet_exit_wakeups
    kill_processes(mp.active_children())
    quiet_exit_wakeups()
    stop_stray_heartbeats()


def stop_stray_heartbeats(wait: float = 5.0) -> int:
    """Stop Optuna's heartbeat threads that nothing will stop; returns how many were stopped.

    Optuna 5.1 starts a trial's heartbeat thread (not a daemon) in ``HeartbeatThread.__enter__`` and stops it in
    ``__exit__``. A Ctrl-C that lands inside ``__enter__`` once the thread has started (``Thread.start`` waits for
    it: a likely place for the signal) skips ``__exit__``: the thread records heartbeats forever and the
    interpreter's exit waits for it, so ``tune`` printed "interrupted" and never exited (once in CI). The thread's
    stop event is its third argument (``_record_heartbeat(trial_id, heartbeat, stop_event)``); setting it ends the
    thread at its next wait. Hand-written: Optuna offers no handle on a thread whose ``__exit__`` never ran."""
    from optuna.storages._heartbeat import HeartbeatThread
    stopped = []
    for t in threading.enumerate():
        target, args = getattr(t, "_target", None), getattr(t, "_args", ())
        if target is HeartbeatThread._record_heartbeat and len(args) == 3 and hasattr(args[2], "set"):
            args[2].set()
            stopped.append(t)
    for t in stopped:
        t.join(wait)
    return len(stopped)


def exit_within(seconds: float, code: int) -> None:
    """After an interruption: if the interpreter's exit has not ended ``seconds`` from now (a thread or a pool's
    queue that some library left waiting), end the process with ``code`` anyway. Everything a run keeps is in
    the storage by then (the interrupted trial is marked failed before the message); only buffered output is
    left, and it is flushed first. A daemon timer: a normal exit ends it with the process."""
    def force():
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - a closed pipe
                pass
        os._exit(code)
    t = threading.Timer(seconds, force)
    t.daemon = True
    t.start()


def _user_error(e: ImtuneError, args, url: str | None) -> int:
    """One line, exit 2; an ImtuneError raised while an interrupt was being handled is the interruption."""
    from tuner.storage import interrupt_in_chain, scrub
    stop = interrupt_in_chain(e)
    if stop is not None:
        return _interrupted(stop, args)
    print(f"tune: error: {scrub(e, url)}", file=sys.stderr)
    return 2


def _unexpected(e: Exception, args, url: str | None) -> int:
    """An exception no command turned into an ImtuneError: an interruption Optuna masked (130 / 143), a storage
    that failed mid-run (one line, exit 2), else one "internal error" line (exit 1; the traceback, credentials
    masked, under IMTUNE_DEBUG=1)."""
    from tuner.storage import interrupt_in_chain, scrub, storage_fault
    # Optuna 5.1's _run_trial catches only Exception while it records a trial: a Ctrl-C / SIGTERM landing there
    # surfaces as UnboundLocalError('updated_state') from its `finally`, the interrupt as its context. It is an
    # interruption (exit 130 / 143), not a storage fault.
    stop = interrupt_in_chain(e)
    if stop is not None:
        return _interrupted(stop, args)
    if os.environ.get("IMTUNE_DEBUG"):  # the traceback, with the storage's credentials masked like every line
        import traceback
        lines = "".join(traceback.format_exception(e)).rstrip().splitlines()
        print("\n".join(scrub(line, url) if line.strip() else line for line in lines), file=sys.stderr)
        return 1
    # a storage that failed mid-run (full disk, server gone): the cause and what to do, exit 2
    fault = storage_fault(e, url, getattr(args, "studies_dir", None)) if hasattr(args, "storage") else None
    if fault:
        print(f"tune: error: {fault}", file=sys.stderr)
        return 2
    msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
    print(f"tune: internal error: {type(e).__name__}: {scrub(msg, url)} (set IMTUNE_DEBUG=1 for details)",
          file=sys.stderr)
    return 1


def _main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        ap = build_parser()  # imports the registries: a broken $IMTUNE_PLUGINS module is a one-line error
    except ImtuneError as e:
        print(f"tune: error: {e}", file=sys.stderr)
        return 2
    argv = route(argv, ap)
    if argv is None:  # bare `tune`: a short help, nothing started
        sys.stdout.write(short_help(ap))
        return 0
    args = ap.parse_args(argv)
    if not getattr(args, "func", None):
        ap.print_help()
        return 2
    # every message is scrubbed of credentials: exceptions from SQLAlchemy / psycopg2 may embed the URL or DSN
    from tuner.storage import quiet_thread_storage_faults
    if hasattr(args, "storage") and args.storage is None and os.environ.get(STORAGE_ENV, "").strip():
        args.storage = os.environ[STORAGE_ENV].strip()  # the connection string kept out of the command line
    url = getattr(args, "storage", None)
    if hasattr(args, "storage"):  # Optuna's heartbeat thread: its storage faults are reported once, below
        quiet_thread_storage_faults(url, getattr(args, "studies_dir", None))
    try:
        return int(args.func(args) or 0)
    except ImtuneError as e:
        return _user_error(e, args, url)
    except BrokenPipeError:  # `tune ... | head`: the reader left; nothing more to say
        try:
            sys.stdout = open(os.devnull, "w")
        except OSError:
            pass
        return 0
    except KeyboardInterrupt as e:
        return _interrupted(e, args)
    except Exception as e:  # never a traceback for users; IMTUNE_DEBUG=1 shows it
        return _unexpected(e, args, url)


if __name__ == "__main__":
    raise SystemExit(main())
