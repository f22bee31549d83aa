"""Render rows (list of dicts) as markdown, csv, latex or json tables."""
from __future__ import annotations

import csv
import io
import json
import math


def _cell(v, digits: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if math.isinf(v) or math.isnan(v):
            return "-" if math.isnan(v) else "inf"
        return f"{v:.{digits}g}" if abs(v) >= 1000 else f"{v:.{digits}f}".rstrip("0").rstrip(".") if "." in f"{v:.{digits}f}" else f"{v}"
    return str(v)


def render(rows: list[dict], fmt: str = "markdown", columns: list[str] | None = None, digits: int = 4) -> str:
    columns = columns or (list(dict.fromkeys(k for r in rows for k in r)) if rows else [])
    if fmt == "json":
        return json.dumps([{c: r.get(c) for c in columns} for r in rows], indent=2, default=str)
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(columns)
        for r in rows:
            w.writerow([_cell(r.get(c), digits) for c in columns])
        return buf.getvalue().rstrip("\n")
    if fmt == "latex":
        esc = lambda s: str(s).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")  # noqa: E731
        lines = [r"\begin{tabular}{" + "l" * len(columns) + "}", r"\toprule",
                 " & ".join(esc(c) for c in columns) + r" \\", r"\midrule"]
        lines += [" & ".join(esc(_cell(r.get(c), digits)) for c in columns) + r" \\" for r in rows]
        lines += [r"\bottomrule", r"\end{tabular}"]
        return "\n".join(lines)
    if fmt != "markdown":
        raise ValueError(f"unknown format {fmt!r}")
    cells = [[_cell(r.get(c), digits) for c in columns] for r in rows]
    widths = [max([len(c)] + [len(row[i]) for row in cells]) for i, c in enumerate(columns)]
    line = lambda vals: "| " + " | ".join(v.ljust(w) for v, w in zip(vals, widths)) + " |"  # noqa: E731
    out = [line(columns), "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    out += [line(row) for row in cells]
    return "\n".join(out)
