"""Every `tune ...` command line quoted in README.md and docs/*.md parses with the real `tune` parser: its
subcommand exists, every option it names is one of that command's options (spelt out in full, no prefix), and
every option value given from a fixed set of choices is one of them. Parsing only, in-process: nothing runs.

Why not just append --help: argparse stops at --help before it rejects unknown options (those are collected and
refused at the end), so a renamed option would pass. Here the option names are checked against the parser's own
option strings, then the whole line is parsed with --help last, which runs argparse's value checks (choices,
types) on every option given before it."""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from tuner.cli import build_parser, route

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PLACEHOLDER = re.compile(r"^(\.\.\.|[A-Z][A-Z0-9_]*(\.\.)?)$")  # `...`, `NAME`, `STUDY_A`: words for the reader


def _lines_in(text: str) -> list[str]:
    """`tune` command lines: inline code spans and lines of code blocks (indented or fenced) starting with
    `tune ` (or `.venv/bin/tune `), with backslash continuations joined and `# comments` cut."""
    found = []
    code = re.sub(r"```.*?```", "", text, flags=re.S)
    for span in re.findall(r"`([^`\n]+)`", code):
        if re.match(r"(\.venv/bin/)?tune( |$)", span.strip()):
            found.append(span.strip())
    lines = text.split("\n")
    in_fence = False
    i = 0
    while i < len(lines):
        raw = lines[i]
        if raw.strip().startswith("```"):
            in_fence = not in_fence
        block = in_fence or raw.startswith("    ")
        s = raw.strip()
        m = re.search(r"(?:^|&& |\$ )((?:\.venv/bin/)?tune(?: .*|$))", s) if block else None
        if m:
            cmd = m.group(1)
            while cmd.endswith("\\") and i + 1 < len(lines):
                i += 1
                cmd = cmd[:-1] + " " + lines[i].strip()
            found.append(cmd)
        i += 1
    return found


def _argv(line: str) -> list[str]:
    line = re.sub(r"\s+#.*$", "", line)  # a trailing comment
    words = shlex.split(line)
    if words and words[0].endswith("tune"):
        words = words[1:]
    return words


def documented_commands() -> list[tuple[str, str]]:
    out = []
    for p in DOCS:
        for line in _lines_in(p.read_text()):
            out.append((p.name, line))
    return out


def _subparsers(ap: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for a in ap._actions:  # argparse has no public accessor for its subcommands
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


def check_line(argv: list[str], ap: argparse.ArgumentParser | None = None) -> list[str]:
    """Problems with one documented command line (empty: it parses)."""
    ap = ap or build_parser()
    routed = route(argv, ap)
    if not routed:  # bare `tune`: the short help
        return []
    problems = []
    parser, rest = ap, list(routed)
    # walk down the subcommands (`data download`)
    while rest and _subparsers(parser) and not rest[0].startswith("-"):
        subs = _subparsers(parser)
        if PLACEHOLDER.match(rest[0]):  # `tune COMMAND -h`
            return []
        if rest[0] not in subs:
            return [f"unknown command {rest[0]!r} (commands: {', '.join(subs)})"]
        parser, rest = subs[rest[0]], rest[1:]
    known = {s: a for a in parser._actions for s in a.option_strings}
    concrete = []
    i = 0
    while i < len(rest):
        w = rest[i]
        if w.startswith("-") and not re.match(r"^-\d", w):
            name, eq, val = w.partition("=")
            action = known.get(name)
            if action is None:
                problems.append(f"unknown option {name!r} of '{parser.prog}'")
                i += 1
                continue
            takes = action.nargs != 0
            if not takes or eq:
                concrete.append(w)
                i += 1
                continue
            # the value(s) that follow: each alternative of `a|b` checked against the choices
            vals_kept = []
            j = i + 1
            while j < len(rest) and not rest[j].startswith("-"):
                vals = rest[j].split("|") if action.choices is not None else [rest[j]]
                for v in vals:
                    if action.choices is not None and not PLACEHOLDER.match(v) and v not in action.choices:
                        problems.append(f"{name}: {v!r} is not one of {list(action.choices)}")
                if not PLACEHOLDER.match(vals[0]):
                    vals_kept.append(vals[0])
                j += 1
                if action.nargs in (None, "?") or isinstance(action.nargs, int) and j - i > action.nargs:
                    break
            if vals_kept:  # an option quoted without a value (`--jobs`), or with a placeholder: its name is checked
                concrete += [w] + vals_kept
            i = j
            continue
        elif not PLACEHOLDER.match(w):
            concrete.append(w.split("|")[0])
        i += 1
    if problems:
        return problems
    # the whole line through argparse with --help last: its value checks (choices, types) run on every option
    # given before --help; placeholders (`...`, `NAME`) were dropped where they are values of no fixed set
    line = routed[: len(routed) - len(rest)] + concrete + ["--help"]
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            ap.parse_args(line)
        except SystemExit as e:
            if e.code != 0:
                return [err.getvalue().strip() or f"exit {e.code}"]
        else:
            return ["--help did not exit"]
    return []


COMMANDS = documented_commands()


def test_docs_quote_commands():
    # the extraction finds the README's main job and a docs page's command: an empty list would pass vacuously
    lines = [c for _, c in COMMANDS]
    assert any(c.startswith("tune --feature sift --ransac degensac") for c in lines)
    assert any(c.startswith("tune data download") for c in lines)
    assert len(COMMANDS) > 40


@pytest.fixture(scope="module")
def parser():
    return build_parser()


@pytest.mark.parametrize("where,line", COMMANDS, ids=[f"{w}:{c[:60]}" for w, c in COMMANDS])
def test_documented_command_parses(where, line, parser):
    assert check_line(_argv(line), parser) == [], f"{where}: {line}"


def test_check_line_catches_a_renamed_option_and_a_bad_choice():
    ap = build_parser()
    assert check_line(["--feature", "sift", "--ransac", "degensac"], ap) == []
    assert check_line(["--feature", "sift", "--ransack", "degensac"], ap)  # an option that does not exist
    assert check_line(["evaluate", "--matcher", "flannn"], ap)  # a value not among the choices
    assert check_line(["data", "downlod", "strecha"], ap)  # a command that does not exist
    assert check_line(["run", "--sampler", "tpe|rnd"], ap)  # one alternative of several
