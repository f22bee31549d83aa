"""The IMC 2025 baseline beside COLMAP out of the box (issue 45): both named reference pipelines of the
reconstruction task on the same datasets, at the same keypoint count, scored with the challenge's metric.

    python benchmarks/imc2025_baseline.py --data ../shared/data/imc2023_heritage --num-features 1024 --write
    python benchmarks/imc2025_baseline.py --data ../shared/data/imc2025 --num-features 1024 --write

Rows: "COLMAP out of the box" is ``--reference colmap`` (COLMAP's SIFT, exhaustive matching, its verification, its
incremental mapper at min_model_size 3 and max_num_models 25); "IMC 2025 baseline" is ``--reference
imc2025-baseline`` (ALIKED + LightGlue, COLMAP's verification at pycolmap's defaults, the same mapper), both at
``--num-features``. One evaluation each, COLMAP's seed ``--seed``. The wall seconds include whatever was not in
the cache (features, LightGlue's output per pair, COLMAP's database): read them as this run's, on a shared
machine. ``--write`` merges the rows into ``benchmarks/results/imc2025-baseline.{md,json}`` (rows of other
datasets or keypoint counts are kept).
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"
PIPELINES = (("colmap", "COLMAP out of the box"), ("imc2025-baseline", "IMC 2025 baseline"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "imc2023_heritage"))
    ap.add_argument("--num-features", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=2, help="COLMAP threads")
    ap.add_argument("--seed", type=int, default=0, help="COLMAP's seed")
    ap.add_argument("--only", default=None, choices=[p for p, _ in PIPELINES])
    ap.add_argument("--cache", default=None)
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/imc2025-baseline.{md,json}")
    a = ap.parse_args(argv)

    from pipeline.cache import H5Cache
    from pipeline.config import FeatureConfig, PipelineConfig
    from pipeline.data import list_scenes, load_scene
    from pipeline.tasks.reconstruction import ReconstructionTask
    cache = H5Cache(a.cache)
    conf = PipelineConfig(feature=FeatureConfig(name="colmap-sift", num_features=a.num_features))
    command = (f"python benchmarks/imc2025_baseline.py --data ../shared/data/{Path(a.data).name} --num-features "
               f"{a.num_features} --seed {a.seed} --workers {a.workers}" + (f" --only {a.only}" if a.only else "")
               + " --write")
    rows = []
    for ds in list_scenes(a.data):
        sc = load_scene(a.data, ds)
        for pipe, label in PIPELINES:
            if a.only and pipe != a.only:
                continue
            task = ReconstructionTask({"pipeline": pipe, "seed": a.seed}, workers=a.workers)
            t0 = time.perf_counter()
            res = task.evaluate([sc], conf, cache)
            s = res.scenes[ds]
            row = {"dataset": ds, "pipeline": pipe, "label": label, "num_features": a.num_features,
                   "score": s["score"], "mAA": s["mAA"], "clusterness": s["clusterness"],
                   "registered": s["registered"], "clusters": s["clusters"], "pairs": s["pairs"],
                   "seconds": time.perf_counter() - t0, "seed": a.seed, "command": command,
                   "date": _dt.date.today().isoformat()}
            rows.append(row)
            print(f"{ds:<34} {label:<22} {a.num_features:>5} kp  score {s['score']:.3f}  mAA {s['mAA']:.3f}  "
                  f"clusterness {s['clusterness']:.3f}  registered {100 * s['registered']:3.0f}%  "
                  f"clusters {s['clusters']}  {row['seconds']:6.0f} s", flush=True)
            if a.write:  # after every row: a long run that is stopped keeps what it measured
                write(rows)
    return 0


def write(rows: list[dict]) -> None:
    """Merge ``rows`` into the results files: a row replaces the row of the same dataset, pipeline and keypoint
    count; the others are kept."""
    jpath, mpath = RESULTS / "imc2025-baseline.json", RESULTS / "imc2025-baseline.md"
    old = json.loads(jpath.read_text()) if jpath.is_file() else {"rows": []}
    merged = {(r["dataset"], r["pipeline"], r["num_features"]): r for r in old["rows"]}
    merged.update({(r["dataset"], r["pipeline"], r["num_features"]): r for r in rows})
    order = [p for p, _ in PIPELINES]
    old["rows"] = sorted(merged.values(), key=lambda r: (r["dataset"], r["num_features"], order.index(r["pipeline"])))
    jpath.write_text(json.dumps(old, indent=2) + "\n")
    lines = ["# The IMC 2025 baseline beside COLMAP out of the box", "",
             "Written by `benchmarks/imc2025_baseline.py` (each row's command and date below); the challenge's "
             "score, mAA and clusterness; one evaluation each (no interval: see the Reconstruction page).", "",
             "<!-- --8<-- [start:scores] -->",
             "| dataset | pipeline (keypoints) | score | mAA | clusterness | registered | clusters |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in old["rows"]:
        lines.append(f"| `{r['dataset']}` | {r['label']} ({r['num_features']}) | {r['score']:.3f} | {r['mAA']:.3f} | "
                     f"{r['clusterness']:.3f} | {100 * r['registered']:.0f}% | {r['clusters']} |")
    lines += ["", "Commands and dates: " + "; ".join(sorted({f"`{r['command']}` ({r['date']})"
                                                           for r in old["rows"]})) + ".",
              "<!-- --8<-- [end:scores] -->", "", "Wall seconds of each row (whatever was not cached, on a shared "
              "machine):", "", "| dataset | keypoints | pipeline | wall s |", "| --- | ---: | --- | ---: |"]
    for r in old["rows"]:
        lines.append(f"| `{r['dataset']}` | {r['num_features']} | {r['label']} | {r['seconds']:.0f} |")
    mpath.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
