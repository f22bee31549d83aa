"""The documentation fits the screen, reads in pieces a reader can take in, and quotes no figure typed in by hand.

Checked on the Markdown of README.md and docs/*.md with every `--8<--` include expanded, each problem reported as
``FILE:LINE: what is wrong: what to do`` (an included line names its benchmarks/results file and line):

- no paragraph or list item over 150 words;
- no table over 8 columns;
- no code-block line over 100 characters;
- **measured figures come from benchmarks/results/**: a docs page (docs/*.md) types no measured figure into its own
  text. What counts as one (the rule is a practical net, not a parser of meaning): a number with three or more
  decimals (an mAA, a score, a p-value, a coverage: 0.678, .4584), a run's duration in minutes or hours
  (15 min 52 s, 2 h 53 min), seconds other than the budget settings (46.2 s, 441 s), and a speed ratio (2.35 x),
  in prose, tables and output blocks; command lines are not checked (their numbers are settings). Such figures
  belong in a file under benchmarks/results/ that says the command, data and date of its run, and the page
  includes the file's section at build time. A few figures are no measurement of imtune (the paper's own
  numbers, a worked example computed by hand): FIGURE_EXCEPTIONS lists them, each with its reason. Not covered:
  percentages, figures with fewer than three decimals, and the README's prose (no site page, it cannot include a
  file: its quoted first run and main-job time are checked against their results files instead);
- each docs page opens, before its first `##` section, with what it is for and a command (a code block);
- a page that uses a term of the glossary (Gamma_max, the budget statistic, auc10, NF / NM / NI, flat region,
  one-se, paired pairs) links its glossary entry;
- every relative link of README.md names a file of the repository (a checkout has no generated pages);
- every `tune` command's help, and each `tune` command the docs quote that is cheap to run (list, data scenes,
  studies, table, results), prints no line over 100 characters on a 100-column terminal;
- the built site (the same build as the other docs tests) holds no table over 8 columns and no paragraph over
  150 words, generated pages (CLI reference, registries, changelog) included.
"""
from __future__ import annotations

import argparse
import fcntl
import html.parser
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [ROOT / "README.md", *DOCS]
SHARED_DATA = Path(os.environ.get("IMTUNE_SHARED", ROOT.parent / "shared")) / "data"

MAX_WORDS = 150
MAX_COLUMNS = 8
MAX_CODE = 100
MAX_TERMINAL = 100

# -- reading the Markdown with its includes ------------------------------------------------------------------

INCLUDE = re.compile(r'^\s*-+8<-+\s+"(?P<path>[^"]+?)(?::(?P<section>[A-Za-z][\w-]*))?"\s*$')
MARKER = re.compile(r"-+8<-+\s*\[(?P<end>start|end):(?P<name>[\w-]+)\]")


@dataclass(frozen=True)
class Line:
    where: str  # path relative to the project root
    n: int  # 1-based line number in that file
    text: str
    included: bool  # from a benchmarks/results file, through an include

    @property
    def at(self) -> str:
        return f"{self.where}:{self.n}"


