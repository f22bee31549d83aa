"""`tune list`: every feature, matcher option, estimator and task, and whether it is available here."""
from __future__ import annotations

import json

from tuner.formatting import render


def register(sub) -> None:
    ap = sub.add_parser("list", help="list features, matchers, estimators and tasks, with availability")
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
    for name, note in [("exact", "brute-force nearest neighbours, L2 or Hamming (default)"),
                       ("flann", "OpenCV FLANN: 4 KD-trees, 128 checks (LSH for binary)"),
                       ("both", "strategy: mutual nearest neighbours (intersection)"),
                       ("either", "strategy: union of the two directions"),
                       ("uni", "strategy: one direction, image 1 -> image 2"),
                       ("fginn", "FGINN: second neighbour must lie > 10 px from the first")]:
        rows.append({"family": "matcher", "name": name, "available": "yes", "note": note})
    return rows


def run(args) -> int:
    rows = inventory()
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        for r in rows:  # the table shows the estimators' model beside their name
            r.setdefault("model", "")
        print(render(rows, "markdown", ["family", "name", "model", "available", "note"]))
    return 0
