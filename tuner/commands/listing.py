"""`tune list`: every feature, matcher option, estimator and task, and whether it is available here.

The table fits a 100-column terminal (:data:`WIDTH`): each note is cut to what fits its column, at a clause
boundary where one fits; `tune list NAME` prints one entry with its full note, `tune list --long` the table with
every note in full, `--json` everything."""
from __future__ import annotations

import json
import re
import textwrap

from tuner.formatting import render

#: the width `tune list` keeps to (characters per line)
WIDTH = 100
COLUMNS = ["family", "name", "available", "note"]  # an E estimator's name carries " (E)"


def register(sub) -> None:
    ap = sub.add_parser("list", help="list features, matchers, estimators and tasks, with availability")
    ap.add_argument("name", nargs="?", default=None, metavar="NAME",
                    help="print one entry (a feature, estimator, pre-filter, task or matcher option) with its full "
                         "note (default: the whole table, each note cut to fit 100 columns)")
    ap.add_argument("--long", action="store_true", help="the whole table with every note in full (wider than 100 "
                                                        "columns)")
    ap.add_argument("--json", action="store_true", help="print a JSON list of {family, name, available, note} "
                    "(estimators also have model: F or E)")
    ap.set_defaults(func=run)


def inventory() -> list[dict]:
    """One row per method: family, name, available (bool), note (why not, or what it is)."""
    from pipeline.features import EXTRACTORS
    from pipeline.geometry import ESTIMATORS
    rows = []
    families = [("feature", EXTRACTORS), ("estimator", ESTIMATORS)]
    try:
        from pipeline.matching.prefilters import PREFILTERS
        families.append(("prefilter", PREFILTERS))
    except ImportError:
        pass
    for family, reg in families:
        for name, (ok, why) in reg.availability().items():
            row = {"family": family, "name": name, "available": "yes" if ok else "no",
                   "note": why or reg.description(name)}
            if family == "estimator":  # "F": fundamental matrix; "E": essential matrix given K1, K2
                row["model"] = getattr(reg.get(name), "model", "F")
            rows.append(row)
    from pipeline.tasks import TASKS  # the tasks `--task` takes, a plug-in's included (IMTUNE_PLUGINS)
    for name, (ok, why) in TASKS.availability().items():
        rows.append({"family": "task", "name": name, "available": "yes" if ok else "no",
                     "note": why or TASKS.description(name)})
    from pipeline.matching.learned import LEARNED_MATCHERS, is_learned
    is_learned("")  # registers the learned matchers
    for name, (ok, why) in LEARNED_MATCHERS.availability().items():  # the learned-matcher family (--matcher NAME)
        rows.append({"family": "matcher", "name": name, "available": "yes" if ok else "no",
                     "note": why or LEARNED_MATCHERS.description(name)})
    for name, note in [("exact", "brute-force nearest neighbours, L2 or Hamming (default)"),
                       ("flann", "OpenCV FLANN: 4 KD-trees, 128 checks (LSH for binary)"),
                       ("both", "strategy: mutual nearest neighbours (intersection)"),
                       ("either", "strategy: union of the two directions"),
                       ("uni", "strategy: one direction, image 1 -> image 2"),
                       ("fginn", "FGINN: second neighbour must lie > 10 px from the first")]:
        rows.append({"family": "matcher", "name": name, "available": "yes", "note": note})
    return rows


def short_note(note: str, width: int, name: str = "") -> str:
    """``note`` in at most ``width`` characters: a leading "NAME: " / "det+desc: " dropped, a path and what follows
    it ("not found in /root/...") dropped, then the longest prefix ending at a clause boundary ("; ", " (", ", ")
    outside parentheses that fits, else cut at a word with "...". The full note is what `tune list NAME` prints."""
    note = " ".join(note.split())
    head, sep, rest = note.partition(": ")
    if sep and " " not in head and ("+" in head or head == name):
        note = rest
    note = re.sub(r" in /\S*( or /\S*)*", "", note).strip()
    if len(note) > width:
        note = re.sub(r"^weights \S+ not found", "weights not found", note)
    if len(note) <= width:
        return note
    cuts = [m.start() for m in re.finditer(r"; | \(|, |\. ", note)
            if 12 <= m.start() <= width and note[:m.start()].count("(") == note[:m.start()].count(")")]
    if cuts:
        return note[:max(cuts)].rstrip(" ,;.")
    return note[:width - 3].rsplit(" ", 1)[0].rstrip(" ,;.") + "..."


def fitted(rows: list[dict], width: int = WIDTH) -> list[dict]:
    """The rows with each note cut so that the markdown table is at most ``width`` characters wide."""
    fixed = sum(max([len(c)] + [len(str(r.get(c, ""))) for r in rows]) for c in COLUMNS[:-1])
    room = max(24, width - fixed - 3 * len(COLUMNS) - 1)
    return [{**r, "note": short_note(str(r["note"]), room, str(r["name"]))} for r in rows]


def entry_text(row: dict, width: int = WIDTH) -> str:
    """One entry, every field on its own line, the note in full (wrapped at ``width``)."""
    out = [f"{k}: {row[k]}" for k in ("name", "family", "model", "available") if row.get(k)]
    out += textwrap.wrap(f"note: {row['note']}", width=width, subsequent_indent="  ", break_long_words=False,
                         break_on_hyphens=False)
    return "\n".join(out)


def run(args) -> int:
    from pipeline.errors import ImtuneError
    from pipeline.registry import did_you_mean
    rows = inventory()
    if getattr(args, "name", None):
        hits = [r for r in rows if r["name"] == args.name]
        if not hits:
            raise ImtuneError(f"tune list: no entry named {args.name!r}"
                              f"{did_you_mean(args.name, [str(r['name']) for r in rows])} (`tune list` shows them "
                              "all)")
        if args.json:
            print(json.dumps(hits, indent=2))
        else:
            print("\n\n".join(entry_text(r) for r in hits))
        return 0
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    shown = [{**r, "name": f"{r['name']} (E)" if r.get("model") == "E" else r["name"]} for r in rows]
    full = getattr(args, "long", False)
    print(render(shown if full else fitted(shown), "markdown", COLUMNS))
    print("(E): an essential-matrix estimator, given both cameras' intrinsics; the others estimate F")
    if not full and any(f["note"] != r["note"] for f, r in zip(fitted(shown), shown)):
        print("notes cut to fit 100 columns: `tune list NAME` prints one in full, `tune list --long` all of them")
    return 0
