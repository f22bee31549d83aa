"""Render rows (list of dicts) as markdown, csv, latex or json tables, with the precision a reader of the
paper expects.

    from tuner.formatting import render, Columns, with_mean_row
    cols = Columns(["scene", "NI", "mAA10"], caption="Stereo test results")
    print(render(with_mean_row(rows, cols), "latex", cols))

Precision is chosen by column name (:func:`column_kind`): counts (NF, NM, NI, NL, features, Gamma, pairs,
bags, rank, ...) as integers; mAA to 3 decimals; the ratio test r to 2 decimals (more when an r < 1 would
read 1.00, the protocol's "no ratio test"); the inlier threshold eta, seconds and ATE to 3 significant digits; SR / RC (percentages) to 1 decimal; TL to 2 decimals. Other
numbers keep the ``digits`` of :func:`render`.

LaTeX (``fmt="latex"``) is ready to paste: a ``table`` float with ``\\caption`` (when the columns carry
one), a booktabs ``tabular`` (``\\toprule`` / ``\\midrule`` / ``\\bottomrule``; needs
``\\usepackage{booktabs}``), numeric columns right-aligned, text columns left-aligned, headers with
``$r$``, ``$\\eta$``, ``$\\Gamma$``, ``mAA($10^\\circ$)``, and LaTeX's special characters escaped
(``_`` -> ``\\_``). A row after which a rule belongs (the "mean" row) is marked with ``{"_rule": True}``.
"""
from __future__ import annotations

import csv
import io
import json
import math
import re


class Columns(list):
    """A list of column names that also carries what the LaTeX form needs: a ``caption`` (plain text: one
    sentence saying what the table shows; escaped for LaTeX), optionally ``latex_caption`` (the same,
    already LaTeX, used as is) and ``labels`` (column -> LaTeX header, overriding :func:`latex_header`).
    A plain list works everywhere a Columns does."""

    def __init__(self, names=(), caption: str | None = None, labels: dict | None = None,
                 latex_caption: str | None = None):
        super().__init__(names)
        self.caption = caption
        self.latex_caption = latex_caption
        self.labels = dict(labels or {})


_INT = {"NF", "NM", "NI", "NL", "features", "count", "Gamma", "Gamma_max", "max_iters", "rank", "pairs", "bags",
        "failed", "trial", "runs", "complete", "pruned", "infeasible", "running", "fail", "waiting"}
_SIG3 = {"eta", "threshold", "B", "ATE", "seconds", "s/pair"}


def column_kind(name: str) -> str:
    """"int", "maa" (3 decimals), "ratio" (2 decimals), "sig3" (3 significant digits), "pct" (1 decimal),
    "tl" (2 decimals) or "" (the default ``digits``) for a column name like "NI degensac" or "mAA10"."""
    name = str(name)
    first = name.split()[0] if name.split() else name
    if name == "best trial" or first in _INT:
        return "int"
    if first.startswith("mAA") or first in ("auc5", "auc10", "auc20"):  # pose AUC: on mAA's scale
        return "maa"
    if first in ("r", "ratio", "r_multiview"):
        return "ratio"
    if first in ("SR", "RC"):
        return "pct"
    if first == "TL":
        return "tl"
    if first in _SIG3 or "seconds" in name or "s/pair" in name or name.startswith("B ") or name.startswith("B("):
        return "sig3"
    return ""


def _sig(v: float, n: int = 3) -> str:
    if v == 0:
        return "0"
    s = f"{v:.{n}g}"
    if "e" in s:  # 12345 -> "1.23e+04" is unreadable in a table: write the integer
        return f"{v:.0f}" if abs(v) >= 1 else s
    return s


