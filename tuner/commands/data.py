"""`tune data ...`: download the public data sets; list scenes of a data folder and where it was found; build
ground truth. Where data is looked for: :mod:`pipeline.data.locate`."""
from __future__ import annotations

from pathlib import Path

from pipeline.data.locate import resolve_data
from pipeline.errors import ImtuneError
from tuner.argtypes import count_int, positive_int, scene_list

DATA_HELP = "data folder (default: $IMTUNE_DATA, imtune.yaml, else strecha in the download location or ../shared/data)"


def register(sub) -> None:
    ap = sub.add_parser("data", help="data sets: download, scenes, build-gt (ground truth)")
    dsub = ap.add_subparsers(dest="data_command", parser_class=type(ap))
    from pipeline.data.download import ENV_BASE, SOURCES
    d = dsub.add_parser("download", help="fetch a public data set from its original home into the download location",
                        description="Downloads into <dest>/<name> atomically (a temporary folder beside it, renamed at "
                                    "the end; nothing is left behind on failure). The default dest is the download "
                                    "location, where every command looks for data.")
    d.add_argument("name", choices=list(SOURCES), metavar="DATA_SET", help=" | ".join(SOURCES))
    d.add_argument("--dest", default=None, help="destination folder (default: the download location, "
                   "$IMTUNE_DATA_HOME or ~/.local/share/imtune/data)")
    d.add_argument("--base-url", default=None, help=f"mirror to download from instead of the original home "
                   f"(default: ${ENV_BASE}, else the original home)")
    d.add_argument("--force", action="store_true", help="download again even if the data set is there")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(func=run_download)
    s = dsub.add_parser("scenes", help="where the data folder was found (and by which rule), its scenes and splits")
    s.add_argument("--data", default=None, help=DATA_HELP)
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.set_defaults(func=run_scenes)
    g = dsub.add_parser("build-gt", help="build ground truth (3D points, co-visibility, bags) with pycolmap",
                        description="From known poses: triangulate SIFT matches with the poses held fixed. From an "
                                    "image folder: SfM with exhaustive matching (pseudo ground truth). Written to "
                                    "--gt-dir, else $IMTUNE_GT, $IMTUNE_CACHE/gt or ~/.cache/imtune/gt, never into "
                                    "the data folder; every later command picks it up.")
    g.add_argument("--data", default=None, help=DATA_HELP)
    g.add_argument("--scenes", type=scene_list, default=None, help="comma-separated scene names (default: all)")
    g.add_argument("--method", default="auto", choices=["auto", "poses", "sfm"],
                   help="auto: poses when every image has K, R, t, else sfm")
    g.add_argument("--num-features", type=int, default=8192, help="COLMAP SIFT keypoints per image")
    g.add_argument("--max-image-size", type=positive_int, default=3200,
                   help="COLMAP extracts on images resized to this (px)")
    g.add_argument("--camera-model", default=None, help="COLMAP camera model for sfm (default SIMPLE_PINHOLE; "
                   "PINHOLE, SIMPLE_RADIAL, ...; distortion is not kept in the scene)")
    g.add_argument("--gt-dir", default=None, help="where ground truth is written (default $IMTUNE_GT, $IMTUNE_CACHE/gt or ~/.cache/imtune/gt)")
    g.add_argument("--force", action="store_true", help="rebuild even if a ground truth with these settings exists")
    g.add_argument("--json", action="store_true", help="print one JSON object")
    g.add_argument("--quiet", action="store_true", help="no progress messages")
    g.set_defaults(func=run_build_gt)
    x = dsub.add_parser("to-imc", help="write posed scenes (Strecha, COLMAP models, IMC 2022, ...) into the IMC "
                        "2024/2025 layout, several scenes mixed into one dataset",
                        description="Writes OUT/train/<dataset>/<scene>_<image> (images linked, or copied with "
                                    "--copy), OUT/train_labels.csv (world-to-camera R, t of every image, in the scene's "
                                    "own units: metres for Strecha) and OUT/train_thresholds.csv (the challenge's six "
                                    "camera-centre thresholds, scaled by --threshold-scale). Several runs with other "
                                    "--dataset names add datasets to the same OUT. The reconstruction task then "
                                    "validates on such a mix and tests on a real challenge dataset.")
    x.add_argument("--data", default=None, help=DATA_HELP)
    x.add_argument("--scenes", type=scene_list, required=True, help="comma-separated posed scenes to mix")
    x.add_argument("--out", required=True, help="the IMC folder written (created; never the data folder)")
    x.add_argument("--dataset", required=True, help="the dataset's name in the IMC layout")
    x.add_argument("--outliers", type=scene_list, default=None,
                   help="comma-separated scenes whose images are written as outliers (no pose)")
    x.add_argument("--threshold-scale", type=float, default=1.0,
                   help="multiply the challenge's thresholds (0.025 ... 1.0 m) by this (scenes in other units)")
    x.add_argument("--copy", action="store_true", help="copy the images (default: symbolic links)")
    x.add_argument("--every", type=positive_int, default=1,
                   help="a sparse subset: every k-th image of each scene, in name order (default 1: all)")
    x.add_argument("--max-outliers", type=count_int, default=None,
                   help="at most this many outlier images, spread evenly over the --outliers scenes (default: all)")
    x.add_argument("--json", action="store_true", help="print one JSON object")
    x.set_defaults(func=run_to_imc)
    ap.set_defaults(func=lambda a: (ap.print_help(), 2)[1])


