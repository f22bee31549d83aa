"""The documentation reads as a product, not a lab notebook, and keeps doing so.

The site is built once (`mkdocs build --strict`, the venv's mkdocs) and then

- opened in headless Chromium at 1400 px (the Debian chromium + chromedriver the dashboard test drives): no code
  block or table of the CLI reference is wider than its column (nothing cut off on the right), no code block of
  any page is (the 100-column terminal output the pages quote fits), and no page has a
  paragraph holding a line that starts with "- " or "| " (a list or a table that Markdown did not render, for want
  of a blank line before it);
- checked for every link of README.md: each one that is not an outside address resolves to a page (and anchor) of
  the built site.

Without the site: no docs page, the README or CONTRIBUTING carries a working-log name (h31, h32rep, ...), this
project's own issue numbers, `notes/` or the other workshop phrases; the user's pages name no source file meant
for developers; README's code blocks have no line over 120 characters; `tune list` fits 100 columns; lists in the
Markdown sources have their blank line.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tests.test_dashboard_browser import CHROMEDRIVER, CHROMIUM, NEEDS_BROWSER

ROOT = Path(__file__).resolve().parent.parent
DOCS = sorted((ROOT / "docs").glob("*.md"))
# pages another change rewrites for a reader (the statistics page, being rewritten with the statistics)
OWNED_ELSEWHERE: set[str] = set()
PAGES = [p for p in DOCS if p.name not in OWNED_ELSEWHERE] + [ROOT / "README.md", ROOT / "CONTRIBUTING.md"]
# the pages a user reads to use imtune (extending, the Python API and CONTRIBUTING are for developers: they may
# name modules and files)
USER_PAGES = [ROOT / "README.md"] + [ROOT / "docs" / f"{n}.md" for n in (
    "index", "getting-started", "protocol", "data", "tuning", "budgets", "reports", "findings", "benchmarks")]
SITE_WIDTH = 1400


# -- the built site -----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def site(docs_build) -> Path:
    r, out = docs_build  # built once for every docs test (tests/conftest.py)
    assert r.returncode == 0, r.stderr[-3000:]
    return out


def site_pages(site: Path) -> list[Path]:
    return sorted(p for p in site.rglob("index.html") if "assets" not in p.parts and "search" not in p.parts)


def readme_links() -> list[str]:
    text = (ROOT / "README.md").read_text()
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    return re.findall(r"\]\(([^)\s]+)\)", text)


def site_target(link: str, site: Path) -> tuple[Path, str]:
    """The file of the built site a README link names, and its anchor ("" for none). A link into docs/ maps to
    its page (docs/data.md -> data/index.html), an asset to its copy; CHANGELOG.md and CONTRIBUTING.md are pages
    of the site too. Anything else is not in the site: an AssertionError."""
    path, _, anchor = link.partition("#")
    if path in ("CHANGELOG.md", "CONTRIBUTING.md"):
        return site / path[:-3].lower() / "index.html", anchor
    assert path.startswith("docs/"), f"README link {link!r} points outside the site"
    rel = path[len("docs/"):]
    if rel.endswith(".md"):
        page = rel[:-3]
        return (site / "index.html" if page == "index" else site / page / "index.html"), anchor
    return site / rel, anchor


def test_every_readme_link_resolves_in_the_built_site(site):
    links = [ln for ln in readme_links() if not re.match(r"https?://", ln)]
    assert len(links) >= 10, links  # the README links its pages: an empty list would pass vacuously
    missing = []
    for link in links:
        target, anchor = site_target(link, site)
        if not target.is_file():
            missing.append(f"{link} -> {target.relative_to(site)} (no such file)")
        elif anchor and f'id="{anchor}"' not in target.read_text():
            missing.append(f"{link} -> no id {anchor!r} in {target.relative_to(site)}")
    assert not missing, missing
    # the generated pages (the CLI reference and the registries) have no file in a checkout: the README links them
    # by the served site's address, and the built site has them there
    served = [ln for ln in readme_links() if ln.startswith("http://127.0.0.1:8000/")]
    assert {"http://127.0.0.1:8000/cli/", "http://127.0.0.1:8000/plugins/"} <= set(served), served
    for ln in served:
        assert (site / ln[len("http://127.0.0.1:8000/"):] / "index.html").is_file(), ln


def test_site_target_refuses_a_link_outside_the_site(site):
    with pytest.raises(AssertionError):
        site_target("notes/h31.md", site)
    target, anchor = site_target("docs/budgets.md#calibration", site)
    assert target == site / "budgets" / "index.html" and anchor == "calibration"


def test_the_cli_reference_shows_options_as_tables(site):
    page = (site / "cli" / "index.html").read_text()
    assert page.count("<table>") > 20, "one table per option group of every command"
    run = page.split('id="tune-run"', 1)[1].split('id="tune-calibrate"', 1)[0]
    for s in ("<code>--test-runs", "test runs of the frozen settings", "<code>--num-features NUM_FEATURES</code>",
              "<code>8000</code>"):
        assert s in run, s


# -- in the browser ---------------------------------------------------------------------------------------------

OVERFLOW_JS = """
const main = document.querySelector('.md-content') || document.body;
const out = [];
for (const el of main.querySelectorAll(arguments[0] || 'pre, table')) {
  // a table sits in Material's scroll wrapper: what matters is whether the wrapper has to scroll
  const box = el.tagName === 'TABLE' ? (el.closest('.md-typeset__scrollwrap') || el.parentElement) : el;
  if (box.scrollWidth > box.clientWidth + 1) {
    out.push(el.tagName + ' ' + box.scrollWidth + ' > ' + box.clientWidth + ': ' + el.innerText.slice(0, 80));
  }
}
return out;
"""

PARAGRAPH_JS = """
const out = [];
for (const p of document.querySelectorAll('.md-content p')) {
  for (const line of p.textContent.split('\\n')) {
    const t = line.trim();
    if (t.startsWith('- ') || t.startsWith('| ')) { out.push(t.slice(0, 100)); }
  }
}
return out;
"""


@pytest.fixture(scope="module")
def browser():
    if not (CHROMIUM and CHROMEDRIVER):
        pytest.skip("chromium and chromedriver not installed (Debian packages chromium, chromium-driver)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    opts = webdriver.ChromeOptions()
    profile = tempfile.mkdtemp(prefix="imtune-docs-chromium-")
    for a in ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
              "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
              f"--window-size={SITE_WIDTH},1000", f"--user-data-dir={profile}"):
        opts.add_argument(a)
    opts.binary_location = CHROMIUM
    drv = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    drv.set_page_load_timeout(60)
    try:
        yield drv
    finally:
        drv.quit()


@NEEDS_BROWSER
def test_no_code_block_or_table_of_the_cli_reference_overflows_at_1400px(site, browser):
    browser.get((site / "cli" / "index.html").as_uri())
    assert browser.execute_script("return window.innerWidth") >= SITE_WIDTH - 20
    n = browser.execute_script("return document.querySelectorAll('.md-content pre, .md-content table').length")
    assert n > 20, n  # the page has its tables: an empty page would pass
    assert browser.execute_script(OVERFLOW_JS) == []


@NEEDS_BROWSER
def test_no_code_block_or_table_of_any_page_overflows_at_1400px(site, browser):
    """The pages quote 100-column terminal output: the content column is as wide as the window (a stylesheet;
    Material's default fitted ~82 characters), so no code block scrolls; tables have at most 8 columns
    (tests/test_docs_style.py), so none scrolls either."""
    bad = {}
    for page in site_pages(site):
        browser.get(page.as_uri())
        found = browser.execute_script(OVERFLOW_JS, "pre, table")
        if found:
            bad[str(page.relative_to(site))] = found
    assert not bad, bad


@NEEDS_BROWSER
def test_the_overflow_check_sees_a_wide_code_block(tmp_path, browser):
    """The check above can fail: a page with a 300-character line in a code block overflows."""
    page = tmp_path / "wide.html"
    page.write_text('<html><body><div class="md-content" style="width:600px"><pre style="overflow:auto">'
                    + "x" * 300 + "</pre></div></body></html>")
    browser.get(page.as_uri())
    assert len(browser.execute_script(OVERFLOW_JS)) == 1


@NEEDS_BROWSER
def test_no_page_has_a_list_or_table_rendered_as_a_paragraph(site, browser):
    bad = {}
    pages = site_pages(site)
    assert len(pages) >= 14, pages
    for page in pages:
        browser.get(page.as_uri())
        found = browser.execute_script(PARAGRAPH_JS)
        if found:
            bad[str(page.relative_to(site))] = found
    for name in OWNED_ELSEWHERE:  # rewritten by another change
        bad.pop(f"{name[:-3]}/index.html", None)
    assert not bad, bad


@NEEDS_BROWSER
def test_the_paragraph_check_sees_a_list_without_its_blank_line(tmp_path, browser):
    page = tmp_path / "p.html"
    page.write_text('<html><body><div class="md-content"><p>Measured:\n- one\n- two</p></div></body></html>')
    browser.get(page.as_uri())
    assert browser.execute_script(PARAGRAPH_JS) == ["- one", "- two"]


# -- the Markdown sources ----------------------------------------------------------------------------------------

WORKSHOP = [
    (re.compile(r"\bh3\d[a-z]*\b"), "a working-log name"),
    (re.compile(r"\bnotes/"), "the working log's folder"),
    (re.compile(r"<abs path"), "a placeholder of the workshop"),
    (re.compile(r"machine kind"), "the workshop's name for its machines"),
    (re.compile(r"the issue's|issue's check"), "this project's issue tracker"),
    (re.compile(r"three scenes of before"), "a working-log phrase"),
]
# an issue number is fine when it is an upstream project's (Optuna issues 820, optuna-dashboard issue 545, ...)
UPSTREAM = re.compile(r"(optuna|dashboard|colmap|kornia|pydegensac|opencv|glue-factory|poselib|benchmark's|its|"
                      r"github\.com)[^.]{0,40}$", re.I)
ISSUE = re.compile(r"\b(issues?|PR|pull request)\s+#?\d+", re.I)


def workshop_words(text: str) -> list[str]:
    found = [f"{why}: {m.group(0)!r}" for pat, why in WORKSHOP for m in pat.finditer(text)]
    for m in ISSUE.finditer(text):
        if not UPSTREAM.search(text[max(0, m.start() - 60):m.start()]):
            found.append(f"this project's issue number: {m.group(0)!r}")
    return found


def test_the_workshop_check_finds_what_it_looks_for():
    assert workshop_words("Gamma_max (issue 31).")
    assert workshop_words("see notes/h32data.md")
    assert workshop_words("set TORCH_HOME=<abs path to shared>/weights")
    assert not workshop_words("SQLite 'database is locked' (Optuna issues 820, 4994, optuna-dashboard 545)")
    assert not workshop_words("the official benchmark's multiview step (its issue 49)")


def generated_pages() -> dict[str, str]:
    sys.path.insert(0, str(ROOT / "docs_hooks"))
    try:
        import generated_pages as g
    finally:
        sys.path.pop(0)
    return {"cli.md": g.cli_reference(), "plugins.md": g.registry_tables(),
            "contributing.md": g.root_page("CONTRIBUTING.md")}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_page_carries_workshop_words(page):
    assert workshop_words(page.read_text()) == []


def test_generated_pages_carry_no_workshop_words():
    for name, text in generated_pages().items():
        assert workshop_words(text) == [], name


@pytest.mark.parametrize("page", USER_PAGES, ids=lambda p: p.name)
def test_user_pages_name_no_source_file(page):
    text = page.read_text()
    found = re.findall(r"\b(?:tuner|pipeline|docs_hooks)/[\w/]*\.py\b", text)
    assert found == [], found


def list_without_blank_line(text: str) -> list[str]:
    """Lines starting a list item or a table row right after a paragraph line (Markdown then folds them into the
    paragraph), outside code blocks."""
    out, fence, prev = [], False, ""
    item = re.compile(r"^\s*([-*+]|\d+\.) ")
    for line in text.splitlines():
        if line.strip().startswith("```"):
            fence = not fence
        elif not fence and (item.match(line) or line.startswith("|")):
            if prev.strip() and not (item.match(prev) or prev.startswith(("|", "#", " ", "\t"))):
                out.append(line)
        prev = "" if fence else line
    return out


def test_the_list_check_sees_a_list_without_its_blank_line():
    assert list_without_blank_line("Measured:\n- one\n- two\n") == ["- one"]
    assert list_without_blank_line("Measured:\n\n- one\n- two\n\n| a |\n|---|\n") == []


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_lists_and_tables_have_their_blank_line(page):
    assert list_without_blank_line(page.read_text()) == []


def readme_code_lines() -> list[str]:
    text = (ROOT / "README.md").read_text()
    lines, fence = [], False
    for line in text.splitlines():
        if line.strip().startswith("```"):
            fence = not fence
            continue
        if fence or line.startswith("    "):
            lines.append(line)
    return lines


def test_readme_code_blocks_fit_120_columns():
    lines = readme_code_lines()
    assert len(lines) > 20, "the README quotes commands and a run's output"
    wide = [ln for ln in lines if len(ln) > 120]
    assert not wide, wide


def test_readme_has_a_picture_and_bibtex():
    text = (ROOT / "README.md").read_text()
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert pictures and all((ROOT / p).is_file() for p in pictures), pictures
    assert all((ROOT / p).stat().st_size < 400_000 for p in pictures)  # small: it lives in the repository
    assert "@article{jin2021image" in text and "@software{imtune" in text


def test_readme_quotes_no_development_data_path():
    text = (ROOT / "README.md").read_text()
    assert "../shared" not in "\n".join(readme_code_lines())
    assert "/work/" not in text


# -- the terminal --------------------------------------------------------------------------------------------

def tune(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT), COLUMNS="100")
    return subprocess.run([sys.executable, "-m", "tuner", *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=300)


def test_tune_list_fits_100_columns_and_names_prints_the_full_note():
    r = tune("list")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) > 40 and lines[0].startswith("| family")
    assert max(len(ln) for ln in lines) <= 100, max(lines, key=len)
    full = {e["name"]: e["note"] for e in json.loads(tune("list", "--json").stdout)}
    long_name = max(full, key=lambda n: len(full[n]))  # the longest note: cut in the table
    assert len(full[long_name]) > 60
    r = tune("list", long_name)
    assert r.returncode == 0, r.stderr
    assert " ".join(full[long_name].split()) in " ".join(r.stdout.split())
    assert max(len(ln) for ln in r.stdout.splitlines()) <= 100
    assert any(len(ln) > 100 for ln in tune("list", "--long").stdout.splitlines()) or len(full[long_name]) < 50


def test_short_note_cuts_at_a_clause_and_keeps_parentheses_balanced():
    from tuner.commands.listing import short_note
    note = ("dog+hardnet: weights checkpoint_liberty_with_aug.pth not found in /root/.cache/torch/hub/checkpoints "
            "or /x/hub/checkpoints (set TORCH_HOME to a folder with hub/checkpoints/x.pth, or "
            "IMTUNE_DOWNLOAD_WEIGHTS=1 to download it)")
    out = short_note(note, 48, "dog-hardnet")
    assert len(out) <= 48 and out.startswith("weights") and "/root" not in out
    mkd = "DoG (OpenCV SIFT detector) + MKD (concat, PCA-whitened, liberty); 128-D float32 (kornia) (= dog+mkd)"
    out = short_note(mkd, 48)
    assert len(out) <= 48 and out.count("(") == out.count(")"), out
    assert short_note("short", 48) == "short"


def test_the_main_jobs_tables_fit_100_columns():
    """The frozen-settings table's notes continue on rows of their own and a wide test table is split by columns,
    the scene in each part (the run printed lines of 162-215 characters)."""
    from tuner.commands.study import frozen_table, test_table
    sc = {"pairs": 12, "NF": 2048.0, "NM": 161.0, "NI": 60.0, "mAA5": 0.217, "mAA5_ci": [0.017, 0.46],
          "mAA10": 0.233, "mAA10_ci": [0.026, 0.498], "auc10": 0.231, "failed": 0.0, "match_seconds": 0.0745,
          "ransac_seconds": 0.102, "ransac_seconds_median": 0.09}
    t = {"task": "stereo", "trial": 5, "runs": [{}], "std": {"mAA10": 0.0},
         "budget": {"test_seconds_per_pair": 1.0, "within_budget": True},
         "mean": {**sc, "scenes": {"castle-P19": dict(sc), "castle-P30": dict(sc), "entry-P10": dict(sc)}},
         "data": {"ground_truth": {s: "the scene's own poses (the camera files of its Strecha-layout folder)"
                                   for s in ("castle-P19", "castle-P30", "entry-P10")}}}
    text = test_table(t)
    assert max(len(ln) for ln in text.splitlines() if ln.startswith("|")) <= 100, text
    heads = [ln for ln in text.splitlines() if ln.startswith("| scene")]
    assert len(heads) == 2 and "ransac_seconds" in heads[1] and "mAA10" in heads[0], heads
    f = {"study": "x", "trial": 5, "task": "stereo", "params": {"max_iters": 94358, "ratio": 0.8511,
                                                               "threshold": 0.1056}, "fixed": {"strategy": "both"},
         "budget": {"seconds_per_pair": 0.5, "gamma_max": 220000},
         "validation": {"mAA10": 0.711, "mAA10_ci": [0.583, 0.83], "mAA5": 0.656, "auc10": 0.7, "pairs": 36,
                        "NF": 2048.0, "NM": 387.0, "NI": 209.0, "failed": 0, "match_seconds": 0.15,
                        "ransac_seconds": 0.333, "ransac_seconds_median": 0.114}}
    text = frozen_table(f)
    assert max(len(ln) for ln in text.splitlines() if ln.startswith("|")) <= 100, text
    assert "ransac_seconds 0.333" in " ".join(text.split())


def test_prose_is_wrapped_on_a_terminal_only():
    """A long line of prose wraps at 100 columns on a terminal and stays one line into a pipe (tests, scripts and
    grep read the output line by line)."""
    from tuner.formatting import fit_text
    line = "flat region: " + ", ".join(f"item {i}" for i in range(40))
    assert fit_text(line) == line  # pytest captures stdout: not a terminal
    wrapped = fit_text(line, 100).splitlines()
    assert len(wrapped) > 1 and max(map(len, wrapped)) <= 100 and " ".join(w.strip() for w in wrapped) == line


def test_no_cli_message_names_a_source_file():
    """Warnings and errors the CLI prints name no source file or working-log page ("tuner/budget.py GAMMA_CEILING",
    "see tuner/space.py", "notes/h32data.md"): string constants of tuner/ and pipeline/ other than docstrings."""
    import ast
    pat = re.compile(r"\b(?:tuner|pipeline|tests)/[\w/]*\.py\b|\bnotes/|GAMMA_CEILING|\bissue \d+")
    found = []
    for f in sorted([*(ROOT / "tuner").rglob("*.py"), *(ROOT / "pipeline").rglob("*.py")]):
        tree = ast.parse(f.read_text())
        docs = {id(n.body[0].value) for n in ast.walk(tree)
                if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body
                and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        for n in ast.walk(tree):
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs and pat.search(n.value):
                found.append(f"{f.relative_to(ROOT)}:{n.lineno}: {n.value[:100]}")
    assert not found, found


def test_every_option_has_a_help_text():
    """`--test-runs` had an empty help text, `tune dashboard --port` and `tune studies --json` too: in the CLI
    reference their rows said nothing."""
    import argparse

    from tuner.cli import build_parser
    todo, empty, seen = [("tune", build_parser())], [], 0
    while todo:
        name, p = todo.pop()
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                todo += [(f"{name} {k}", sp) for k, sp in a.choices.items()]
            elif a.option_strings and a.help is not argparse.SUPPRESS:
                seen += 1
                if not (a.help or "").strip():
                    empty.append(f"{name} {a.option_strings[0]}")
    assert seen > 200 and not empty, empty


def test_run_help_describes_what_most_people_set_and_names_the_rest():
    """`tune run -h` was 232 lines, ~60 options in one wall of text: it now describes what most people set and
    names the less used options in one paragraph; `--help-all` describes every one, and every option is still
    accepted."""
    from tuner.commands.study import RUN_LESS_USED
    short, full = tune("run", "-h"), tune("run", "--help-all")
    assert short.returncode == 0 and full.returncode == 0, short.stderr + full.stderr
    s, f = short.stdout, full.stdout
    assert len(s.splitlines()) < 140 < len(f.splitlines()), (len(s.splitlines()), len(f.splitlines()))
    for opt in ("--feature FEATURE", "--num-features NUM_FEATURES", "--ransac RANSAC", "--n-trials N_TRIALS",
                "--budget BUDGET", "--studies-dir STUDIES_DIR", "--replicates K"):
        assert opt in s and opt in f, opt
    head, tail = s.split("less used options", 1)
    named = re.findall(r"--[\w-]+", tail)
    for opt in RUN_LESS_USED:
        described = re.compile(rf"^\s+{re.escape(opt)}(\s|,|$)", re.M)  # an option's line of the help
        assert opt in named and described.search(f), opt  # named by -h, described by --help-all
        assert not described.search(head), opt  # not described by -h
    assert "--fginn" in tail and "FGINN: 2nd neighbour" in f and "FGINN: 2nd neighbour" not in s
    from tests.test_docs_commands import check_line
    assert check_line(["run", "--fginn", "--confidence", "0.99", "--bags", "5:2"]) == []


def test_a_docs_extra_serves_the_site_without_the_test_packages():
    """mkdocs came only with the lint extra, which `install.sh --test` installs beside Debian packages through
    apt and sudo: a reader could not serve the site without them."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    names = {re.split(r"[<>=\[ ]", d, maxsplit=1)[0] for d in extras["docs"]}
    assert {"mkdocs", "mkdocs-material", "mkdocstrings"} <= names, names
    script = (ROOT / ".ci" / "install.sh").read_text()
    assert "--docs) DOCS=1" in script and "'.[docs]'" in script
    docs_branch = script.split('elif [ "$DOCS" -eq 1 ]; then', 1)[1].split("else", 1)[0]
    assert "apt-get" not in docs_branch and "SUDO" not in docs_branch
    r = subprocess.run(["bash", str(ROOT / ".ci" / "install.sh"), "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--docs" in r.stdout
    assert "bash .ci/install.sh --docs" in (ROOT / "README.md").read_text()


def test_a_strecha_layout_scene_is_not_called_laser_scanned():
    """`tune test` on a KITTI sequence, the Middlebury temple or an IMC scene in the Strecha layout said "the scene's
    own poses (Strecha's laser-scan cameras)": the layout tells only that each image has a camera file."""
    from pipeline.data.scene import Scene
    scene = Scene(name="kitti-00", root=ROOT, images={}, source="strecha")
    origin = scene.truth_origin()
    assert origin == "the scene's own poses (the camera files of its Strecha-layout folder)", origin
    assert "laser" not in origin.lower()
