"""The `tune` command. A thin layer over documented Python calls; every error is one line on stderr
and a non-zero exit (set IMTUNE_DEBUG=1 for a traceback).

    tune --feature sift --ransac degensac          # tune on validation, freeze, run the test scenes
    tune evaluate --feature sift --ratio 0.85 ...  # one fixed configuration
    tune list                                      # every method and whether it runs here
    tune data download strecha
"""
from __future__ import annotations

import argparse
import os
import sys

from pipeline.errors import ImtuneError

# Subcommand modules: each has ``register(subparsers)`` that adds its parser with ``func=run``.
SUBCOMMAND_MODULES = ["tuner.commands.evaluate", "tuner.commands.listing", "tuner.commands.data",
                      "tuner.commands.viz"]
OPTIONAL_MODULES = ["tuner.commands.study"]  # the Optuna commands (run, calibrate, test, table, ...)
DEFAULT_SUBCOMMAND = "run"


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2 (argparse's own usage dump is noise here)
        sys.stderr.write(f"tune: error: {message}\n")
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    import importlib
    ap = _Parser(prog="tune", description="Tune and evaluate wide-baseline image matching (IMC protocol).")
    sub = ap.add_subparsers(dest="command", parser_class=_Parser)
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


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = build_parser()
    known = set(ap._subparsers._group_actions[0].choices) if ap._subparsers else set()
    if not argv or (argv[0] not in known and argv[0] not in ("-h", "--help")):
        if DEFAULT_SUBCOMMAND in known:
            argv = [DEFAULT_SUBCOMMAND] + argv
        elif not argv:
            ap.print_help()
            return 2
    args = ap.parse_args(argv)
    if not getattr(args, "func", None):
        ap.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except ImtuneError as e:
        print(f"tune: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("tune: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # never a traceback for users; IMTUNE_DEBUG=1 shows it
        if os.environ.get("IMTUNE_DEBUG"):
            raise
        msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
        print(f"tune: internal error: {type(e).__name__}: {msg} (set IMTUNE_DEBUG=1 for details)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