def run_to_imc(args) -> int:
    import json

    from pipeline.data.imc_export import export_imc
    from pipeline.data.locate import locate
    root = locate(args.data).path
    out = export_imc(root, args.scenes.split(","), args.out, args.dataset,
                     outliers=args.outliers.split(",") if args.outliers else [],
                     threshold_scale=args.threshold_scale, copy=args.copy, every=args.every,
                     max_outliers=args.max_outliers)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"{out['dataset']}: {out['images']} images ({', '.join(f'{k} {v}' for k, v in out['scenes'].items())}"
              f"{', outliers ' + str(out['outliers']) if out['outliers'] else ''}) -> {out['out']}")
    return 0


def run_download(args) -> int:
    import sys
    from pathlib import Path

    from pipeline.data.download import NET_HINT, NetworkError, describe_source, download, downloaded
    from pipeline.data.locate import DEFAULT_SET, download_home, locate
    from pipeline.errors import ImtuneError
    dest = Path(args.dest).expanduser().resolve() if args.dest else download_home()[0]
    target = dest / args.name
    if not args.force and downloaded(target):
        print(f"{args.name}: already in {target} (--force downloads it again)", file=sys.stderr)
    elif not args.quiet:
        print(f"{args.name}: {describe_source(args.name, args.base_url)} -> {target}", file=sys.stderr, flush=True)
    try:
        out = download(args.name, dest, base_url=args.base_url, force=args.force, quiet=args.quiet)
    except NetworkError as e:  # the host cannot be reached: say what else works
        raise ImtuneError(f"{e}; {NET_HINT}") from None
    print(f"{args.name}: ready in {out}")
    try:
        found = locate().path if args.name == DEFAULT_SET else None
    except Exception:  # noqa: BLE001 - only a hint
        found = None
    if found == out.resolve():
        print("every command finds it with no --data (see `tune data scenes`)", file=sys.stderr)
    else:
        print(f"use it with --data {out}", file=sys.stderr)
    return 0


def _other_sets(used) -> list[dict]:
    """Every data set in the download location and ../shared/data, with the rule that would find it."""
    from pipeline.data.locate import fallback_roots
    out = []
    for r in fallback_roots():
        if not r.path.is_dir():
            continue
        for p in sorted(r.path.iterdir()):
            if p.is_dir() and not p.name.startswith(".") and p.resolve() != used:
                out.append({"name": p.name, "path": str(p), "rule": r.rule, "detail": r.detail})
    return out


