"""`tune data ...`: download the public data sets; list scenes of a data folder."""
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
