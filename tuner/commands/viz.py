"""`tune viz`: the paper's qualitative figures as PNGs, and an HTML gallery of them.

    tune viz --study sift-8000-degensac-stereo          # frozen settings: worst, best, random test pairs
    tune viz --feature sift --ratio 0.85 --ransac degensac --threshold 0.5 --scenes fountain-P11
    tune viz --study NAME --pairs '0000.jpg|0004.jpg,entry-P10:0002.jpg|0005.jpg'
    tune viz --study NAME --pair 0000.jpg 0004.jpg      # the same, without quoting
    tune viz --compare STUDY_A STUDY_B                  # or two YAML / JSON config files
    tune viz --study NAME --task multiview [--bag 5:0]  # a reconstructed bag: keypoints in / not in the model

Configurations: ``--study NAME`` reads ``<studies dir>/<study>/frozen.yaml`` (the validation optimum) and
draws its test scenes (``--split val`` for the validation scenes); ``--config FILE`` reads a YAML or JSON file
(a frozen.yaml, a pipeline dict with feature / matching / geometry sections, flat option names such as
``feature: sift`` / ``ratio: 0.85``, or an official IMC benchmark method JSON); otherwise the pipeline options,
exactly as `tune evaluate` takes them. ``--compare A B``: each of A and B is a config file or a study name.

Output: PNGs in ``--out`` (default ``<studies dir>/<study>/viz`` for a study, else ``./imtune-viz``) and a
gallery, ``gallery.html`` beside them (for a study: ``<studies dir>/<study>/gallery.html``, linked from the
study's ``report.html`` when there is one). Re-running updates the gallery.

Python: ``pipeline.viz.batch.render_pairs / render_compare / render_bags`` and ``pipeline.viz.gallery``;
:func:`viz` below is the whole command as one call.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.errors import ImtuneError
from tuner.argtypes import count_int, seed_int
from tuner.options import (
    add_multiview_options,
    add_pipeline_options,
    build_config,
    multiview_config,
    resolve_data,
    task_choices,
)
from tuner.sources import Source, load_config_source, load_study_source, resolve_source, studies_dir  # noqa: E402,F401

# ---------------------------------------------------------------------------------------------- command

def register(sub) -> None:
    ap = sub.add_parser("viz", help="qualitative figures (matches coloured by error, multiview keypoints), a gallery",
                        description="Draw PNG figures of a configuration (a study's frozen settings, a config file "
                                    "or the pipeline options) and write / update an HTML gallery.")
    add_pipeline_options(ap)
    add_multiview_options(ap)
    s = ap.add_argument_group("what to draw")
    s.add_argument("--study", default=None, help="draw this study's frozen settings (studies/<study>/frozen.yaml)")
    s.add_argument("--config", default=None, help="draw the configuration in this YAML / JSON file")
    s.add_argument("--compare", nargs=2, metavar=("A", "B"), default=None,
                   help="the same pairs for two configurations (each a study name or a config file), side by side")
    s.add_argument("--studies-dir", default=None, help="where studies live (default $IMTUNE_STUDIES, else studies/)")
    s.add_argument("--split", default="test", choices=["val", "test"],
                   help="with --study and no --scenes: the study's test (default) or validation scenes")
    s.add_argument("--task", default=None, choices=task_choices(),
                   help="what to draw (default: the task of --study / a frozen --config, else stereo)")
    s.add_argument("--pairs", default=None, help="comma-separated pairs 'IMAGE1|IMAGE2' or 'SCENE:IMAGE1|IMAGE2' "
                                                 "(quote them: '|' is the shell's pipe)")
    s.add_argument("--pair", nargs=2, action="append", default=None, metavar=("IMAGE1", "IMAGE2"),
                   help="one pair (repeatable); SCENE:IMAGE1 selects the scene")
    s.add_argument("--worst", type=count_int, default=2, help="pairs with the largest pose error (default 2)")
    s.add_argument("--best", type=count_int, default=2, help="pairs with the smallest pose error (default 2)")
    s.add_argument("--random", type=count_int, default=2, help="a random sample of the other pairs (default 2)")
    s.add_argument("--sample-seed", type=seed_int, default=0, help="seed of the random sample of pairs")
    s.add_argument("--num", type=count_int, default=3, help="--compare: the pairs on which A and B differ most (default 3)")
    s.add_argument("--bag", action="append", default=None, metavar="SIZE:INDEX",
                   help="multiview: this bag (repeatable; default the first bag of each size)")
    f = ap.add_argument_group("figures")
    f.add_argument("--out", default=None, help="PNG folder (default studies/<study>/viz, else ./imtune-viz)")
    f.add_argument("--gallery", default=None, help="gallery HTML (default gallery.html beside the PNGs; "
                                                   "studies/<study>/gallery.html for a study)")
    f.add_argument("--no-gallery", action="store_true", help="write the PNGs only")
    f.add_argument("--width", type=int, default=1600, help="figure width in px (default 1600)")
    f.add_argument("--max-lines", type=count_int, default=200, help="at most this many match lines per figure (default 200)")
    f.add_argument("--layout", default="horizontal", choices=["horizontal", "vertical"],
                   help="images side by side (default) or one above the other")
    f.add_argument("--no-depth", action="store_true", help="epipolar distance even where depth maps exist")
    from tuner.options import track_explicit
    track_explicit(ap)  # a pipeline option typed beside --study / --config / --compare is refused, not ignored
    ap.set_defaults(func=run)


def _pair_specs(args) -> list[str]:
    from pipeline.viz.select import parse_pair_specs
    specs = parse_pair_specs(args.pairs)
    for a, b in args.pair or []:
        if ":" in a:
            sc, a = a.split(":", 1)
            specs.append(f"{sc}:{a}|{b}")
        else:
            specs.append(f"{a}|{b}")
    return specs


def _parse_bags(values) -> list[tuple[int, int]] | None:
    if not values:
        return None
    out = []
    for v in values:
        try:
            size, index = (int(x) for x in str(v).split(":"))
        except ValueError:
            raise ImtuneError(f"--bag {v!r}: expected SIZE:INDEX, e.g. 5:0") from None
        if size < 2 or index < 0:
            raise ImtuneError(f"--bag {v!r}: size must be >= 2 and index >= 0")
        out.append((size, index))
    return out


def _scenes_for(args, src: Source | None) -> tuple[Path, list[str] | None, float | None]:
    """Data root, scene names (None: all) and minimum co-visibility for a run."""
    data = (src.frozen or {}).get("data", {}) if src is not None else {}
    if args.data:
        root = resolve_data(args.data)
    elif data.get("root") and Path(data["root"]).is_dir():
        root = Path(data["root"])
    else:
        root = resolve_data(None)
    names = None
    if args.scenes:
        names = [n.strip() for n in args.scenes.split(",") if n.strip()]
    elif data:
        names = list(data.get("test_scenes" if args.split == "test" else "val_scenes") or []) or None
        if names is None and args.split == "test":
            from pipeline.data import default_splits
            names = list(default_splits(root).get("test", [])) or None
    min_cov = args.covisibility
    if src is not None and src.frozen and "min_covisibility" in data and args.covisibility == 0.1:
        min_cov = data["min_covisibility"]
    return root, names, min_cov


def _check_something_to_draw(args: argparse.Namespace, tasks: list[str]) -> None:
    """One line, before any pair is evaluated, for options that draw nothing (every pair was evaluated, then an empty
    gallery written, exit 0) or contradict each other (--gallery with --no-gallery: ignored)."""
    if args.no_gallery and args.gallery:
        raise ImtuneError(f"--gallery {args.gallery} does not apply with --no-gallery (no gallery is written): drop "
                          "one of them")
    from tuner.options import explicit_options
    typed = [o for o in ("worst", "best", "random", "sample_seed", "num") if o in explicit_options(args)]
    picks = "--compare draws the --num pairs on which A and B differ most" if args.compare else \
        "--worst / --best / --random pick the pairs of one configuration"
    for o in typed:  # each was ignored, unsaid, where the pairs are chosen otherwise
        no_pairs = "stereo" not in tasks and not args.compare
        if _pair_specs(args) or no_pairs or (args.compare and o != "num") or (not args.compare and o == "num"):
            how = "--pairs / --pair name the pairs" if _pair_specs(args) else \
                f"--task {args.task} draws multiview bags (--bag)" if no_pairs else picks
            raise ImtuneError(f"--{o.replace('_', '-')} does not apply here: {how}; drop it")
    if _pair_specs(args):
        return
    if args.compare and args.num == 0:
        raise ImtuneError("--num 0 selects no pair to compare: give a count, or --pairs")
    if not args.compare and tasks == ["stereo"] and args.worst + args.best + args.random == 0:
        raise ImtuneError("--worst 0 --best 0 --random 0 selects no pair to draw: give one of them a count, or "
                          "--pairs / --pair")


def _check_outputs(args: argparse.Namespace, out_dir: Path, gallery: Path | None) -> None:
    """The PNG folder and the gallery's folder can be written (or created): a file in the way (``--out`` naming
    an existing file), a read-only or full disk is one line naming the folder, before any work; nothing is
    created."""
    from pipeline.fileio import check_writable_folder
    fix = "give --out a folder that can be written (new or existing)" if args.out else \
        "choose a writable folder with --out DIR"
    check_writable_folder(out_dir, "--out folder" if args.out else "figures folder", fix)
    if gallery is not None and gallery.parent != out_dir:
        check_writable_folder(gallery.parent, "gallery folder",
                              "give --gallery a file in a writable folder, or --no-gallery")
    if gallery is not None and gallery.is_dir():
        raise ImtuneError(f"--gallery {gallery} is a folder; give the path of an HTML file")
    if gallery is not None and args.gallery and gallery.suffix.lower() not in (".html", ".htm"):
        # --gallery studies/S/frozen.yaml (or test.json, an image) was overwritten by the gallery's HTML
        raise ImtuneError(f"--gallery {args.gallery}: tune viz writes the gallery as an HTML page (over what is "
                          f"there); name it .html, e.g. {Path(args.gallery).with_suffix('.html')}")
    from pipeline.viz.gallery import MANIFEST
    if gallery is not None and gallery.with_name(MANIFEST).is_dir():  # found after every figure was drawn
        raise ImtuneError(f"{gallery.with_name(MANIFEST)} is a folder where the gallery keeps its list of figures: "
                          "move it away, or give --gallery another file, or --no-gallery")


def viz(args: argparse.Namespace) -> dict:
    """The whole `tune viz` command as one call on parsed options; returns {"figures": [...], "gallery": path,
    "out": folder, "failures": [...]}."""
    from pipeline.cache import H5Cache
    from pipeline.viz.batch import VizOptions, gallery_entries, render_compare, render_task
    from pipeline.viz.gallery import link_gallery, write_gallery
    from tuner.evaluate import load_scenes
    from tuner.freeze import study_dir
    chosen = [x for x in ("study", "config", "compare") if getattr(args, x)]
    if len(chosen) > 1:
        got = ", ".join("--" + c for c in chosen)
        raise ImtuneError(f"give only one of --study, --config and --compare (got {got})")
    if args.width < 320:
        raise ImtuneError(f"--width must be at least 320 px, got {args.width}")
    from tuner.options import OPTION_FIELDS, explicit_options
    typed = [o for o in OPTION_FIELDS if o in explicit_options(args)]
    if chosen and typed:  # the figures were drawn with the file's / study's settings, the typed one ignored, unsaid
        drawn = {"study": "the study's frozen settings", "config": "the file's settings",
                 "compare": "each configuration's settings"}[chosen[0]]
        raise ImtuneError(f"--{typed[0].replace('_', '-')} does not apply with --{chosen[0]}: tune viz draws {drawn} "
                          "as they are; drop it, or give the pipeline options alone (without --study / --config / "
                          "--compare)")
    sdir = studies_dir(args.studies_dir)
    if args.compare:
        sources = [resolve_source(s, sdir) for s in args.compare]
    elif args.study:
        sources = [load_study_source(args.study, sdir)]
    elif args.config:
        sources = [load_config_source(args.config)]
    else:
        conf = build_config(args)
        from pipeline.config_files import config_label
        sources = [Source(conf, config_label(conf))]
    primary = sources[0]
    if "split" in explicit_options(args) and (args.scenes or not (primary.frozen or {}).get("data")):
        # the split picks a study's scenes: beside --scenes, or for settings without a study's data, it was ignored
        why = "beside --scenes" if args.scenes else "without --study (or a frozen.yaml) naming its scenes"
        raise ImtuneError(f"--split {args.split} chooses a study's validation or test scenes, and does not apply {why}: "
                          "drop it")
    if args.task is None:  # a multiview study's frozen r drawn as stereo pairs with an untuned eta 0.5, unsaid
        args.task = ((primary.frozen or {}).get("task") or "stereo") if not args.compare else "stereo"
    from pipeline.tasks import task_list
    if args.bag and (args.compare or "multiview" not in task_list(args.task)):
        # --bag picks a multiview bag: on stereo pairs or a comparison it was silently ignored
        what = "tune viz --compare draws stereo pairs" if args.compare else f"--task {args.task} draws stereo pairs"
        raise ImtuneError(f"--bag {args.bag[0]} selects a multiview bag, but {what}; add --task multiview "
                          "(or --task both), or drop --bag")
    _check_something_to_draw(args, task_list(args.task))
    from tuner.options import check_multiview_only
    check_multiview_only(args, task_list(args.task))
    study = next((s.study for s in sources if s.study), None)  # a comparison goes to its study's gallery
    if args.out:
        out_dir = Path(args.out).expanduser().resolve()
        gallery = Path(args.gallery).expanduser().resolve() if args.gallery else out_dir / "gallery.html"
    elif study:
        out_dir = study_dir(sdir, study) / "viz"
        gallery = Path(args.gallery).expanduser().resolve() if args.gallery else study_dir(sdir, study) / "gallery.html"
    else:
        out_dir = (Path.cwd() / "imtune-viz").resolve()
        gallery = Path(args.gallery).expanduser().resolve() if args.gallery else out_dir / "gallery.html"
    _check_outputs(args, out_dir, None if args.no_gallery else gallery)  # before any feature is computed
    root, names, min_cov = _scenes_for(args, primary)
    scenes = load_scenes(root, names, split="all", gt_dir=args.gt_dir)
    opts = VizOptions(width=int(args.width), max_lines=int(args.max_lines), layout=args.layout,
                      use_depth=not args.no_depth, seed=int(args.sample_seed))
    cache = H5Cache(args.cache)
    progress = not (args.quiet or args.json)
    specs = _pair_specs(args)
    results, replace = [], set()
    if args.compare:
        results += render_compare(scenes, [(s.conf, s.label) for s in sources], out_dir, cache=cache,
                                  pairs=specs or None, n=args.num, min_covisibility=min_cov, opts=opts,
                                  progress=progress)
    else:
        for name in task_list(args.task):
            figs, rep = render_task(name, scenes, primary.conf, out_dir, cache=cache, pairs=specs or None,
                                    worst=args.worst, best=args.best, random=args.random,
                                    sample_seed=args.sample_seed, min_covisibility=min_cov, label=primary.label,
                                    opts=opts, progress=progress, mv=multiview_config(args),
                                    bags=_parse_bags(args.bag))
            results += figs
            replace |= rep
    failures = [r for r in results if r.get("failure") and not r.get("png")]
    if results and len(failures) == len(results):
        raise ImtuneError(failures[0]["failure"])
    out = {"out": str(out_dir), "gallery": None, "figures": results, "failures": [r["failure"] for r in failures]}
    if not args.no_gallery:
        links = {}
        title = "imtune figures"
        if study:
            title = f"imtune study {study}: qualitative figures"
            report = study_dir(sdir, study) / "report.html"
            if report.is_file() and gallery.parent == report.parent:
                link_gallery(report, gallery.name)
                links["study report"] = "report.html"
        scope = results[0]["config"] if results and replace else None
        write_gallery(gallery, gallery_entries(results, gallery.parent), title=title,
                      replace_sections=tuple(sorted(replace)), scope=scope, links=links)
        out["gallery"] = str(gallery)
    return out


def _line(r: dict) -> str:
    def deg(v):
        return "inf" if v in (None, "inf") else f"{float(v):.2f}"
    if r["section"] == "compare":
        parts = [f"{p['label'].split(':')[0]}: NI {p.get('NI')} err {deg(p.get('err'))}" for p in r["panels"]]
        return f"compare  {r['scene']} {r['pair']}  " + " | ".join(parts) + f"  -> {r['png']}"
    if "bag_size" in r:
        if not r.get("png"):
            return f"multiview {r['scene']} bag {r['bag_size']}#{r['bag']}: {r['failure']}"
        return (f"multiview {r['scene']} bag {r['bag_size']}#{r['bag']}  registered {len(r['registered'])}/"
                f"{len(r['images'])} NL {r['NL']}  -> {r['png']}")
    state = r["failure"] if r.get("failure") else \
        ("no ground truth" if r.get("no_ground_truth") else f"err {deg(r.get('err'))} deg")
    return f"{r['section']:<7} {r['scene']} {r['pair']}  NI {r.get('NI')}  {state}  [{r['error_kind']}]  -> {r['png']}"


def run(args) -> int:
    out = viz(args)
    if args.json:
        print(json.dumps(out, indent=2, default=str))
        return 0
    for r in out["figures"]:
        print(_line(r))
    for msg in out["failures"]:
        print(f"tune viz: warning: {msg}", file=sys.stderr)
    if out["gallery"]:
        print(f"gallery: {out['gallery']}")
    return 0