def _rel(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def included(page: Line, path: str, section: str | None) -> list[Line]:
    """The lines an include brings in (its section's, or the whole file's), each naming its own file and line."""
    f = ROOT / path
    assert f.is_file(), f"{page.at}: includes {path}, which does not exist: fix the path or add the file"
    lines = f.read_text().splitlines()
    span = range(len(lines))
    if section:
        starts = [i for i, t in enumerate(lines) if (m := MARKER.search(t)) and m["end"] == "start"
                  and m["name"] == section]
        ends = [i for i, t in enumerate(lines) if (m := MARKER.search(t)) and m["end"] == "end"
                and m["name"] == section]
        assert starts and ends and ends[0] > starts[0], (
            f"{page.at}: includes section {section!r} of {path}, which has no <!-- --8<-- [start:{section}] --> ... "
            f"<!-- --8<-- [end:{section}] --> pair: add the markers")
        span = range(starts[0] + 1, ends[0])
    return [Line(_rel(f), i + 1, lines[i], True) for i in span if not MARKER.search(lines[i])]


def expand(path: Path) -> list[Line]:
    """A Markdown file's lines with its includes expanded (as pymdownx.snippets expands them in the build)."""
    out: list[Line] = []
    for n, text in enumerate(path.read_text().splitlines(), 1):
        m = INCLUDE.match(text)
        if m:
            out += included(Line(_rel(path), n, text, False), m["path"], m["section"])
        elif not MARKER.search(text):
            out.append(Line(_rel(path), n, text, False))
    return out


@dataclass
class Block:
    kind: str  # "paragraph", "item", "table", "code", "command" (a code block of command lines)
    lines: list[Line]


ITEM = re.compile(r"^\s*(?:[-*+]|\d+\.)\s+")
FENCE = re.compile(r"^\s*(```|~~~)")
COMMAND = re.compile(r"^\s*(?:\$ )?(?:\.venv/bin/)?(?:tune|python|bash|PYTHONPATH=|IMTUNE_\w+=|mkdir|printf|pip|"
                     r"cd|export|ln|git|\.ci/)\b")


def blocks(lines: list[Line]) -> list[Block]:
    """Paragraphs, list items, tables and code blocks (fenced, or indented by 4+ after a blank line)."""
    out: list[Block] = []
    cur: Block | None = None
    fence: str | None = None
    blank = True
    for ln in lines:
        t = ln.text
        if fence is not None:
            if t.strip().startswith(fence):
                fence, cur = None, None
            else:
                assert cur is not None
                cur.lines.append(ln)
            continue
        m = FENCE.match(t)
        if m:
            fence, cur = m.group(1), Block("code", [])
            out.append(cur)
            blank = False
            continue
        if not t.strip():
            blank = True
            if cur is not None and cur.kind != "code":
                cur = None
            continue
        if t.startswith("    ") and (blank and (cur is None or cur.kind == "code")) and not ITEM.match(t):
            if cur is None or cur.kind != "code":
                cur = Block("code", [])
                out.append(cur)
            cur.lines.append(ln)
            blank = False
            continue
        if cur is not None and cur.kind == "code" and not t.startswith("    "):
            cur = None
        blank = False
        if t.startswith("#") or t.startswith("!!!") or t.startswith(":::"):
            cur = None
            continue
        if t.lstrip().startswith("|"):
            if cur is None or cur.kind != "table":
                cur = Block("table", [])
                out.append(cur)
            cur.lines.append(ln)
            continue
        if ITEM.match(t):
            cur = Block("item", [ln])
            out.append(cur)
            continue
        if cur is None or cur.kind not in ("paragraph", "item"):
            cur = Block("paragraph", [])
            out.append(cur)
        cur.lines.append(ln)
    for b in out:
        if b.kind == "code" and b.lines and all(COMMAND.match(x.text) or x.text.strip().startswith("#")
                                                or not x.text.strip() or x.text.startswith("        ")
                                                for x in b.lines):
            b.kind = "command"
    return out


def words(text: str) -> int:
    text = re.sub(r"\]\([^)]*\)", "]", text)  # a link's target is no word the reader reads
    return len(text.split())


def table_columns(block: Block) -> int:
    """Columns of a Markdown table, counted on its delimiter row (`|---|--:|`), which holds no text."""
    for ln in block.lines:
        if re.match(r"^\s*\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$", ln.text):
            return len(re.findall(r"-{3,}", ln.text))
    return 0


# -- the checks (each returns its problems as "FILE:LINE: what: what to do") --------------------------------

def long_paragraphs(bs: list[Block]) -> list[str]:
    out = []
    for b in bs:
        if b.kind in ("paragraph", "item"):
            n = words(ITEM.sub("", " ".join(x.text for x in b.lines), count=1))
            if n > MAX_WORDS:
                out.append(f"{b.lines[0].at}: a {'list item' if b.kind == 'item' else 'paragraph'} of {n} words "
                           f"(at most {MAX_WORDS}): split it, or move the detail to a list or a table")
    return out


def wide_tables(bs: list[Block]) -> list[str]:
    out = []
    for b in bs:
        if b.kind == "table":
            n = table_columns(b)
            if n > MAX_COLUMNS:
                out.append(f"{b.lines[0].at}: a table of {n} columns (at most {MAX_COLUMNS}): split it in two "
                           "(repeating the first column) or transpose it")
    return out


def long_code_lines(bs: list[Block]) -> list[str]:
    out = []
    for b in bs:
        if b.kind not in ("code", "command"):
            continue
        texts = [x.text.expandtabs() for x in b.lines]
        indent = min((len(t) - len(t.lstrip()) for t in texts if t.strip()), default=0)
        for x, t in zip(b.lines, texts):
            if len(t) - indent > MAX_CODE:
                out.append(f"{x.at}: a code line of {len(t) - indent} characters (at most {MAX_CODE}): break a "
                           "command with ` \\` and an indented continuation, or shorten the comment")
    return out


# What a measured figure looks like (see the module docstring for what this covers and what it does not).
MEASURED = re.compile(
    r"(?<![\w.\-/])[-+]?\d*\.\d{3,}(?!\w|\.\d)"  # 0.678, .4584, 0.0490
    r"|\b\d+ ?h \d+ ?min\b|\b\d+(?:\.\d+)? ?min\b(?: \d+ ?s\b)?"  # 2 h 53 min, 15 min 52 s, 20 min
    r"|(?<![\w.])\d+(?:\.\d+)? ?s\b(?![\w/])"  # 46.2 s, 441 s (the budget settings are excepted below)
    r"|(?<![\w.])\d+\.\d+ ?x\b(?! ?\d)"  # 2.35 x, 1.68x
)
# the budget settings (B = 0.5 s on validation, 1 s on test, and the values the docs' examples set) and the
# protocol's fixed confidence: settings, not measurements
SETTINGS = re.compile(r"^(?:0\.1|0\.25|0\.5|1|2|5|10|30|60) ?s$|^0\.999999$")
# Figures a page may type by hand, none of them a measurement of imtune: (page, text on the line) -> why.
FIGURE_EXCEPTIONS: dict[tuple[str, str], str] = {
    ("protocol.md", "errors {1, 3} -> auc5 0.75, auc10 0.875, auc20 0.9375"):
        "a worked example of the AUC's definition, computed by hand (and checked by tests/test_metrics_auc.py)",
    ("statistics.md", "A - B = -0.1029 [-0.5247, +0.3189] (95%), p = 0.404"):
        "the form of a comparison's output, on synthetic scores the page says it used: no measurement",
    ("statistics.md", "A - B = -0.0057 [-0.0747, +0.0632] (95%), p = 0.82"):
        "the form of an inconclusive comparison's output, on synthetic scores the page says it used",
    ("statistics.md", "(synthetic scores: 30 pairs in 3 scenes, K = 3 per side, a tuning sd of 0.015"):
        "the settings of that synthetic example",
}


def handmade_figures(path: Path, bs: list[Block]) -> list[str]:
    out = []
    for b in bs:
        if b.kind == "command":
            continue
        for x in b.lines:
            if x.included:
                continue
            text = x.text
            if b.kind == "code" and COMMAND.match(text):
                continue
            if any(page == path.name and s in text for page, s in FIGURE_EXCEPTIONS):
                continue
            found = [m.group(0) for m in MEASURED.finditer(text) if not SETTINGS.match(m.group(0).strip())]
            if found:
                out.append(f"{x.at}: measured figure(s) typed into the page ({', '.join(found[:4])}): write them to "
                           "a file under benchmarks/results/ with the command, data and date of the run, and include "
                           'its section (--8<-- "benchmarks/results/FILE.md:SECTION"), or drop them')
    return out


def opening(path: Path, bs: list[Block], lines: list[Line]) -> list[str]:
    """The page's text before its first `##` holds a sentence and a code block (what it is for; the command)."""
    head = []
    for ln in lines:
        if ln.text.startswith("## ") and not ln.included:
            break
        head.append(ln)
    hb = blocks(head)
    kinds = {b.kind for b in hb}
    problems = []
    if not kinds & {"paragraph", "item"}:
        problems.append("no sentence saying what the reader can do with it")
    if not kinds & {"code", "command"}:
        problems.append("no command (a code block)")
    return [f"{_rel(path)}:1: the page's opening, before its first `##`, has {' and '.join(problems)}: open with "
            "what the reader can do with this page and the one command that does it"] if problems else []


# term as the pages write it -> its entry in docs/glossary.md
GLOSSARY = {
    r"\bGamma_max\b": "gamma_max",
    r"\bbudget statistic\b": "budget-statistic",
    r"\bauc10\b": "auc10",
    r"\bN[FMI]\b": "nf-nm-ni",
    r"\bflat region\b": "flat-region",
    r"\bone-se\b": "one-se",
    r"\bpaired pairs\b": "paired-pairs",
}
NOT_GLOSSED = {"glossary.md"}


def unlinked_terms(path: Path, bs: list[Block]) -> list[str]:
    """Terms of the prose (code blocks and included results name fields, not terms); a link anywhere on the page
    counts."""
    if path.parent != ROOT / "docs" or path.name in NOT_GLOSSED:
        return []
    own = [x for b in bs if b.kind not in ("code", "command") for x in b.lines if not x.included]
    text = "\n".join(x.text for x in own)
    out = []
    for term, anchor in GLOSSARY.items():
        first = next((x for x in own if re.search(term, x.text)), None)
        if first is not None and f"glossary.md#{anchor})" not in text:
            used = re.search(term, first.text).group(0)  # type: ignore[union-attr]
            out.append(f"{first.at}: uses {used!r} without linking its definition: link it once, e.g. "
                       f"[{used}](glossary.md#{anchor})")
    return out


def checks(path: Path) -> list[str]:
    lines = expand(path)
    bs = blocks(lines)
    out = long_paragraphs(bs) + wide_tables(bs) + long_code_lines(bs)
    if path.parent == ROOT / "docs":
        out += handmade_figures(path, bs) + opening(path, bs, lines) + unlinked_terms(path, bs)
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_page_style(page):
    problems = checks(page)
    assert not problems, "\n" + "\n".join(problems)


# -- the checks can fail ------------------------------------------------------------------------------------

def _check_text(tmp_path, text: str, name: str = "page.md") -> list[str]:
    d = tmp_path / "docs"
    d.mkdir(exist_ok=True)
    p = d / name
    p.write_text(text)
    global ROOT
    saved = ROOT
    ROOT = tmp_path  # the page lives in this docs/ folder
    try:
        return checks(p)
    finally:
        ROOT = saved


OPENING = "# A page\n\nWhat it does.\n\n    tune list\n\n"


def test_the_checks_find_what_they_look_for(tmp_path):
    assert _check_text(tmp_path, OPENING + "## Section\n\nShort.\n") == []
    wall = OPENING + "## S\n\n" + " ".join(["word"] * 151) + "\n"
    assert any("paragraph of 151 words" in p and "page.md:9" in p for p in _check_text(tmp_path, wall))
    item = OPENING + "## S\n\n- " + " ".join(["word"] * 160) + "\n"
    assert any("list item of 160 words" in p for p in _check_text(tmp_path, item))
    wide = OPENING + "## S\n\n| " + " | ".join("abcdefghi") + " |\n|" + "---|" * 9 + "\n"
    assert any("table of 9 columns" in p and "page.md:9" in p for p in _check_text(tmp_path, wide))
    code = OPENING + "## S\n\n```text\n" + "x" * 101 + "\n```\n"
    assert any("code line of 101 characters" in p and "page.md:10" in p for p in _check_text(tmp_path, code))
    indented = OPENING + "## S\n\nText:\n\n    tune evaluate " + "--x " * 30 + "\n"
    assert any("code line of" in p for p in _check_text(tmp_path, indented))
    for fig in ("mAA(10) 0.678 on test", "it took 15 min 52 s", "mapping 46.2 s", "2.35 x faster", "p = .4584"):
        found = _check_text(tmp_path, OPENING + f"## S\n\nHere {fig}.\n")
        assert any("measured figure" in p for p in found), fig
    for setting in ("a budget of 0.5 s per pair", "confidence 0.999999", "r 0.85, eta 0.5 px", "8k x 8k"):
        assert _check_text(tmp_path, OPENING + f"## S\n\nWith {setting}.\n") == [], setting
    assert any("opening" in p for p in _check_text(tmp_path, "# A page\n\nText only.\n\n## S\n\nMore.\n"))
    assert any("glossary.md#gamma_max" in p for p in _check_text(tmp_path, OPENING + "Gamma_max is 5.\n"))
    assert _check_text(tmp_path, OPENING + "[Gamma_max](glossary.md#gamma_max) is 5.\n") == []


def test_an_included_figure_passes_and_names_its_own_file(tmp_path):
    res = tmp_path / "benchmarks" / "results"
    res.mkdir(parents=True)
    (res / "run.md").write_text("# Run\n\nnot included 0.111\n<!-- --8<-- [start:t] -->\nIt took 15 min 52 s (`tune`, "
                                "5 December 2026). " + " ".join(["w"] * 150) + "\n<!-- --8<-- [end:t] -->\n")
    page = OPENING + '## S\n\n--8<-- "benchmarks/results/run.md:t"\n'
    found = _check_text(tmp_path, page)
    assert len(found) == 1 and found[0].startswith("benchmarks/results/run.md:5: a paragraph of"), found
    with pytest.raises(AssertionError, match="no <!-- --8<-- \\[start:u\\]"):
        _check_text(tmp_path, OPENING + '## S\n\n--8<-- "benchmarks/results/run.md:u"\n')


# -- links of the README in a checkout -------------------------------------------------------------------------

def test_readme_links_name_files_of_the_repository():
    text = re.sub(r"```.*?```", "", (ROOT / "README.md").read_text(), flags=re.S)
    links = [x for x in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"[a-z]+://|#|mailto:", x)]
    assert len(links) >= 10, links
    dead = [x for x in links if not (ROOT / x.partition("#")[0]).exists()]
    assert not dead, f"README.md links to files a checkout does not have: {dead} (a generated page: link the " \
                     "built site's address instead)"


