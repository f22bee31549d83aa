"""MkDocs hook (mkdocs.yml `hooks:`): pages generated at build time, so they cannot drift from their source.

- ``cli.md``: every `tune` command's options as tables (option, default, help) grouped as its parser groups them,
  read from the argparse parsers `tune` itself builds (``tuner.cli.build_parser``): a renamed option or a new
  command shows here on the next build.
- ``plugins.md``: the features, estimators, pre-filters and tasks registered in this build's registries, each
  with its registry description: a new estimator appears in the table by being registered.
- ``changelog.md`` and ``contributing.md``: CHANGELOG.md and CONTRIBUTING.md of the project root, as pages (their
  links into ``docs/`` made relative to the site).
"""

from __future__ import annotations

import argparse
import re
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


_DEFAULT = re.compile(r"\s*\((?:default[: ]|else )((?:[^()]|\([^()]*\))*)\)", re.I)  # "(default: x)", "(else y)"


def _md(text: str) -> str:
    """Plain help text as one Markdown table cell: `<family>` must not read as an HTML tag, `*` as emphasis."""
    return (re.sub(r"\s+", " ", text).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
            .replace("|", "\\|").replace("*", "\\*"))


def _option_row(action: argparse.Action, formatter: argparse.HelpFormatter) -> tuple[str, str, str]:
    """(option, default, help) of one argparse action, the default taken from where the help states it or else
    from the action, as `tune COMMAND -h` shows it."""
    names = ", ".join(action.option_strings) or action.metavar or action.dest
    if action.nargs != 0 and action.option_strings and action.choices is None:
        names += f" {formatter._metavar_formatter(action, action.dest.upper())(1)[0]}"
    helptext = formatter._expand_help(action) if action.help else ""
    default = ""
    m = _DEFAULT.search(helptext)
    if m:  # the help states its default in words: that is the default shown
        default = m.group(1).strip()
        default = default[1:].strip() if default.startswith(":") else default
        helptext = (helptext[:m.start()] + helptext[m.end():]).strip()
    elif action.default not in (None, argparse.SUPPRESS, []) and action.option_strings:
        d = action.default
        default = ("on" if d else "off") if isinstance(d, bool) else str(d)
    elif action.option_strings and action.nargs == 0 and action.const is True:
        default = "off"
    if action.required:
        default = "required"
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        choices = ", ".join(f"`{c}`" for c in action.choices)
        helptext = f"{helptext.rstrip('.; ')}; one of {choices}" if helptext else f"One of {choices}"
    opt = f"`{names}`"
    return opt, (f"`{default}`" if default and " " not in default and len(default) < 24 else _md(default)), \
        _md_keep_code(helptext)


def _md_keep_code(text: str) -> str:
    """_md outside `code spans`; inside them only the table pipe is escaped."""
    parts = text.split("`")
    return "`".join(_md(t) if i % 2 == 0 else t.replace("|", "\\|") for i, t in enumerate(parts)).strip()


def _synopsis(name: str, parser: argparse.ArgumentParser) -> str:
    pos = [a for a in parser._actions if not a.option_strings and not isinstance(a, argparse._SubParsersAction)]
    words = [name] + (["COMMAND"] if _subcommands(parser) else []) + [a.metavar or a.dest.upper() for a in pos]
    has_options = any(a.option_strings and a.help is not argparse.SUPPRESS and "-h" not in a.option_strings
                      for a in parser._actions)
    return " ".join(words + (["[OPTIONS]"] if has_options else []))


def command_section(path: list[str], parser: argparse.ArgumentParser) -> list[str]:
    """One command: its synopsis, what it does, its subcommands, then one table per option group of its parser
    (the groups `-h` shows: pipeline, data, study, ...), each row option | default | what it does."""
    name = " ".join(path)
    out = ["", f'## `{name}` {{ #{"-".join(path)} }}', ""]
    out += ["```text", _synopsis(name, parser), "```", ""]
    sub = _subcommands(parser)
    if parser.description:
        desc = parser.description.split("\n\n", 1)[0] if path == ["tune"] else parser.description
        out += [_md_keep_code(desc), ""]
    elif len(path) > 1:
        help_of = next((a.help for a in _parent_choices(path) if a.dest == path[-1]), None)
        if help_of:
            out += [_md_keep_code(help_of[0].upper() + help_of[1:]) + ".", ""]
    less = getattr(parser, "less_used", None)
    if less:
        out += [f"`{name} -h` describes the options most people set and only names the less used ones "
                f"({', '.join(f'`{o}`' for o in less)}); `{name} --help-all` describes them all, as the tables below "
                "do.", ""]
    if sub:
        out += ["| command | what it does |", "|---|---|"]
        helps = {a.dest: a.help for a in _choices_actions(parser)}
        out += [f"| [`{name} {c}`](#{'-'.join(path + [c])}) | {_md_keep_code(helps.get(c) or '')} |" for c in sub]
        out.append("")
    fmt = parser._get_formatter()
    for group in parser._action_groups:
        rows = [a for a in group._group_actions if a.help is not argparse.SUPPRESS
                and not isinstance(a, argparse._SubParsersAction) and "-h" not in a.option_strings]
        if not rows:
            continue
        title = group.title if group.title not in ("options", "optional arguments") else "options"
        out += [f"**{title}**", "", "| option | default | what it does |", "|---|---|---|"]
        out += ["| {} | {} | {} |".format(*_option_row(a, fmt)) for a in rows]
        out.append("")
    if path == ["tune"]:
        out += ["`tune` with an option first and no command runs `tune run` (the main job).", ""]
    if parser.epilog:
        out += [_md_keep_code(parser.epilog), ""]
    return out


_PARSERS: dict[tuple[str, ...], argparse.ArgumentParser] = {}


def _choices_actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return list(action._choices_actions)
    return []


def _parent_choices(path: list[str]) -> list[argparse.Action]:
    parent = _PARSERS.get(tuple(path[:-1]))
    return _choices_actions(parent) if parent is not None else []


def cli_reference() -> str:
    """Markdown: one section per command (`tune`, `tune run`, `tune data download`, ...), its options as tables
    (option, default, what it does) grouped as the parser groups them: what `tune COMMAND --help` prints."""
    from tuner.cli import build_parser

    top = build_parser()
    commands = list(_walk(top, ["tune"]))
    _PARSERS.clear()
    _PARSERS.update({tuple(p): ap for p, ap in commands})
    out = ["# CLI reference", "",
           "Every `tune` command with its options, generated from the parsers `tune` itself builds when this "
           "site is built: the same options, defaults and help as `tune COMMAND -h` prints (`tune run -h` describes "
           "the options most people set and names the others, which `tune run --help-all` describes). `tune` with "
           "an option first and no command runs `tune run` (the main job).", ""]
    out += [f"- [`{' '.join(p)}`](#{'-'.join(p)})" for p, _ in commands]
    for path, parser in commands:
        out += command_section(path, parser)
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
    for name in ("CHANGELOG.md", "CONTRIBUTING.md"):
        files.append(File.generated(config, name.lower(), content=root_page(name)))
    return files


def root_page(name: str) -> str:
    """A Markdown file of the project root as a site page: its links to ``docs/PAGE.md`` become ``PAGE.md``."""
    return re.sub(r"\]\(docs/", "](", (ROOT / name).read_text())