def run_scenes(args) -> int:
    import json

    from pipeline.data import default_max_pairs, default_splits, list_scenes
    from pipeline.data.locate import locate
    loc = locate(args.data)
    root = loc.path
    splits = default_splits(root)
    cap = default_max_pairs(root)
    scenes = [{"scene": n, "split": "val" if n in splits.get("val", []) else
               "test" if n in splits.get("test", []) else "-"} for n in list_scenes(root)]
    others = _other_sets(root)
    from pipeline.data import imc2025
    imc = {d["dataset"]: d for d in imc2025.describe(root)}  # IMC 2024/2025 datasets: their scenes, outliers, K
    for s in scenes:
        if s["scene"] in imc:
            s["imc"] = imc[s["scene"]]
    if args.json:
        print(json.dumps({"data": str(root), "rule": loc.rule, "detail": loc.detail, "scenes": scenes,
                          "max_pairs": cap, "other_data_sets": others}, indent=2))
        return 0
    # every line within TERMINAL_WIDTH columns, into a pipe too (a terminal, a log, the docs read it alike)
    from tuner.formatting import TERMINAL_WIDTH, fit_text
    print(f"data: {root}  (found by {loc.describe()})")  # the one place the folder's path is said
    for s in scenes:
        print(f"{s['scene']}\t{s['split']}")
        d = s.get("imc")
        if d:
            print(fit_text(f"  IMC dataset: {d['images']} images; outliers {d['outliers']}; intrinsics "
                           f"{'known' if d['intrinsics'] else 'unknown'}"
                           + (f"; {d['unlabelled']} image(s) in no label row (left out)" if d["unlabelled"] else ""),
                           width=TERMINAL_WIDTH))
            print(fit_text("  scenes: " + ", ".join(f"{k} ({v})" for k, v in d["scenes"].items()),
                           width=TERMINAL_WIDTH))
    if cap is not None:
        print(fit_text(f"pairs: the main job uses at most {cap} pairs per scene here (evenly spread; --max-pairs N "
                       "to change)", width=TERMINAL_WIDTH))
    if not splits.get("test"):
        print(fit_text("note: no test split in this folder: the main job needs --test-scenes NAME[,...] (or "
                       "--no-test), or a splits.yaml beside the scenes", width=TERMINAL_WIDTH))
    by_folder: dict[str, list[dict]] = {}
    for o in others:  # each folder's path once, its data sets by name
        by_folder.setdefault(str(Path(o["path"]).parent), []).append(o)
    for folder, sets in by_folder.items():
        print(fit_text(f"also in {folder} ({sets[0]['rule']}), each usable as --data: "
                       f"{', '.join(o['name'] for o in sets)}", width=TERMINAL_WIDTH))
    return 0


def run_build_gt(args) -> int:
    import json
    import sys
    import time

    from pipeline.data.ground_truth import GTConfig, build_ground_truth
    from tuner.evaluate import load_scenes
    root = resolve_data(args.data)
    if args.camera_model is not None and args.method == "poses":  # accepted and unused, unsaid
        raise ImtuneError("--camera-model is for --method sfm only (poses triangulates with each image's known K): "
                          "drop it, or use --method sfm")
    conf = GTConfig(method=args.method, num_features=args.num_features, max_image_size=args.max_image_size,
                    **({"camera_model": args.camera_model} if args.camera_model is not None else {}))
    scenes = load_scenes(root, args.scenes, split="all", ground_truth=False)
    if not scenes:  # was exit 0 with nothing printed: it looked like a build that found nothing to do
        raise ImtuneError(f"no scenes in {root} to build ground truth for (see `tune data scenes --data {root}`)")
    if args.camera_model is not None:
        from pipeline.data.ground_truth import choose_method
        posed = [sc.name for sc in scenes if choose_method(sc, args.method) == "poses"]
        if posed:
            print(f"warning: --camera-model {args.camera_model} is not used for {', '.join(posed)}: their images have "
                  "known poses and K (--method auto triangulates with them); --method sfm reconstructs with it",
                  file=sys.stderr, flush=True)
    from pipeline.data.ground_truth import choose_method
    if args.method == "sfm":  # a scene's own poses (Strecha's laser scans) are replaced in every later command
        posed = [sc.name for sc in scenes if choose_method(sc, "auto") == "poses"]
        if posed:
            print(f"warning: --method sfm on {', '.join(posed)}, whose images have known poses and K: every later "
                  "command evaluates against the SfM reconstruction's poses in place of them (--method auto keeps "
                  "them; rebuild with it and --force to go back)", file=sys.stderr, flush=True)
    from pipeline.data.ground_truth import find_ground_truth
    for sc in scenes:  # before any scene is built (a build takes minutes)
        find_ground_truth(sc, args.gt_dir)  # a file or folder in the way of its gt.h5: one line, now
    report, failed = {}, {}
    for sc in scenes:
        t0 = time.perf_counter()
        say = (lambda m, n=sc.name: print(f"{n}: {m}", file=sys.stderr, flush=True)) if not (args.quiet or args.json) \
            else None
        total = len(sc.images)
        try:
            gt, path = build_ground_truth(sc, args.gt_dir, conf, force=args.force, progress=say)
        except (ImtuneError, OSError) as e:  # this scene failed (too few posed images, SfM, COLMAP, its work folder):
            # the other scenes are still built
            msg = str(e) if isinstance(e, ImtuneError) else f"cannot build its ground truth ({e})"
            failed[sc.name] = msg if msg.startswith(f"scene {sc.name}:") else f"scene {sc.name}: {msg}"
            report[sc.name] = {"error": failed[sc.name]}
            continue
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
    for msg in failed.values():  # one line per scene not built (those built above are kept)
        print(f"tune: error: {msg}", file=sys.stderr)
    return 2 if failed else 0
