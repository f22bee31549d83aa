"""Where the reconstruction task lost to COLMAP out of the box (issue 44): each suspected cause changed alone from
the defaults before the fix, the new defaults, and the COLMAP reference, scored with the challenge's metric.

    python benchmarks/reconstruction_causes.py --data ../shared/data/imc2023_heritage
    python benchmarks/reconstruction_causes.py --data ../shared/data/imc2025 --write

Every row is one evaluation of the dataset (pycolmap's incremental mapper, seed ``--seed``); "before" is the
reconstruction task at imtune's defaults before issue 44 (OpenCV SIFT, r 0.85 mutual, DEGENSAC eta 0.5 px, Gamma
50,000, a 10-image shortlist above 30 images, 15 inliers, F written as an uncalibrated geometry, COLMAP's
``max_num_models`` 50). Each cause row changes one thing from "before"; "new defaults" is the task's defaults now;
"COLMAP reference" is ``--reference colmap`` (COLMAP's SIFT, exhaustive matching, its verification, its mapper at
min_model_size 3 and max_num_models 25). Verified pairs are shared between rows that change only what follows
verification (the task's in-memory cache). ``--write`` writes ``benchmarks/results/reconstruction-causes.md`` and
``.json`` (rows of earlier datasets in those files are kept).
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"


def variants(nf: int):
    """(cause, what changes, configuration changes, task options) rows, "before" first."""
    from pipeline.config import FeatureConfig, GeometryConfig, MapperConfig, MatchConfig, PipelineConfig
    before = PipelineConfig(feature=FeatureConfig(name="sift", num_features=nf), matching=MatchConfig(ratio=0.85),
                            geometry=GeometryConfig(threshold=0.5, max_iters=50_000),
                            mapper=MapperConfig(max_num_models=50, init_min_num_inliers=100,
                                                abs_pose_min_num_inliers=30))  # pycolmap's, as before issue 44
    rc0 = {"shortlist": 10, "verifier": "ours", "two_view": "F", "pipeline": "imtune"}

    def with_(section: str, **kw):
        return dataclasses.replace(before, **{section: dataclasses.replace(getattr(before, section), **kw)})
    from pipeline.tasks.reconstruction import NEW_DEFAULTS, ReconstructionConfig
    new = dataclasses.replace(before, feature=dataclasses.replace(before.feature, name=NEW_DEFAULTS["feature"]),
                              geometry=dataclasses.replace(before.geometry, threshold=NEW_DEFAULTS["threshold"],
                                                           max_iters=NEW_DEFAULTS["max_iters"]),
                              mapper=MapperConfig())
    rows = [
        ("before", "imtune's defaults before issue 44", before, rc0),
        ("eta", "eta 0.5 -> 4 px (COLMAP verifies at 4 px)", with_("geometry", threshold=4.0), rc0),
        ("two-view geometry", "F -> COLMAP's two-view estimation on our inliers (E / H / F)", before,
         {**rc0, "two_view": "colmap"}),
        ("verification", "our DEGENSAC -> COLMAP's verification of our tentative matches", before,
         {**rc0, "verifier": "colmap"}),
        ("shortlist", "10-image shortlist -> exhaustive (all pairs)", before, {**rc0, "shortlist": 0}),
        ("min inliers", "15 -> 10 inliers per pair", with_("mapper", min_inliers=10), rc0),
        ("mapper options", "abs_pose_min_num_inliers 30 -> 15, init_min_num_inliers 100 -> 50",
         with_("mapper", abs_pose_min_num_inliers=15, init_min_num_inliers=50), rc0),
        ("max models", "max_num_models 50 -> 25 (IMC 2025 baseline)", with_("mapper", max_num_models=25), rc0),
        ("features", "OpenCV SIFT (strongest responses) -> COLMAP's SIFT (colmap-sift)",
         with_("feature", name="colmap-sift"), rc0),
        ("new defaults", "the task's defaults now (colmap-sift, eta 1 px, Gamma 10k, shortlist 20, mapper)", new,
         {**rc0, "shortlist": ReconstructionConfig().shortlist}),
        ("COLMAP reference", "--reference colmap", before, {**rc0, "pipeline": "colmap"}),
    ]
    first = ("before", "features", "new defaults", "COLMAP reference")  # the rows that matter most run first
    return sorted(rows, key=lambda r: (r[0] not in first, first.index(r[0]) if r[0] in first else 0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "imc2023_heritage"))
    ap.add_argument("--num-features", type=int, default=2048)
    ap.add_argument("--workers", type=int, default=2, help="pair processes and COLMAP threads")
    ap.add_argument("--seed", type=int, default=0, help="COLMAP's and the estimator's seed")
    ap.add_argument("--only", default=None, help="comma-separated causes to run (default: all)")
    ap.add_argument("--skip", default=None, help="comma-separated causes not to run")
    ap.add_argument("--reuse-before", action="store_true",
                    help="with --only: take the 'before' score from the results file instead of measuring it again")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/reconstruction-causes.{md,json}")
    ap.add_argument("--render", action="store_true", help="only write the .md again from the recorded .json")
    a = ap.parse_args(argv)
    if a.render:
        write_md(json.loads((RESULTS / "reconstruction-causes.json").read_text()), RESULTS / "reconstruction-causes.md")
        return 0

    from pipeline.cache import H5Cache
    from pipeline.config import GeometryConfig
    from pipeline.data import list_scenes, load_scene
    from pipeline.tasks import reconstruction
    from pipeline.tasks.reconstruction import ReconstructionTask
    reconstruction.VERIFIED_KEPT = 16  # every row's verification kept: rows that differ after it share it
    cache = H5Cache(a.cache)
    command = (f"python benchmarks/reconstruction_causes.py --data ../shared/data/{Path(a.data).name} --num-features "
               f"{a.num_features} --seed {a.seed} --workers {a.workers}" + (f" --only '{a.only}'" if a.only else "")
               + (f" --skip '{a.skip}'" if a.skip else "") + (" --reuse-before" if a.reuse_before else "")
               + " --write")
    rows = []
    kept: dict = {}
    only = set(a.only.split(",")) if a.only else None
    skip = set(a.skip.split(",")) if a.skip else set()
    for ds in list_scenes(a.data):
        sc = load_scene(a.data, ds)
        base_score = None
        stored = {}
        jpath = RESULTS / "reconstruction-causes.json"
        if jpath.is_file():
            stored = {r["cause"]: r for r in json.loads(jpath.read_text())["runs"].get(ds, {}).get("rows", [])}
        for cause, what, conf, rc in variants(a.num_features):
            if cause == "before" and only and "before" not in only and "before" in stored and a.reuse_before:
                base_score = stored["before"]["score"]  # --reuse-before: the stored row of the same command
                continue
            if (only and cause not in only and cause != "before") or cause in skip:
                continue
            conf = dataclasses.replace(conf, geometry=dataclasses.replace(conf.geometry, seed=a.seed)) \
                if isinstance(conf.geometry, GeometryConfig) else conf
            task = ReconstructionTask({**rc, "seed": a.seed}, workers=a.workers)
            task._kept = kept  # verified pairs shared by rows that change only what follows verification
            t0 = time.perf_counter()
            res = task.evaluate([sc], conf, cache)
            dt = time.perf_counter() - t0
            s = res.scenes[ds]
            if cause == "before":
                base_score = s["score"]
            row = {"dataset": ds, "cause": cause, "change": what, "before": base_score, "score": s["score"],
                   "mAA": s["mAA"], "clusterness": s["clusterness"], "registered": s["registered"],
                   "clusters": s["clusters"], "pairs": s["pairs"], "seconds": dt}
            rows.append(row)
            if a.write:  # after every row: a long run that is stopped keeps what it measured
                write(rows, command, a)
            print(f"{ds:<18} {cause:<17} score {base_score:.3f} -> {s['score']:.3f}  mAA {s['mAA']:.3f}  "
                  f"registered {100 * s['registered']:3.0f}%  clusters {s['clusters']}  {dt:5.0f} s", flush=True)
    if a.write:
        write(rows, command, a)
    return 0


def write(rows: list[dict], command: str, a) -> None:
    """Merge ``rows`` into the results files (a row replaces the dataset's row of the same cause; other rows are kept)
    and render the markdown table. Every row keeps the command and date that measured it."""
    jpath, mpath = RESULTS / "reconstruction-causes.json", RESULTS / "reconstruction-causes.md"
    old = json.loads(jpath.read_text()) if jpath.is_file() else {"runs": {}}
    date = _dt.date.today().isoformat()
    order = [c for c, *_ in variants(a.num_features)]
    for run in old["runs"].values():
        for r in run["rows"]:  # rows written before rows carried their own command
            r.setdefault("command", run.get("command"))
            r.setdefault("date", run.get("date"))
    for ds in {r["dataset"] for r in rows}:
        run = old["runs"].setdefault(ds, {"rows": []})
        mine = {r["cause"]: {**r, "command": command, "date": date, "num_features": a.num_features, "seed": a.seed}
                for r in rows if r["dataset"] == ds}
        merged = {r["cause"]: r for r in run["rows"]}
        merged.update(mine)
        run["rows"] = sorted(merged.values(), key=lambda r: order.index(r["cause"]) if r["cause"] in order else 99)
        for k in ("command", "date", "num_features", "seed", "workers"):
            run.pop(k, None)
    jpath.write_text(json.dumps(old, indent=2) + "\n")
    write_md(old, mpath)


def write_md(old: dict, mpath: Path) -> None:
    """The results page: one table per dataset (a page's width: no dataset column), then every row's command."""
    lines: list[str] = []
    commands: dict[str, list[str]] = {}
    for ds, run in old["runs"].items():
        lines += [f"Dataset `{ds}`:", "", "| cause | change | before | after | registered | clusters |",
                  "| --- | --- | ---: | ---: | ---: | ---: |"]
        for r in run["rows"]:
            lines.append(f"| {r['cause']} | {r['change']} | {r['before']:.3f} | {r['score']:.3f} | "
                         f"{100 * r['registered']:.0f}% | {r['clusters']} |")
            commands.setdefault(f"`{r['command']}`, {r['date']}", []).append(f"{ds}: {r['cause']}")
        lines.append("")
    notes = [f"- {c}: {', '.join(v)}." for c, v in commands.items()]
    mpath.write_text("\n".join(lines) + "\nIncremental mapper; every row's command and date:\n\n" + "\n".join(notes)
                     + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
