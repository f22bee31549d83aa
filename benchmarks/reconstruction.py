"""Reconstruction task benchmark (issue 39): the mapping time per dataset of pycolmap's incremental and global
(GLOMAP) mappers, side by side in one run on the same verified pairs, and their ratio; the figures of each.

    python benchmarks/reconstruction.py                                   # ../shared/data/imc2025, 8k SIFT
    python benchmarks/reconstruction.py --num-features 2048 --repeat 2    # quicker; medians of 2

Features, k-NN tables and the verification by our estimator (DEGENSAC, the paper's defaults r 0.8, eta 0.5 px) run
once per dataset (cached); then the two mappers map the same database, alternating ``--repeat`` times. Printed per
dataset: pairs verified, wall seconds of each mapper (median), the global / incremental ratio, and the score, mAA,
clusterness, clusters and registered fraction of each. Ratios only are stable on a shared machine.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "imc2025"))
    ap.add_argument("--datasets", default=None, help="comma-separated datasets (default: all)")
    ap.add_argument("--num-features", type=int, default=8000)
    ap.add_argument("--ratio", type=float, default=0.8)
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--workers", type=int, default=None, help="pair processes and COLMAP threads (default: CPUs)")
    ap.add_argument("--repeat", type=int, default=1, help="alternate the two mappers this many times; medians")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)

    import dataclasses

    from pipeline import colmap_db as cdb
    from pipeline.cache import H5Cache
    from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
    from pipeline.cpus import available_cpus
    from pipeline.data import list_scenes, load_scene
    from pipeline.data.resize import scaled_K
    from pipeline.tasks.prepare import image_features
    from pipeline.tasks.reconstruction import (
        ReconstructionConfig,
        ReconstructionTask,
        clusters_from_models,
        map_dataset,
        score_rows,
        submission_rows,
        verify_all,
    )

    conf = PipelineConfig(feature=FeatureConfig(num_features=a.num_features), matching=MatchConfig(ratio=a.ratio),
                          geometry=GeometryConfig(threshold=a.threshold))
    cache = H5Cache(a.cache)
    workers = a.workers or available_cpus()
    names = a.datasets.split(",") if a.datasets else list_scenes(a.data)
    out: dict = {"cpus": available_cpus(), "workers": workers, "datasets": {}}
    for ds in names:
        sc = load_scene(a.data, ds)
        task = ReconstructionTask()
        t0 = time.perf_counter()
        feats = {n: image_features(cache, im, conf.feature) for n, im in sc.images.items()}
        pairs = task.pairs_of(sc, feats)
        verified = verify_all(cache, dict(sc.images), conf, pairs, workers)
        prep = time.perf_counter() - t0
        images = []
        for n, im in sc.images.items():
            f = feats[n]
            K = None if im.K is None else scaled_K(im.K, f.sx, f.sy)
            images.append((n, cdb.make_camera(f.width, f.height, K, "colmap", im.path), f.keypoints))
        res: dict = {"images": len(sc.images), "pairs": len(pairs), "prepare_seconds": prep}
        times: dict[str, list[float]] = {"incremental": [], "global": []}
        for _ in range(a.repeat):
            for mapper in ("incremental", "global"):
                rc = dataclasses.replace(ReconstructionConfig(), mapper=mapper)
                with tempfile.TemporaryDirectory(prefix="imtune-bench-") as tmp:
                    models, failure, dt = map_dataset(Path(tmp), images, verified, conf, rc, threads=workers)
                    clusters = clusters_from_models(models, list(sc.images), conf.mapper.min_model_size)
                times[mapper].append(dt)
                s = score_rows(sc, submission_rows(ds, list(sc.images), clusters))
                reg = {n for c in clusters.values() for n in c}
                res[mapper] = {"score": s.score, "mAA": s.mAA, "clusterness": s.clusterness,
                               "clusters": len(clusters), "registered": len(reg) / len(sc.images), "failure": failure}
        for mapper, ts in times.items():
            res[mapper]["map_seconds"] = statistics.median(ts)
            res[mapper]["map_seconds_all"] = ts
        res["global_over_incremental"] = res["global"]["map_seconds"] / max(res["incremental"]["map_seconds"], 1e-9)
        out["datasets"][ds] = res
        if not a.json:
            print(f"{ds}: {res['images']} images, {res['pairs']} pairs verified (features, k-NN, RANSAC: "
                  f"{prep:.0f} s)")
            for mapper in ("incremental", "global"):
                r = res[mapper]
                print(f"  {mapper:<11} map {r['map_seconds']:7.1f} s   score {r['score']:.3f}  mAA {r['mAA']:.3f}  "
                      f"clusterness {r['clusterness']:.3f}  clusters {r['clusters']}  registered "
                      f"{100 * r['registered']:.0f}%")
            print(f"  global / incremental mapping time: {res['global_over_incremental']:.2f} x")
    if a.json:
        print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
