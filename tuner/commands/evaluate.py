"""`tune evaluate`: one fixed configuration on the stereo task (JSON with --json, else a table)."""
from __future__ import annotations

import json
import math

from tuner.formatting import render
from tuner.options import add_pipeline_options, build_config, evaluate_config, resolve_data

COLUMNS = ["scene", "pairs", "NF", "NM", "NI", "mAA5", "mAA10", "failed", "match_seconds", "ransac_seconds"]


def register(sub) -> None:
    ap = sub.add_parser("evaluate", help="evaluate one fixed configuration")
    add_pipeline_options(ap)
    ap.add_argument("--pairs", action="store_true", help="include every pair record in the JSON")
    ap.set_defaults(func=run)


def stereo_rows(stereo: dict) -> list[dict]:
    rows = [dict(scene=name, **{k: s[k] for k in COLUMNS[1:]}) for name, s in stereo["scenes"].items()]
    rows.append(dict(scene="mean", **{k: stereo[k] for k in COLUMNS[1:]}))
    return rows


def _jsonable(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None if math.isnan(o) else ("inf" if o > 0 else "-inf")
    if isinstance(o, dict):
        return {k: _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    return o


def run(args) -> int:
    conf = build_config(args)
    data = resolve_data(args.data)
    out = evaluate_config(conf, data, args.scenes, cache_dir=args.cache,
                          min_covisibility=args.covisibility, progress=not (args.quiet or args.json),
                          with_pairs=args.pairs)
    if args.json:
        print(json.dumps(_jsonable(out), indent=2))
    else:
        c = conf
        print(f"{c.feature.name} ({c.feature.num_features}) | r={c.matching.ratio} {c.matching.strategy} | "
              f"{c.geometry.ransac} eta={c.geometry.threshold}px Gamma={c.geometry.max_iters} | data {data}")
        print(render(stereo_rows(out["stereo"]), "markdown", COLUMNS))
    return 0
