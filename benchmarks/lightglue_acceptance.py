"""Issue 45's acceptance check: ALIKED matched by LightGlue (c 0.1) against ALIKED with the ratio test at its defaults
(r 0.85 mutual), DEGENSAC at the paper defaults (eta 0.5 px, Gamma 50k), on the same pairs of one scene.

    python benchmarks/lightglue_acceptance.py                       # 8000 keypoints (the default), every pair
    python benchmarks/lightglue_acceptance.py --max-pairs 12 --write

It is what `tune evaluate --feature aliked [--matcher lightglue] --ransac degensac --scenes fountain-P11` computes
(both through ``tuner.evaluate.evaluate_config``), compared on the same pairs by `tune compare`'s paired test
(``tuner.compare.compare_records``). ``--max-pairs N``: N pairs evenly spread over the scene (the stereo task's own
subset), for a machine where LightGlue at 8000 keypoints on every pair does not fit; both sides see those pairs.
``--write`` merges the row into ``benchmarks/results/lightglue-acceptance.{md,json}``; ``--render`` only writes the
.md again from the .json, whose ``checks`` list (the acceptance's other checks, each with its command, date and
result, entered by hand) is rendered below the rows.
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


def main(argv=None) -> int:
    from pipeline.config import FeatureConfig
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "strecha"))
    ap.add_argument("--scene", default="fountain-P11")
    ap.add_argument("--num-features", type=int, default=FeatureConfig().num_features)
    ap.add_argument("--max-pairs", type=int, default=None)
    ap.add_argument("--cache", default=None)
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--render", action="store_true", help="only write the .md again from the recorded .json")
    a = ap.parse_args(argv)
    if a.render:
        write(None)
        return 0

    from tuner.compare import compare_records
    from tuner.evaluate import evaluate_config
    common = ["--feature", "aliked", "--ransac", "degensac", "--num-features", str(a.num_features)]
    sides = [("ratio test (r 0.85 mutual)", evaluate_config_of(common)),
             ("LightGlue (c 0.1)", evaluate_config_of([*common, "--matcher", "lightglue"]))]
    assert sides[0][1].matching.ratio == 0.85 and sides[1][1].matching.min_confidence == 0.1, sides
    out = []
    for label, conf in sides:
        t0 = time.perf_counter()
        res = evaluate_config(conf, Path(a.data), [a.scene], cache_dir=a.cache, max_pairs=a.max_pairs,
                              with_pairs=True, jobs=1)
        st = res["stereo"]
        out.append({"label": label, "mAA10": st["mAA10"], "mAA10_ci": st["mAA10_ci"], "pairs": st["pairs"],
                    "NM": st["NM"], "NI": st["NI"], "match_seconds": st["match_seconds"],
                    "seconds": time.perf_counter() - t0, "records": st["pair_records"]})
        print(f"{label:<28} mAA(10) {st['mAA10']:.3f} [{st['mAA10_ci'][0]:.3f}, {st['mAA10_ci'][1]:.3f}]  "
              f"{st['pairs']} pairs  NM {st['NM']:.0f}  NI {st['NI']:.0f}  matching {st['match_seconds']:.2f} s/pair",
              flush=True)
    cmp = compare_records([(o["label"], o["records"]) for o in out], task="stereo")[0]["overall"]
    print(f"LightGlue - ratio test: {cmp['difference']:+.3f} [{cmp['ci'][0]:+.3f}, {cmp['ci'][1]:+.3f}], "
          f"p {cmp['p_value']:.3g}")
    if a.write:
        command = (f"python benchmarks/lightglue_acceptance.py --scene {a.scene} --num-features {a.num_features}"
                   + (f" --max-pairs {a.max_pairs}" if a.max_pairs else "") + " --write")
        row = {"scene": a.scene, "num_features": a.num_features, "max_pairs": a.max_pairs, "command": command,
               "date": _dt.date.today().isoformat(), "sides": [{k: v for k, v in o.items() if k != "records"}
                                                               for o in out],
               "difference": cmp["difference"], "ci": cmp["ci"], "p_value": cmp["p_value"]}
        write(row)
    return 0


def evaluate_config_of(argv: list[str]):
    """The configuration `tune evaluate ARGV` runs, built by that command's own parser (its defaults: r 0.85
    mutual, c 0.1, eta 0.5 px, Gamma 50k, long side 1024 px). Building it by hand from the dataclasses' defaults
    compared LightGlue with mutual nearest neighbours and no ratio test (``MatchConfig.ratio`` defaults to 1)."""
    from tuner.commands.evaluate import config_of, register
    ap = argparse.ArgumentParser()
    register(ap.add_subparsers(dest="command"))
    conf, _ = config_of(ap.parse_args(["evaluate", *argv]))
    return conf


def write(row: dict | None) -> None:
    """Merge ``row`` into the .json (None: keep it as it is) and write the .md from the .json."""
    jpath, mpath = RESULTS / "lightglue-acceptance.json", RESULTS / "lightglue-acceptance.md"
    old = json.loads(jpath.read_text()) if jpath.is_file() else {"rows": []}
    if row is not None:
        keep = [r for r in old["rows"] if (r["scene"], r["num_features"], r["max_pairs"]) !=
                (row["scene"], row["num_features"], row["max_pairs"])]
        old["rows"] = sorted(keep + [row], key=lambda r: (r["scene"], r["num_features"], r["max_pairs"] or 10**9))
        jpath.write_text(json.dumps(old, indent=2) + "\n")
    lines = ["# Acceptance check: ALIKED + LightGlue against ALIKED + the ratio test at its defaults", "",
             "Written by `benchmarks/lightglue_acceptance.py`; DEGENSAC eta 0.5 px, Gamma 50k; mAA(10) with its 95% "
             "interval (bootstrap over pairs), the difference by the paired test of `tune compare`.", "",
             "<!-- --8<-- [start:check] -->",
             "| scene | keypoints | pairs | ratio test | LightGlue | LightGlue - ratio test | p |",
             "| --- | ---: | ---: | --- | --- | --- | ---: |"]
    for r in old["rows"]:
        rt, lg = r["sides"]
        lines.append(f"| {r['scene']} | {r['num_features']} | {rt['pairs']} | {rt['mAA10']:.3f} "
                     f"[{rt['mAA10_ci'][0]:.3f}, {rt['mAA10_ci'][1]:.3f}] | {lg['mAA10']:.3f} "
                     f"[{lg['mAA10_ci'][0]:.3f}, {lg['mAA10_ci'][1]:.3f}] | {r['difference']:+.3f} "
                     f"[{r['ci'][0]:+.3f}, {r['ci'][1]:+.3f}] | {r['p_value']:.3g} |")
    lines += ["", "Commands and dates: " + "; ".join(f"`{r['command']}` ({r['date']})" for r in old["rows"]) + ".",
              "<!-- --8<-- [end:check] -->", "", "Matches, inliers and matching seconds per pair (a shared machine):",
              "", "| scene | keypoints | pairs | side | NM | NI | matching s / pair |",
              "| --- | ---: | ---: | --- | ---: | ---: | ---: |"]
    for r in old["rows"]:
        for s in r["sides"]:
            lines.append(f"| {r['scene']} | {r['num_features']} | {s['pairs']} | {s['label']} | {s['NM']:.0f} | "
                         f"{s['NI']:.0f} | {s['match_seconds']:.2f} |")
    if old.get("checks"):
        lines += ["", "The acceptance's other checks (each run's command, date and result):", ""]
        for c in old["checks"]:
            lines.append(f"- {c['check']}: `{c['command']}` ({c['date']}): {c['result']}")
    mpath.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
