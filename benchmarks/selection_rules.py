"""Selection rules: which of `--select best | one-se | smooth | lower-bound` generalises best, and which Strecha
families to validate on.

Leave-one-family-out on the six Strecha scenes in four families (fountain-P11; entry-P10; Herz-Jesus-P8 + P25;
castle-P19 + P30: a family stays on one side, its scenes share images or a facade): for each held-out family, one
study tunes eta, r and Gamma on the other families' validation pairs (the tuner's own objective, TPE, median
pruner, budget B), then each rule (``tuner.select``) picks a trial from the *same* trials, and that trial's
configuration is evaluated on the held-out family's pairs. The untuned paper defaults (r 0.85 both, eta 0.5 px,
Gamma 50k) are evaluated on the same pairs, and each rule's pick is compared with them by the paired bootstrap.
``--folds halves`` tunes on two families and tests on the other two (the six splits of four families: the
measurement behind the default split, pipeline.data.STRECHA_VAL_FAMILIES); ``--folds scenes`` is the earlier
leave-one-scene-out over fountain-P11, Herz-Jesus-P8 and entry-P10.

    python benchmarks/selection_rules.py --trials 14 --max-pairs 15 --test-max-pairs 25 --first-seed 0 --json f0.json
    python benchmarks/selection_rules.py --folds halves --trials 14 --max-pairs 15 --test-max-pairs 25 --json h0.json
    python benchmarks/selection_rules.py --combine f0.json f1.json   # the folds of several runs together

Prints per fold and rule: the frozen trial, its validation mAA(10) [95% interval], the held-out test mAA(10)
[interval], the drop (validation - test) and the difference to the paper defaults [interval]; then the held-out
mAA(10) per fold and rule beside the paper defaults, per rule the mean test mAA(10) over folds, the mean drop and
the folds won, and the winner (highest mean test mAA(10); ties: the smaller mean drop), and each other rule's
fold-by-fold difference to the winner with an exact sign-flip p. A fold's Gamma_max comes from a timing
calibration, so two runs of the same seed are different studies (their folds are pooled as separate folds).
``--json`` is rewritten after every fold (an interrupted run keeps what it measured).

Measured: benchmarks/results/default-split-and-freeze-rules.md (December 2026, six scenes) and, for the earlier three-scene data (before December 2026), the docs'
"How sure a number is" (15 folds: best 0.678, one-se 0.671, smooth 0.650).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SCENES = ("fountain-P11", "Herz-Jesus-P8", "entry-P10")  # --folds scenes: the three scenes of before
#: --folds families (the default): the six Strecha scenes in four families; a family stays on one side of a split
#: (castle-P19 / P30 share 11 byte-identical images, Herz-Jesus-P8 / P25 show the same facade)
FAMILIES = {"fountain": ("fountain-P11",), "entry": ("entry-P10",), "Herz-Jesus": ("Herz-Jesus-P8", "Herz-Jesus-P25"),
            "castle": ("castle-P19", "castle-P30")}


def _f(v, ci=None) -> str:
    if v is None:
        return "-"
    return f"{v:.3f}" + (f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="the Strecha folder (default: ../shared/data/strecha)")
    ap.add_argument("--feature", default="sift")
    ap.add_argument("--num-features", type=int, default=2000)
    ap.add_argument("--ransac", default="degensac")
    ap.add_argument("--folds", choices=("families", "halves", "scenes"), default="families",
                    help="leave one family out (six scenes, four families), test on two families after tuning on "
                         "the other two (halves: 6 folds), or leave one scene out (the three scenes of before)")
    ap.add_argument("--only", nargs="+", default=None, metavar="FOLD", help="run only these held-out folds")
    ap.add_argument("--trials", type=int, default=24, help="trials per study (one study per fold and seed)")
    ap.add_argument("--max-pairs", type=int, default=15, help="validation pairs per scene (0 = all)")
    ap.add_argument("--test-max-pairs", type=int, default=0, help="test pairs of the held-out scene (0 = all)")
    ap.add_argument("--seeds", type=int, default=1, help="studies per fold (seeds first-seed .. first-seed + N - 1)")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--combine", nargs="+", default=None, metavar="JSON",
                    help="print the table of the folds of earlier --json outputs together (no tuning)")
    ap.add_argument("--budget", type=float, default=0.5)
    ap.add_argument("--cache", default=None)
    ap.add_argument("--workdir", default=None, help="storage and studies folder (default: a temporary one)")
    ap.add_argument("--json", default=None, help="also write every figure to this JSON file")
    args = ap.parse_args(argv)
    if args.combine:
        rows = []
        for f in args.combine:  # folds of different files are different folds (calibration, trials differ)
            rows += [{**r, "file": r.get("file") or f} for r in json.loads(Path(f).read_text())["rows"]]
        from tuner.select import RULES
        print(f"{len(args.combine)} result files, {len(rows) // len(RULES)} folds")
        return table(rows, "combined: " + ", ".join(args.combine), key=lambda r: (r["held_out"], r["seed"], r.get("file")))

    import warnings
    warnings.filterwarnings("ignore")
    import optuna

    from pipeline.cache import H5Cache
    from pipeline.config_files import pipeline_from_dict
    from tuner.freeze import frozen_from_study, run_test
    from tuner.select import RULES, select_trial
    from tuner.study import TuneSettings, _quiet_optuna, tune
    _quiet_optuna()
    root = Path(args.data) if args.data else Path(__file__).resolve().parents[2] / "shared" / "data" / "strecha"
    folds = FAMILIES if args.folds == "families" else {s: (s,) for s in SCENES}
    if args.folds == "halves":  # validate on two families, test on the other two (each split of the four, both ways)
        from itertools import combinations
        folds = {"+".join(k for k in FAMILIES if k not in v): tuple(s for k in FAMILIES if k not in v
                                                                   for s in FAMILIES[k])
                 for v in combinations(FAMILIES, 2)}
    if args.only:
        folds = {k: v for k, v in folds.items() if k in args.only}
    needed = [s for g in (FAMILIES if args.folds in ("families", "halves") else {s: (s,) for s in SCENES}).values() for s in g]
    if not all((root / s).is_dir() for s in needed):
        print(f"selection_rules: the Strecha scenes {', '.join(needed)} are not all in {root} (give --data)",
              file=sys.stderr)
        return 2
    all_scenes = needed
    work = Path(args.workdir or tempfile.mkdtemp(prefix="imtune-select-"))
    work.mkdir(parents=True, exist_ok=True)
    storage = f"sqlite:///{work / 'selection.db'}"
    cache = H5Cache(args.cache)
    base = pipeline_from_dict({"feature": {"name": args.feature, "num_features": args.num_features},
                               "geometry": {"ransac": args.ransac}})
    t_all = time.perf_counter()
    rows = []
    for held, held_scenes in folds.items():
        val = [s for s in all_scenes if s not in held_scenes]
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            name = f"loso-{held}-s{seed}-{args.feature}{args.num_features}-{args.ransac}"
            t0 = time.perf_counter()
            s = TuneSettings(base=base, data_root=root, study_name=name, storage=storage, studies_dir=work,
                             n_trials=args.trials, seed=seed, budget=args.budget, val_scenes=val, test_scenes=list(held_scenes),
                             max_pairs=args.max_pairs or None, cache_dir=args.cache, calibration_pairs=6,
                             progress=False, test=False, log=lambda m: None)
            tune(s)
            study = optuna.load_study(study_name=name, storage=storage)
            tune_s = time.perf_counter() - t0
            tested: dict[int, dict] = {}  # trial number -> test result (rules often agree)
            ref = None
            for rule in RULES:
                trial, info = select_trial(study, rule)
                frozen = frozen_from_study(study, rule)
                if trial.number not in tested:
                    tested[trial.number] = run_test(frozen, root, None, scenes=list(held_scenes), cache=cache, runs=1,
                                                    max_pairs=args.test_max_pairs or None,
                                                    reference="paper" if ref is None else "none")
                    if ref is None:
                        r0 = tested[trial.number]["reference"]
                        ref = {"mAA10": r0["mAA10"], "mAA10_ci": r0["mean"].get("mAA10_ci"), "runs": r0["runs"],
                               "scenes": r0["mean"].get("scenes")}
                t = tested[trial.number]
                # the paired comparison with the paper defaults on the same held-out pairs
                from tuner.select import compare_reference
                cmp = compare_reference([r.get("pair_errors") for r in ref["runs"]],
                                        [r.get("pair_errors") for r in t["runs"]], 2000)
                v = frozen["validation"]
                row = {"held_out": held, "seed": seed, "rule": rule, "trial": trial.number,
                       "params": frozen["params"], "val": v.get("mAA10"), "val_ci": v.get("mAA10_ci"),
                       "test": t["mean"]["mAA10"], "test_ci": t["mean"].get("mAA10_ci"),
                       "drop": v.get("mAA10") - t["mean"]["mAA10"],
                       "vs_defaults": cmp["difference"] if cmp else None, "vs_defaults_ci": cmp["ci"] if cmp else None,
                       "defaults": ref["mAA10"], "defaults_ci": ref["mAA10_ci"], "tune_seconds": tune_s,
                       "select_note": info.get("note"), "held_scenes": list(held_scenes),
                       "test_pairs": len(t["runs"][0].get("pair_errors") or []),
                       "test_scenes": {k: v.get("mAA10") for k, v in (t["mean"].get("scenes") or {}).items()},
                       "defaults_scenes": {k: v.get("mAA10") for k, v in (ref.get("scenes") or {}).items()}}
                rows.append(row)
            if args.json:  # every finished fold is kept (a long run interrupted keeps what it measured)
                Path(args.json).write_text(json.dumps({"rows": rows, "args": vars(args)}, indent=2, default=str))
            print(f"fold held-out {held} (seed {seed}): tuned on {', '.join(val)} in {tune_s:.0f} s; "
                  f"paper defaults on {held}: {_f(ref['mAA10'], ref['mAA10_ci'])}", flush=True)
            for r in rows[-len(RULES):]:
                p = r["params"]
                print(f"  {r['rule']:7s} trial {r['trial']:3d} (r {p.get('ratio', float('nan')):.3f}, eta "
                      f"{p.get('threshold', float('nan')):.3g} px, Gamma {int(p.get('max_iters', 0)):,}): val "
                      f"{_f(r['val'], r['val_ci'])} -> test {_f(r['test'], r['test_ci'])}, drop {r['drop']:+.3f}, "
                      f"vs defaults {r['vs_defaults']:+.3f} [{r['vs_defaults_ci'][0]:+.3f}, "
                      f"{r['vs_defaults_ci'][1]:+.3f}]", flush=True)
    for r in rows:
        r["file"] = str(work)
    rc = table(rows, f"{args.feature} {args.num_features}, {args.ransac}, {args.trials} trials, "
                     f"{args.max_pairs or 'all'} validation pairs per scene; studies in {work}; total "
                     f"{time.perf_counter() - t_all:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "args": vars(args)}, indent=2, default=str))
    return rc


def table(rows: list[dict], what: str, key=lambda r: (r["held_out"], r["seed"], r.get("file"))) -> int:
    """Per rule: mean validation and held-out test mAA(10) over the folds, the drop, the difference to the paper
    defaults, folds won; then the winner, and each rule's paired fold-by-fold difference to the winner."""
    import numpy as np

    from tuner.select import RULES
    folds = sorted({key(r) for r in rows}, key=str)
    summary = []
    for rule in RULES:
        rr = [r for r in rows if r["rule"] == rule]
        wins = 0
        for fk in folds:
            here = {r["rule"]: r["test"] for r in rows if key(r) == fk}
            if here[rule] >= max(here.values()) - 1e-12:
                wins += 1
        summary.append({"rule": rule, "mean_test": float(np.mean([r["test"] for r in rr])),
                        "mean_val": float(np.mean([r["val"] for r in rr])),
                        "mean_drop": float(np.mean([r["drop"] for r in rr])),
                        "mean_vs_defaults": float(np.mean([r["vs_defaults"] for r in rr])),
                        "folds_won": wins, "folds": len(folds)})
    print()  # held-out mAA(10) per fold and rule, the paper defaults on the same pairs beside them
    print("| held out (seed) | pairs | " + " | ".join(RULES) + " | paper defaults |")
    print("|---|---:|" + "---:|" * (len(RULES) + 1))
    for fk in folds:
        here = {r["rule"]: r for r in rows if key(r) == fk}
        r0 = next(iter(here.values()))
        print(f"| {r0['held_out']} ({r0['seed']}) | {r0.get('test_pairs', '?')} | "
              + " | ".join(f"{here[rule]['test']:.3f}" if rule in here else "-" for rule in RULES)
              + f" | {r0['defaults']:.3f} |")
    winner = max(summary, key=lambda s: (round(s["mean_test"], 9), -s["mean_drop"]))
    print()
    print("| rule | mean val mAA10 | mean test mAA10 | mean drop (val - test) | mean vs paper defaults | "
          "folds won (ties count for each) |")
    print("|---|---:|---:|---:|---:|---:|")
    for s in summary:
        print(f"| {s['rule']} | {s['mean_val']:.3f} | {s['mean_test']:.3f} | {s['mean_drop']:+.3f} | "
              f"{s['mean_vs_defaults']:+.3f} | {s['folds_won']}/{s['folds']} |")
    print(f"\nwinner: {winner['rule']} (highest mean held-out mAA(10) over {len(folds)} folds; ties: smaller drop); "
          f"{what}")
    w = {key(r): r["test"] for r in rows if r["rule"] == winner["rule"]}
    for rule in RULES:
        if rule == winner["rule"]:
            continue
        d = np.array([r["test"] - w[key(r)] for r in rows if r["rule"] == rule])
        # sign-flip test over folds: is the fold-by-fold difference real? Exact (2^n patterns) for n <= 16, else
        # 200,000 random patterns (seeded: the same p each time)
        n = len(d)
        obs = abs(d.sum())
        pats = np.array(np.meshgrid(*[[-1, 1]] * n)).reshape(n, -1).T if 0 < n <= 16 else \
            np.random.default_rng(0).choice([-1.0, 1.0], size=(200_000, n)) if n else None
        p = float(np.mean(np.abs(pats @ d) >= obs - 1e-12)) if pats is not None else float("nan")
        print(f"  {rule} - {winner['rule']}: mean {d.mean():+.3f} over {n} folds (min {d.min():+.3f}, max "
              f"{d.max():+.3f}), sign-flip p = {p:.2f}" + ("  (not significant)" if p >= 0.05 else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