# -- the terminal -------------------------------------------------------------------------------------------------

def _parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    from tuner.cli import build_parser
    todo, out = [("tune", build_parser())], []
    while todo:
        name, p = todo.pop(0)
        out.append((name, p))
        for a in p._actions:  # argparse has no public accessor for its subcommands
            if isinstance(a, argparse._SubParsersAction):
                todo += [(f"{name} {k}", sp) for k, sp in a.choices.items()]
    return out


def test_every_help_fits_100_columns(monkeypatch):
    """`tune`, `tune --help` and every command's `-h` and `--help-all`, formatted for a 100-column terminal."""
    monkeypatch.setenv("COLUMNS", str(MAX_TERMINAL))
    from tuner.cli import build_parser, short_help
    texts = {"tune": short_help(build_parser())}
    for name, p in _parsers():
        texts[f"{name} -h"] = p.format_help()
        if getattr(p, "less_used", None):
            texts[f"{name} --help-all"] = p.format_help(full=True)  # type: ignore[call-arg]
    assert len(texts) > 15
    wide = [f"`{k}`: {len(ln)} characters: {ln[:60]}..." for k, t in texts.items() for ln in t.splitlines()
            if len(ln) > MAX_TERMINAL]
    assert not wide, "\n".join(wide)


def on_terminal(argv: list[str], env: dict[str, str], columns: int = MAX_TERMINAL) -> tuple[int, list[str]]:
    """Run `tune ARGV` with its standard output on a pseudo-terminal `columns` wide (a terminal, as a user sees it:
    prose is wrapped only on one); its exit code and output lines. Standard error is not read: an error or a
    warning is one line by the project's rule, however long."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "tuner", *argv], stdout=slave, stderr=subprocess.DEVNULL,
                            stdin=subprocess.DEVNULL, cwd=ROOT, env=env, close_fds=True)
    os.close(slave)
    chunks = []
    try:
        while True:
            r, _, _ = select.select([master], [], [], 300)
            if not r:
                proc.kill()
                raise AssertionError(f"tune {' '.join(argv)}: no output for 300 s")
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the child closed the terminal
                break
            if not data:
                break
            chunks.append(data)
    finally:
        os.close(master)
    code = proc.wait(timeout=60)
    text = b"".join(chunks).decode(errors="replace").replace("\r\n", "\n")
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]|\r[^\n]*(?=\r)", "", text)  # colour codes; progress bars redrawn in place
    return code, [ln.split("\r")[-1] for ln in text.split("\n")]


# Commands that only read what is there. `studies`, `table` and `results` need a storage of tested studies (their
# tables are checked on recorded studies in test_docs_site); `--json` is for programs and `list --long` prints
# every note whole on purpose.
CHEAP = (("list",), ("data", "scenes"))
NOT_FOR_A_TERMINAL = ("--json", "--long")


def quoted_cheap_commands() -> list[list[str]]:
    """The `tune` command lines the docs quote that only read (list, data scenes), as argv, and the scenes of the
    IMC dataset beside the project."""
    from tests.test_docs_commands import COMMANDS, PLACEHOLDER, _argv
    seen: dict[tuple[str, ...], None] = {}
    for _, line in COMMANDS:
        argv = _argv(line)
        if any(PLACEHOLDER.match(w) or "|" in w or "..." in w or w in NOT_FOR_A_TERMINAL for w in argv):
            continue
        if any(tuple(argv[:len(c)]) == c for c in CHEAP) and not any(w in ("-h", "--help", "--help-all")
                                                                       for w in argv):
            seen[tuple(argv)] = None
    seen[("data", "scenes", "--data", str(SHARED_DATA / "imc2025"))] = None
    return [list(a) for a in seen]


def test_the_docs_quote_cheap_commands():
    cmds = quoted_cheap_commands()
    assert any(c[:2] == ["data", "scenes"] for c in cmds) and any(c[:1] == ["list"] for c in cmds), cmds


@pytest.mark.parametrize("argv", quoted_cheap_commands(), ids=lambda a: " ".join(a)[:60])
def test_quoted_command_fits_100_columns(argv, tmp_path):
    if "--data" in argv and not Path(argv[argv.index("--data") + 1]).exists():
        pytest.skip(f"{argv[argv.index('--data') + 1]} is absent (the shared data beside the project)")
    env = dict(os.environ, PYTHONPATH=str(ROOT), COLUMNS=str(MAX_TERMINAL), IMTUNE_STUDIES=str(tmp_path / "studies"),
               IMTUNE_JOBS="1")
    code, lines = on_terminal(argv, env)
    assert code == 0, "\n".join(lines[-20:])
    wide = [f"{len(ln)}: {ln}" for ln in lines if len(ln) > MAX_TERMINAL]
    assert not wide, f"`tune {' '.join(argv)}` on a {MAX_TERMINAL}-column terminal:\n" + "\n".join(wide)


def test_the_terminal_check_sees_a_long_line():
    """The pseudo-terminal is real: a line longer than its width comes back whole (nothing wraps it for us), and
    the output is a terminal's (`tune list` prints its table)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    code, lines = on_terminal(["list", "--long"], env)
    assert code == 0 and any(ln.startswith("| family") for ln in lines), lines[:5]
    assert any(len(ln) > MAX_TERMINAL for ln in lines), "tune list --long prints every note whole"


