"""`tune data ...`: download the public data sets; list scenes of a data folder; build ground truth."""
from __future__ import annotations

from pathlib import Path

from tuner.options import resolve_data


def register(sub) -> None:
    ap = sub.add_parser("data", help="data sets: download, scenes")
    dsub = ap.add_subparsers(dest="data_command", parser_class=type(ap))
    d = dsub.add_parser("download", help="fetch a public data set from its original home")
    d.add_argument("name", help="strecha | sacre_coeur | scannet_sample | phototourism")
    d.add_argument("--dest", default=None, help="destination folder (default: $IMTUNE_DATA_HOME or ~/.cache/imtune/data)")
    d.add_argument("--base-url", default=None, help="mirror to download from instead of the original home")
    d.set_defaults(func=run_download)
    s = dsub.add_parser("scenes", help="list the scenes of a data folder and their default split")
    s.add_argument("--data", default=None)
    s.set_defaults(func=run_scenes)
    g = dsub.add_parser("build-gt", help="build ground truth (3D points, co-visibility, bags) with pycolmap",
                        description="From known poses: triangulate SIFT matches with the poses held fixed. From an "
                                    "image folder: SfM with exhaustive matching (pseudo ground truth). Written to "
                                    "$IMTUNE_CACHE/gt (or --gt-dir), never into the data folder; `tune evaluate` "
                                    "picks it up.")
    g.add_argument("--data", default=None, help="data folder (else $IMTUNE_DATA, imtune.yaml, ../shared/data/strecha)")
    g.add_argument("--scenes", default=None, help="comma-separated scene names (default: all)")
    g.add_argument("--method", default="auto", choices=["auto", "poses", "sfm"],
                   help="auto: poses when every image has K, R, t, else sfm")
    g.add_argument("--num-features", type=int, default=8192, help="COLMAP SIFT keypoints per image")
    g.add_argument("--max-image-size", type=int, default=3200, help="COLMAP extracts on images resized to this (px)")
    g.add_argument("--camera-model", default="SIMPLE_PINHOLE", help="COLMAP camera model for sfm (SIMPLE_PINHOLE, "
                   "PINHOLE, SIMPLE_RADIAL, ...; distortion is not kept in the scene)")
    g.add_argument("--gt-dir", default=None, help="where ground truth is written (default $IMTUNE_GT, $IMTUNE_CACHE/gt or ~/.cache/imtune/gt)")
    g.add_argument("--force", action="store_true", help="rebuild even if a ground truth with these settings exists")
    g.add_argument("--json", action="store_true", help="print one JSON object")
    g.add_argument("--quiet", action="store_true", help="no progress messages")
    g.set_defaults(func=run_build_gt)
    ap.set_defaults(func=lambda a: (ap.print_help(), 2)[1])


def run_download(args) -> int:
    import os

    from pipeline.data.download import download
    dest = Path(args.dest or os.environ.get("IMTUNE_DATA_HOME") or Path.home() / ".cache" / "imtune" / "data")
    out = download(args.name, dest, base_url=args.base_url)
    print(f"{args.name}: ready in {out}")
    return 0


def run_scenes(args) -> int:
    from pipeline.data import default_splits, list_scenes
    root = resolve_data(args.data)
    splits = default_splits(root)
    for n in list_scenes(root):
        role = "val" if n in splits.get("val", []) else "test" if n in splits.get("test", []) else "-"
        print(f"{n}\t{role}")
    return 0


def run_build_gt(args) -> int:
    import json
    import sys
    import time

    from pipeline.data.ground_truth import GTConfig, build_ground_truth
    from tuner.options import load_scenes
    root = resolve_data(args.data)
    conf = GTConfig(method=args.method, num_features=args.num_features, max_image_size=args.max_image_size,
                    camera_model=args.camera_model)
    scenes = load_scenes(root, args.scenes, split="all", ground_truth=False)
    report = {}
    for sc in scenes:
        t0 = time.perf_counter()
        say = (lambda m, n=sc.name: print(f"{n}: {m}", file=sys.stderr, flush=True)) if not (args.quiet or args.json) \
            else None
        total = len(sc.images)
        gt, path = build_ground_truth(sc, args.gt_dir, conf, force=args.force, progress=say)
        m = gt.meta
        rep = m.get("reprojection", {})
        report[sc.name] = {"method": gt.method, "images": total, "registered": len(gt.names),
                           "dropped": m.get("dropped", []), "points": int(len(gt.points3d)),
                           "reprojection_median_px": rep.get("median_px"), "reprojection_p90_px": rep.get("p90_px"),
                           "pairs": m.get("pairs"), "pairs_covisible_0.1": m.get("pairs_covisible_0.1"),
                           "bags": m.get("bags"), "path": str(path), "seconds": round(time.perf_counter() - t0, 1)}
        if not args.json:
            r = report[sc.name]
            med = f"{r['reprojection_median_px']:.3f}" if r["reprojection_median_px"] is not None else "-"
            print(f"{sc.name}: {r['method']}: {r['registered']}/{total} images registered, {r['points']} points, "
                  f"reprojection median {med} px; {r['pairs_covisible_0.1']}/{r['pairs']} pairs with co-visibility "
                  f">= 0.1; bags {r['bags']}; {r['seconds']} s -> {path}")
            if r["dropped"]:
                print(f"{sc.name}: dropped (not registered): {', '.join(r['dropped'])}")
    if args.json:
        print(json.dumps(report, indent=2))
    return 0
