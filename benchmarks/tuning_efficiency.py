"""Tuning efficiency: TPE vs the paper's grid search, on the same cached validation data.

The grid is the search space's ``grid`` values of r x eta (8 x 8 = 64 evaluations for the shipped
DEGENSAC-like space) at a fixed iteration cap Gamma; TPE (as `tune` configures it: multivariate,
constant liar, n_startup = n_trials / 5 clipped to 3..10) searches the continuous (r, eta) ranges with
at most a quarter of the grid's evaluations. Target: TPE's best mAA(10) within 1% of the grid optimum.
Every evaluation is the tuner's own objective (all validation pairs, no pruning, estimator seed 0).

    python benchmarks/tuning_efficiency.py                       # sift 2048, degensac, fountain-P11
    python benchmarks/tuning_efficiency.py --num-features 8000 --seeds 5 --max-iters 20000

Prints the grid optimum, per TPE seed the best value, the evaluations TPE needed to come within 1%
(if it did), and the ratio of evaluations used to the grid's.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--scenes", default=None, help="validation scenes (default: the data set's val split)")
    ap.add_argument("--feature", default="sift")
    ap.add_argument("--num-features", type=int, default=2048)
    ap.add_argument("--ransac", default="degensac")
    ap.add_argument("--max-iters", type=int, default=20000, help="Gamma, fixed for grid and TPE")
    ap.add_argument("--max-pairs", type=int, default=None)
    ap.add_argument("--seeds", type=int, default=5, help="TPE runs (seeds 0..N-1)")
    ap.add_argument("--fraction", type=float, default=0.25, help="TPE evaluations as a fraction of the grid's")
    ap.add_argument("--tolerance", type=float, default=0.01, help="relative distance to the grid optimum")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    import optuna

    from pipeline.cache import H5Cache
    from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
    from tuner.evaluate import load_scenes
    from tuner.objective import Objective, ValidationSet
    from tuner.options import resolve_data
    from tuner.space import load_space
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings("ignore")

    root = resolve_data(args.data)
    vs = ValidationSet.from_scenes(load_scenes(root, args.scenes, split="val"), 0.1, args.max_pairs, chunk_pairs=10**9)
    base = PipelineConfig(feature=FeatureConfig(name=args.feature, num_features=args.num_features),
                          matching=MatchConfig(ratio=1.0),
                          geometry=GeometryConfig(ransac=args.ransac, max_iters=args.max_iters, seed=0))
    cache = H5Cache(args.cache)
    vs.prepare(base, cache, progress=True)
    space = load_space(feature=args.feature, estimator=args.ransac, fixes=[f"max_iters={args.max_iters}"])
    space = space.resolve(args.max_iters)
    grid = space.grid()
    n_grid = space.grid_size()
    budget = 1e9  # no budget constraint here: the comparison is about the search, at a fixed Gamma
    objective = Objective(base, space, vs, cache, budget=budget, prune_over_budget=0)

    def run(sampler, n) -> list[float]:
        study = optuna.create_study(direction="maximize", sampler=sampler, pruner=optuna.pruners.NopPruner())
        study.optimize(objective, n_trials=n)
        return [t.value for t in sorted(study.trials, key=lambda t: t.number)]

    t0 = time.perf_counter()
    grid_values = run(optuna.samplers.GridSampler(grid, seed=0), n_grid)
    grid_s = time.perf_counter() - t0
    opt = max(grid_values)
    n_tpe = max(1, int(n_grid * args.fraction))
    target = opt * (1 - args.tolerance)
    runs = []
    for seed in range(args.seeds):
        sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=max(3, min(10, n_tpe // 5)),
                                             multivariate=True, constant_liar=True)
        t0 = time.perf_counter()
        vals = run(sampler, n_tpe)
        best, reached = -1.0, None
        for i, v in enumerate(vals, 1):
            best = max(best, v)
            if reached is None and best >= target:
                reached = i
        runs.append({"seed": seed, "best": best, "evaluations_to_within": reached, "evaluations": len(vals),
                     "seconds": time.perf_counter() - t0, "ratio_to_grid": (reached or len(vals)) / n_grid,
                     "within": reached is not None})
    ok = sum(r["within"] for r in runs)
    out = {"feature": args.feature, "num_features": args.num_features, "ransac": args.ransac,
           "max_iters": args.max_iters, "scenes": vs.scene_names, "pairs": vs.n_pairs,
           "grid": {k: v for k, v in grid.items() if len(v) > 1}, "grid_evaluations": n_grid,
           "grid_optimum": opt, "grid_seconds": grid_s, "tpe_evaluations": n_tpe, "tolerance": args.tolerance,
           "runs": runs, "seeds_within": ok,
           "median_evaluations_to_within": sorted(r["evaluations_to_within"] or 10**9 for r in runs)[len(runs) // 2]}
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{args.feature} {args.num_features}, {args.ransac}, Gamma={args.max_iters}; {vs.n_pairs} pairs of "
          f"{', '.join(vs.scene_names)}")
    print(f"grid search: {n_grid} evaluations ({' x '.join(str(len(v)) for v in grid.values() if len(v) > 1)}), "
          f"optimum mAA(10) = {opt:.4f}  [{grid_s:.0f} s]")
    print(f"TPE: {n_tpe} evaluations per run ({args.fraction:g} of the grid), target >= {target:.4f} "
          f"(within {args.tolerance:.0%})")
    for r in runs:
        used = r["evaluations_to_within"]
        print(f"  seed {r['seed']}: best {r['best']:.4f} ({r['best'] / opt:.3f} x grid optimum); "
              + (f"within {args.tolerance:.0%} after {used} evaluations = {used / n_grid:.3f} of the grid's"
                 if used else "not within the tolerance"))
    med = out["median_evaluations_to_within"]
    print(f"{ok}/{len(runs)} TPE runs within {args.tolerance:.0%} of the grid optimum using <= {n_tpe} evaluations; "
          + (f"median {med} evaluations = {med / n_grid:.3f} of the grid's" if med < 10**9 else "median: not reached"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
