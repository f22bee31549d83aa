"""MkDocs hook (mkdocs.yml `hooks:`): pages generated at build time, so they cannot drift from their source.

- ``cli.md``: every `tune` command's usage and options, rendered from the argparse parsers `tune` itself builds
  (``tuner.cli.build_parser``): a renamed option or a new command shows here on the next build.
- ``plugins.md``: the features, estimators, pre-filters and tasks registered in this build's registries, each
  with its registry description: a new estimator appears in the table by being registered.
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


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def registry_tables() -> str:
    """Markdown: one table per registry (name, description), in registration order."""
    import pipeline.geometry  # noqa: F401  (importing a family registers its members)
    import pipeline.tasks  # noqa: F401
    from pipeline.features.registry import EXTRACTORS
    from pipeline.geometry.registry import ESTIMATORS
    from pipeline.matching.prefilters import PREFILTERS
    from pipeline.tasks import TASKS

    out = ["# Features, estimators, pre-filters and tasks", "",
           "Generated at build time from imtune's registries (`pipeline.registry.Registry`): everything a "
           "`--feature`, `--ransac`, `--prefilter` or `--task` accepts by name, with its registry description. "
           "`tune list` prints the same and says whether each runs on your machine (an optional library may be "
           "missing). Composed feature names (`det+aff+desc`) and `custom:DIR` are resolved on top of these: see "
           "[Extending](extending.md).", ""]
    for title, option, reg in (("Estimators", "--ransac", ESTIMATORS), ("Features", "--feature", EXTRACTORS),
                               ("Pre-filters", "--prefilter", PREFILTERS), ("Tasks", "--task", TASKS)):
        out += [f"## {title} (`{option}`)", "", "| name | what it is |", "|---|---|"]
        out += [f"| `{n}` | {_cell(reg.description(n))} |" for n in reg.names()]
        out.append("")
    return "\n".join(out)


def on_files(files, config):
    files.append(File.generated(config, "cli.md", content=cli_reference()))
    files.append(File.generated(config, "plugins.md", content=registry_tables()))
    files.append(File.generated(config, "changelog.md", content=(ROOT / "CHANGELOG.md").read_text()))
    return files