def format_value(column: str, v, digits: int = 4) -> str:
    """The text of one cell (markdown / csv form): "-" for missing, "inf" for infinity."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = float(v) if isinstance(v, float) else v
        if isinstance(v, float) and (math.isinf(v) or math.isnan(v)):
            return "-" if math.isnan(v) else ("inf" if v > 0 else "-inf")
        kind = column_kind(column)
        if kind == "int":
            return str(int(round(v)))
        if kind == "maa":
            return f"{v:.3f}"
        if kind == "ratio":  # 2 decimals as in the paper, more where they would turn r < 1 into 1.00 (no test)
            d = 2
            while v < 1.0 and float(f"{v:.{d}f}") >= 1.0 and d < 6:
                d += 1
            return f"{v:.{d}f}"
        if kind == "pct":
            return f"{v:.1f}"
        if kind == "tl":
            return f"{v:.2f}"
        if kind == "sig3":
            return _sig(float(v))
        if isinstance(v, int):
            return str(v)
        return _cell(v, digits)
    return str(v)


def _cell(v, digits: int = 4) -> str:
    """The default form of a number with no known column kind: ``digits`` decimals, trailing zeros cut."""
    if abs(v) >= 1000:
        return _sig(v, digits)
    s = f"{v:.{digits}f}"
    return s.rstrip("0").rstrip(".") if "." in s else s


def is_numeric(rows: list[dict], column: str) -> bool:
    """Whether every present value of the column is a number (such columns are right-aligned)."""
    vals = [r.get(column) for r in rows if r.get(column) is not None]
    return bool(vals) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals)


_LATEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                  "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def latex_escape(s) -> str:
    """Plain text -> LaTeX text (every special character escaped)."""
    return "".join(_LATEX_SPECIAL.get(ch, ch) for ch in str(s)).replace("°", r"$^\circ$")


_SYMBOLS = {"r": "$r$", "eta": r"$\eta$", "Gamma": r"$\Gamma$", "B": "$B$", "r_multiview": "$r$ multiview"}


def latex_header(column: str) -> str:
    """A column name as a LaTeX header: r / eta / Gamma / B become $r$ / $\\eta$ / $\\Gamma$ / $B$,
    mAA10 / mAA(10°) become mAA($10^\\circ$); the rest is escaped text."""
    out = []
    for word in str(column).split(" "):
        m = re.fullmatch(r"mAA\(?(\d+)(?:°|deg)?\)?", word)
        if word in _SYMBOLS:
            out.append(_SYMBOLS[word])
        elif m:
            out.append(f"mAA(${m.group(1)}^\\circ$)")
        else:
            out.append(latex_escape(word))
    return " ".join(out)


def _latex_cell(column: str, v, digits: int) -> str:
    if v is None:
        return "--"
    if isinstance(v, float) and math.isinf(v):
        return r"$\infty$" if v > 0 else r"$-\infty$"
    return latex_escape(format_value(column, v, digits))


def with_mean_row(rows: list[dict], columns: list[str], key: str = "scene", what: str = "scenes",
                  skip: tuple[str, ...] = ()) -> list[dict]:
    """``rows`` plus a mean row when there are several rows (one row: returned as is, a mean of one scene
    says nothing). The mean row's ``key`` cell says what it averages ("mean over 2 scenes"); a numeric
    column gets the plain mean over the rows, and stays empty when some rows lack a value (a mean over
    fewer rows than the label says would mislead); ``skip``: columns left empty (e.g. "pairs")."""
    rows = list(rows)
    if len(rows) < 2:
        return rows
    mean = {key: f"mean over {len(rows)} {what}", "_rule": True}
    for c in columns:
        if c == key or c in skip:
            continue
        vals = [r.get(c) for r in rows]
        nums = [float(v) for v in vals if isinstance(v, (int, float)) and not isinstance(v, bool)]
        if len(nums) == len(rows):
            finite = [x for x in nums if math.isfinite(x)]
            mean[c] = float(sum(finite) / len(finite)) if len(finite) == len(nums) else float("inf")
    return rows + [mean]


def render(rows: list[dict], fmt: str = "markdown", columns: list[str] | None = None, digits: int = 4) -> str:
    """The table in ``fmt`` (markdown, csv, latex, json). ``columns``: a list or a :class:`Columns`
    (whose caption and labels the LaTeX form uses); default every key of the rows in order."""
    columns = columns if columns is not None else (
        [k for k in dict.fromkeys(k for r in rows for k in r) if not str(k).startswith("_")] if rows else [])
    if fmt == "json":
        return json.dumps([{c: r.get(c) for c in columns} for r in rows], indent=2, default=str)
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(columns)
        for r in rows:
            w.writerow([format_value(c, r.get(c), digits) for c in columns])
        return buf.getvalue().rstrip("\n")
    numeric = [is_numeric(rows, c) for c in columns]
    if fmt == "latex":
        labels = getattr(columns, "labels", {}) or {}
        caption = getattr(columns, "latex_caption", None) or (
            latex_escape(columns.caption) if getattr(columns, "caption", None) else None)
        lines = [r"\begin{table}[t]", r"\centering"]
        if caption:
            lines.append(r"\caption{" + caption + "}")
        lines += [r"\begin{tabular}{" + "".join("r" if n else "l" for n in numeric) + "}", r"\toprule",
                  " & ".join(labels.get(c, latex_header(c)) for c in columns) + r" \\", r"\midrule"]
        for r in rows:
            if r.get("_rule"):
                lines.append(r"\midrule")
            lines.append(" & ".join(_latex_cell(c, r.get(c), digits) for c in columns) + r" \\")
        lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
        return "\n".join(lines)
    if fmt != "markdown":
        raise ValueError(f"unknown format {fmt!r}")
    cells = [[format_value(c, r.get(c), digits) for c in columns] for r in rows]
    widths = [max([len(str(c)), 3] + [len(row[i]) for row in cells]) for i, c in enumerate(columns)]

    def line(vals):
        return "| " + " | ".join(v.rjust(w) if n else v.ljust(w) for v, w, n in zip(vals, widths, numeric)) + " |"

    head = "| " + " | ".join(str(c).ljust(w) for c, w in zip(columns, widths)) + " |"
    out = [head,
           "|" + "|".join(("-" * (w + 1) + ":") if n else ("-" * (w + 2)) for w, n in zip(widths, numeric)) + "|"]
    out += [line(row) for row in cells]
    caption = getattr(columns, "caption", None)
    if caption:  # pandoc's table caption: a "Table:" paragraph after the table
        out += ["", f"Table: {caption}"]
    return "\n".join(out)


#: the terminal width the tables and notes `tune` prints keep to (characters per line)
TERMINAL_WIDTH = 100


def fit_text(text: str, width: int | None = None) -> str:
    """A line of prose as a terminal shows it best: on a terminal, in lines of at most ``width`` characters
    (default: the terminal's width, at most :data:`TERMINAL_WIDTH`; the continuation indented by two, words whole);
    into a pipe or a file, one line as before, so that what reads the output line by line keeps working."""
    import shutil
    import sys
    import textwrap
    if width is None:
        if not sys.stdout.isatty():
            return text
        width = min(TERMINAL_WIDTH, shutil.get_terminal_size((TERMINAL_WIDTH, 24)).columns)
    if len(text) <= width:
        return text
    return "\n".join(textwrap.wrap(text, width=width, subsequent_indent="  ", break_long_words=False,
                                    break_on_hyphens=False))


def render_fitted(rows: list[dict], columns: list[str], width: int = TERMINAL_WIDTH, keep: int = 1,
                  digits: int = 4) -> str:
    """The markdown table, split by columns into tables of at most ``width`` characters (each repeating the first
    ``keep`` columns, e.g. the scene): a table that fits is one table."""
    def wide(cols: list[str]) -> int:
        return max(len(ln) for ln in render(rows, "markdown", cols, digits).splitlines())
    columns = list(columns)
    chunks, chunk = [], columns[:keep]
    for c in columns[keep:]:
        if len(chunk) > keep and wide(chunk + [c]) > width:
            chunks.append(chunk)
            chunk = columns[:keep]
        chunk = chunk + [c]
    chunks.append(chunk)
    return "\n\n".join(render(rows, "markdown", ch, digits) for ch in chunks)


def wrapped_cell_rows(rows: list[dict], column: str, width: int) -> list[dict]:
    """Rows whose ``column`` text is longer than ``width`` continued on rows of their own (other cells empty),
    the text broken after a comma or a space, so that a table of notes fits a terminal."""
    import textwrap
    out = []
    for r in rows:
        text = str(r.get(column, "") or "")
        parts = textwrap.wrap(text, width=width, break_long_words=False, break_on_hyphens=False) or [""]
        out.append({**r, column: parts[0]})
        out += [{**{k: "" for k in r}, column: part} for part in parts[1:]]
    return out


def gamma_max_text(gmax, fixed=None, unit: str = "") -> str:
    """``Gamma_max 48213`` (``unit`` appended, e.g. " iterations"), or what stands for it where no calibration was
    made (a study that fixed max_iters measures none: the frozen table and the report said 'Gamma_max None')."""
    if gmax is not None:
        return f"Gamma_max = {gmax}{unit}" if unit else f"Gamma_max {gmax}"
    return "Gamma_max not calibrated" + (" (max_iters fixed)" if "max_iters" in (fixed or {}) else "")


def ground_truth_origins(scenes) -> dict:
    """scene name -> where the poses it is evaluated against come from (:meth:`pipeline.data.scene.Scene.truth_origin`:
    the scene's own, or imtune's SfM by `tune data build-gt`), what a study, test.json and reports record."""
    return {s.name: s.truth_origin() for s in scenes}


def ground_truth_short(origins) -> str:
    """A table cell for recorded :func:`ground_truth_origins` (scene -> the phrase of
    :meth:`pipeline.data.scene.Scene.truth_origin`): "own poses", "own poses, SfM co-visibility", "own poses,
    co-visibility from 3D points", "SfM (build-gt)" or "none", the scenes named when they differ; "not recorded"
    for a study or test.json written before imtune recorded it."""
    if not isinstance(origins, dict) or not origins:
        return "not recorded"

    def short(origin: str) -> str:
        if origin.startswith("imtune's SfM"):
            return "SfM (build-gt)"
        if origin.startswith("none"):
            return "none"
        if origin.startswith("the scene's own poses"):
            if "co-visibility from imtune's SfM" in origin:
                return "own poses, SfM co-visibility"
            if "co-visibility from 3D points" in origin:
                return "own poses, co-visibility from 3D points"
            return "own poses"
        return origin  # a phrase this function does not know: shown whole, never guessed

    groups: dict[str, list[str]] = {}
    for name, origin in origins.items():
        groups.setdefault(short(str(origin)), []).append(str(name))
    if len(groups) == 1:
        return next(iter(groups))
    return "; ".join(f"{', '.join(names)}: {label}" for label, names in groups.items())


def ground_truth_text(origins) -> str | None:
    """One line of recorded :func:`ground_truth_origins`, the scenes of one origin together ("A, B: origin; C:
    other"); None when nothing was recorded (a study or test.json written before imtune recorded it)."""
    if not isinstance(origins, dict) or not origins:
        return None
    groups: dict[str, list[str]] = {}
    for name, origin in origins.items():
        groups.setdefault(str(origin), []).append(str(name))
    return "; ".join(f"{', '.join(names)}: {origin}" for origin, names in groups.items())