# -- the built site ------------------------------------------------------------------------------------------------

class _SiteText(html.parser.HTMLParser):
    """Per page: the header cells of each table and the words of each paragraph of the content column."""

    def __init__(self):
        super().__init__()
        self.tables: list[int] = []
        self.paragraphs: list[str] = []
        self._in_p = 0
        self._p: list[str] = []
        self._row = 0
        self._cells = 0
        self._depth_content = 0

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self._row, self._cells = 0, 0
        elif tag == "tr":
            self._row += 1
        elif tag in ("th", "td") and self._row == 1:
            self._cells += 1
        elif tag == "p":
            self._in_p += 1
            self._p = []

    def handle_endtag(self, tag):
        if tag == "tr" and self._row == 1:
            self.tables.append(self._cells)
        elif tag == "p" and self._in_p:
            self._in_p -= 1
            self.paragraphs.append(" ".join("".join(self._p).split()))

    def handle_data(self, data):
        if self._in_p:
            self._p.append(data)


def test_the_built_site_has_no_wide_table_or_long_paragraph(docs_build):
    r, site = docs_build
    assert r.returncode == 0, r.stderr[-3000:]
    pages = sorted(p for p in site.rglob("index.html") if "search" not in p.parts)
    assert len(pages) >= 14
    bad = []
    for page in pages:
        text = page.read_text()
        content = text.split('class="md-content"', 1)[-1]
        parser = _SiteText()
        parser.feed(content)
        name = str(page.relative_to(site))
        bad += [f"{name}: a table of {n} columns (at most {MAX_COLUMNS})" for n in parser.tables if n > MAX_COLUMNS]
        bad += [f"{name}: a paragraph of {len(p.split())} words (at most {MAX_WORDS}): {p[:80]}..."
                for p in parser.paragraphs if len(p.split()) > MAX_WORDS]
    assert not bad, "\n".join(bad)


