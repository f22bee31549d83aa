"""Seconds per evaluation of the reconstruction task, features and k-NN tables cached (issue 44's target: the 76-image
dataset at 2048 features in at most 60 s on 2 cores): the defaults before issue 44 and the task's defaults now, side
by side in one run, and their ratio.

    python benchmarks/reconstruction_speed.py --data ../shared/data/imc2025
    python benchmarks/reconstruction_speed.py --data ../shared/data/imc2025 --write   # results/reconstruction-speed.md

Each configuration is first evaluated once to fill the caches (features, k-NN tables; not timed), then evaluated
``--repeat`` times by a fresh task (no verified pairs in memory: every evaluation verifies every pair and maps), and
the median wall time is printed with the phases (features read, verification, mapping). Absolute seconds on a shared
machine move by 50%; the ratio, measured in the same run, is the figure to read.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"


def configs(nf: int) -> dict:
    from pipeline.config import FeatureConfig, GeometryConfig, MapperConfig, MatchConfig, PipelineConfig
    from pipeline.tasks.reconstruction import NEW_DEFAULTS, ReconstructionConfig
    before = PipelineConfig(feature=FeatureConfig(name="sift", num_features=nf), matching=MatchConfig(ratio=0.85),
                            geometry=GeometryConfig(threshold=0.5, max_iters=50_000),
                            mapper=MapperConfig(max_num_models=50, init_min_num_inliers=100,
                                                abs_pose_min_num_inliers=30))  # pycolmap's, as before issue 44
    g = {k: v for k, v in NEW_DEFAULTS.items() if k in ("threshold", "max_iters")}
    now = dataclasses.replace(before, feature=dataclasses.replace(before.feature, name=NEW_DEFAULTS["feature"]),
                              geometry=dataclasses.replace(before.geometry, **g), mapper=MapperConfig())
    return {"before issue 44": (before, 10), "defaults now": (now, ReconstructionConfig().shortlist)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "imc2025"))
    ap.add_argument("--num-features", type=int, default=2048)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--cache", default=None)
    ap.add_argument("--write", action="store_true")
    a = ap.parse_args(argv)
    from pipeline.cache import H5Cache
    from pipeline.data import list_scenes, load_scene
    from pipeline.tasks.reconstruction import ReconstructionTask
    cache = H5Cache(a.cache)
    out: dict = {"command": f"python benchmarks/reconstruction_speed.py --data ../shared/data/{Path(a.data).name} "
                            f"--num-features {a.num_features} --workers {a.workers} --repeat {a.repeat}"
                            + (" --write" if a.write else ""),
                 "date": _dt.date.today().isoformat(), "datasets": {}}
    for ds in list_scenes(a.data):
        sc = load_scene(a.data, ds)
        res: dict = {}
        for label, (conf, shortlist) in configs(a.num_features).items():
            ReconstructionTask(workers=a.workers, shortlist=shortlist).evaluate([sc], conf, cache)  # caches, not timed
            times, phases, score = [], [], None
            for _ in range(a.repeat):
                t0 = time.perf_counter()
                r = ReconstructionTask(workers=a.workers, shortlist=shortlist).evaluate([sc], conf, cache)
                times.append(time.perf_counter() - t0)
                phases.append(r.seconds)
                score = r.scenes[ds]["score"]
            res[label] = {"seconds": statistics.median(times), "all": times, "phases": phases[-1], "score": score,
                          "feature": conf.feature.name, "eta": conf.geometry.threshold,
                          "Gamma": conf.geometry.max_iters, "shortlist": shortlist}
            p = phases[-1]
            print(f"{ds}: {label:<16} {res[label]['seconds']:6.1f} s  (features {p['features']:.1f}, pairs "
                  f"{p['pairs']:.1f}, mapping {p['mapping']:.1f})  score {score:.3f}", flush=True)
        ratio = res["defaults now"]["seconds"] / res["before issue 44"]["seconds"]
        res["ratio_now_over_before"] = ratio
        print(f"{ds}: defaults now / before issue 44: {ratio:.2f} x")
        out["datasets"][ds] = res
    if a.write:
        (RESULTS / "reconstruction-speed.json").write_text(json.dumps(out, indent=2) + "\n")
        lines = ["| dataset | configuration | seconds | verification | mapping | score |",
                 "| --- | --- | ---: | ---: | ---: | ---: |"]
        for ds, res in out["datasets"].items():
            for label in ("before issue 44", "defaults now"):
                r = res[label]
                lines.append(f"| `{ds}` | {label} ({r['feature']}, eta {r['eta']:g} px, Gamma {r['Gamma']:,}, "
                             f"shortlist {r['shortlist']}) | "
                             f"{r['seconds']:.1f} | {r['phases']['pairs']:.1f} | {r['phases']['mapping']:.1f} | "
                             f"{r['score']:.3f} |")
            lines.append(f"| `{ds}` | ratio now / before | {res['ratio_now_over_before']:.2f} x | | | |")
        (RESULTS / "reconstruction-speed.md").write_text(
            "\n".join(lines) + f"\n\n`{out['command']}`, {out['date']}, features and k-NN tables cached, "
            f"{a.workers} workers on a shared 2-core machine.\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
