"""MkDocs hook (mkdocs.yml `hooks:`): pages generated at build time, so they cannot drift from their source.

- ``cli.md``: every `tune` command's usage and options, rendered from the argparse parsers `tune` itself builds
  (``tuner.cli.build_parser``): a renamed option or a new command shows here on the next build.
- ``changelog.md``: CHANGELOG.md of the project root, as a page.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parent.parent


def _subcommands(ap: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser's subcommands in their registration order (empty when it has none)."""
    for action in ap._actions:  # argparse keeps no public accessor for its subparsers
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _walk(ap: argparse.ArgumentParser, path: list[str]):
    yield path, ap
    for name, sub in _subcommands(ap).items():
        yield from _walk(sub, path + [name])


def cli_reference() -> str:
    """Markdown: one section per command (`tune`, `tune run`, `tune data download`, ...), each its `--help`."""
    os.environ.setdefault("COLUMNS", "110")  # argparse wraps help text to $COLUMNS
    from tuner.cli import build_parser

    top = build_parser()
    commands = list(_walk(top, ["tune"]))
    out = ["# CLI reference", "",
           "Generated at build time from the argparse parsers `tune` builds (`tuner.cli.build_parser`): what "
           "`tune COMMAND --help` prints, for every command. `tune` with an option first and no command runs "
           "`tune run` (the main job).", ""]
    out += [f"- [`{' '.join(p)}`](#{'-'.join(p)})" for p, _ in commands]
    for path, parser in commands:
        name = " ".join(path)
        out += ["", f'## `{name}` {{ #{"-".join(path)} }}', "", "```text", parser.format_help().rstrip(), "```"]
    return "\n".join(out) + "\n"


def on_files(files, config):
    files.append(File.generated(config, "cli.md", content=cli_reference()))
    files.append(File.generated(config, "changelog.md", content=(ROOT / "CHANGELOG.md").read_text()))
    return files