def test_the_readme_quotes_the_first_run_as_its_results_file_records_it():
    """The README is no site page and cannot include a file: the first run's transcript it quotes must be the one
    benchmarks/results/first-run.md records (and the site includes), so that a re-measured run is one edit of the
    results file, copied here, and never two different runs."""
    def transcript(text: str) -> str:
        m = re.search(r"```text\n(study .*?)```", text, flags=re.S)
        assert m, "no first-run transcript (```text block starting with 'study ')"
        return m.group(1)
    readme = transcript((ROOT / "README.md").read_text())
    recorded = transcript((ROOT / "benchmarks" / "results" / "first-run.md").read_text())
    assert readme == recorded, "README.md's first-run transcript differs from benchmarks/results/first-run.md's"


def test_the_readme_gives_the_main_jobs_time_its_results_file_records():
    """The main job's measured time in the README is the one benchmarks/results/main-job.md records (the site
    includes that file): re-measured, both change together."""
    section = (ROOT / "README.md").read_text().split("## The main job", 1)[1].split("\n## ", 1)[0]
    m = re.search(r"took \*\*([^*]+)\*\*", section)
    assert m, "README's main-job section gives no 'took **TIME**'"
    recorded = (ROOT / "benchmarks" / "results" / "main-job.md").read_text()
    assert f"**{m.group(1)}**" in recorded, (m.group(1), "not in benchmarks/results/main-job.md")
