"""`tune evaluate`: one fixed configuration on the stereo and/or multiview task (JSON with --json, else tables)."""
from __future__ import annotations

import json
import math

from tuner.formatting import render
from tuner.options import (TASKS, add_multiview_options, add_pipeline_options, build_config, evaluate_config,
                           multiview_config, resolve_data)

COLUMNS = ["scene", "pairs", "NF", "NM", "NI", "mAA5", "mAA10", "failed", "match_seconds", "ransac_seconds"]
IM_COLUMNS = ["scene", "pairs", "repeatability_3px", "matching_score_3px", "epipolar_matching_score"]
MV_COLUMNS = ["scene", "bag_size", "bags", "SR", "RC", "NL", "TL", "mAA5", "mAA10", "ATE", "failed", "NM", "seconds"]


def register(sub) -> None:
    ap = sub.add_parser("evaluate", help="evaluate one fixed configuration")
    add_pipeline_options(ap)
    ap.add_argument("--task", default="stereo", choices=list(TASKS), help="stereo (default), multiview or both")
    add_multiview_options(ap)
    ap.add_argument("--pairs", action="store_true", help="include every pair record in the JSON")
    ap.add_argument("--bag-records", action="store_true", help="include every multiview bag record in the JSON")
    ap.add_argument("--intermediate", action="store_true",
                    help="also repeatability and matching score at 1..10 px (depth maps) / epipolar matching score")
    ap.set_defaults(func=run)


def stereo_rows(stereo: dict) -> list[dict]:
    rows = [dict(scene=name, **{k: s[k] for k in COLUMNS[1:]}) for name, s in stereo["scenes"].items()]
    rows.append(dict(scene="mean", **{k: stereo[k] for k in COLUMNS[1:]}))
    return rows


def multiview_rows(mv: dict) -> list[dict]:
    """One row per scene and bag size, one per scene (mean over bag sizes), and the overall mean."""
    rows = []

    def row(scene, size, s):
        return dict(scene=scene, bag_size=size, **{k: s.get(k) for k in MV_COLUMNS[2:]})
    for name, s in mv["scenes"].items():
        for size, ss in s.get("by_size", {}).items():
            rows.append(row(name, size, ss))
        rows.append(row(name, "all", s))
    rows.append(row("mean", "all", mv))
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
    mv = multiview_config(args) if args.task in ("multiview", "both") else None
    out = evaluate_config(conf, data, args.scenes, cache_dir=args.cache,
                          min_covisibility=args.covisibility, progress=not (args.quiet or args.json),
                          with_pairs=args.pairs, task=args.task, multiview=mv, workers=args.workers,
                          gt_dir=args.gt_dir, with_bags=args.bag_records, keep_models=args.keep_models,
                          intermediate=args.intermediate)
    if args.json:
        print(json.dumps(_jsonable(out), indent=2))
    else:
        c = conf
        print(f"{c.feature.name} ({c.feature.num_features}) | r={c.matching.ratio} {c.matching.strategy} | "
              f"{c.geometry.ransac} eta={c.geometry.threshold}px Gamma={c.geometry.max_iters} | data {data}")
        if "stereo" in out:
            print(render(stereo_rows(out["stereo"]), "markdown", COLUMNS))
        if "multiview" in out:
            print(f"multiview: COLMAP from tentative matches (intrinsics: {mv.intrinsics}); "
                  f"SR, RC in %; ATE in ground-truth units")
            print(render(multiview_rows(out["multiview"]), "markdown", MV_COLUMNS))
        if "intermediate" in out:
            im = out["intermediate"]
            rows = [dict(scene=n, **{k: s.get(k) for k in IM_COLUMNS[1:]}) for n, s in im["scenes"].items()]
            rows.append(dict(scene="mean", **{k: im.get(k) for k in IM_COLUMNS[1:]}))
            print("intermediate: tentative matches before RANSAC; repeatability / matching score need depth maps")
            print(render(rows, "markdown", IM_COLUMNS))
    return 0
