"""How far apart two reconstruction settings really are on validation data: each evaluated at several seeds (COLMAP's
seed and the estimator's), the difference with a paired Student t interval over the seeds.

    python benchmarks/reconstruction_noise.py --data /tmp/imc-all --scenes imc2023_heritage,strecha-sparse \\
        --config STUDIES/NAME/frozen.yaml --seeds 0 1 2 3 4 --write

A study scores every trial once, at one seed, and freezes the best of N. When settings differ on validation by less
than the run-to-run noise, the best is partly the luckiest (the winner's curse) and need not transfer to a dataset
the study never saw. This script runs ``tune evaluate --task reconstruction --json`` for the task's defaults and for
``--config`` (a study's frozen.yaml) at each seed, and prints each side's mean and sd over the seeds and frozen -
defaults with its 95% t interval (``--write``: ``benchmarks/results/reconstruction-noise.{json,md}``, one row per
config and scenes, each with its command and date).
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"
NAME = "reconstruction-noise"


def evaluate(a, seed: int, config: str | None) -> float:
    cmd = [sys.executable, "-m", "tuner", "evaluate", "--task", "reconstruction", "--data", a.data, "--scenes",
           a.scenes, "--num-features", str(a.num_features), "--seed", str(seed), "--json", "--quiet"]
    if config:
        cmd += ["--config", config]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise SystemExit(f"tune evaluate failed (exit {r.returncode}): {r.stderr.strip().splitlines()[-1:]}")
    return float(json.loads(r.stdout)["reconstruction"]["score"])


def paired(a: list[float], b: list[float]) -> dict:
    """mean of a - b over seeds, its 95% Student t interval and the t test's p."""
    from pipeline.metrics.replicates import one_sample_t
    mean, ci, _, p = one_sample_t(np.asarray(a) - np.asarray(b))
    return {"difference": mean, "ci": ci, "p_value": p}


def render(rows: list[dict]) -> str:
    out = ["# Run-to-run noise of reconstruction settings on validation data", "",
           "Written by `benchmarks/reconstruction_noise.py`: each setting evaluated at every seed (COLMAP's and the "
           "estimator's), frozen - defaults paired by seed with a 95% Student t interval over the seeds.", "",
           "<!-- --8<-- [start:noise] -->",
           "| datasets | setting | seeds | defaults, mean (sd) | setting, mean (sd) | setting - defaults [95%] | p |",
           "| --- | --- | ---: | --- | --- | --- | ---: |"]
    for r in rows:
        ci = r["comparison"]["ci"]
        p = r["comparison"]["p_value"]
        out.append(f"| {r['scenes'].replace(',', ', ')} | {r['label']} | {len(r['seeds'])} | "
                   f"{np.mean(r['defaults']):.3f} ({np.std(r['defaults'], ddof=1):.3f}) | "
                   f"{np.mean(r['config_scores']):.3f} ({np.std(r['config_scores'], ddof=1):.3f}) | "
                   f"{r['comparison']['difference']:+.3f} [{ci[0]:+.3f}, {ci[1]:+.3f}] | "
                   f"{'?' if p is None else format(p, '.2g')} |")
    out += ["", "Scores by seed and commands:", ""]
    for r in rows:
        out.append(f"- {r['label']} on {r['scenes']}: defaults {', '.join(f'{x:.3f}' for x in r['defaults'])}; "
                   f"setting {', '.join(f'{x:.3f}' for x in r['config_scores'])} (seeds "
                   f"{', '.join(map(str, r['seeds']))}); `{r['command']}`, {r['date']}")
    out.append("<!-- --8<-- [end:noise] -->")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a folder of IMC-format datasets")
    ap.add_argument("--scenes", required=True, help="comma-separated datasets of --data")
    ap.add_argument("--config", required=True, help="the setting compared with the task's defaults (a frozen.yaml)")
    ap.add_argument("--label", default=None, help="the setting's name in the table (default: its study folder)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--num-features", type=int, default=2048)
    ap.add_argument("--write", action="store_true", help=f"merge the row into benchmarks/results/{NAME}.{{md,json}}")
    a = ap.parse_args(argv)
    if len(a.seeds) < 2:
        ap.error("--seeds: give at least two (a spread needs two runs)")
    if not Path(a.config).is_file():
        ap.error(f"--config {a.config}: no such file")
    label = a.label or Path(a.config).resolve().parent.name
    defaults, scores = [], []
    for s in a.seeds:
        defaults.append(evaluate(a, s, None))
        scores.append(evaluate(a, s, a.config))
        print(f"seed {s}: defaults {defaults[-1]:.3f}, {label} {scores[-1]:.3f}", flush=True)
    cmp = paired(scores, defaults)
    print(f"{label} - defaults over {len(a.seeds)} seeds: {cmp['difference']:+.3f} "
          f"[{cmp['ci'][0]:+.3f}, {cmp['ci'][1]:+.3f}], p {cmp['p_value']}")
    row = {"label": label, "scenes": a.scenes, "seeds": a.seeds, "defaults": defaults, "config_scores": scores,
           "comparison": cmp, "config": a.config, "date": _dt.date.today().isoformat(),
           "command": "python benchmarks/reconstruction_noise.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    if a.write:
        jpath = RESULTS / f"{NAME}.json"
        rows = json.loads(jpath.read_text())["rows"] if jpath.is_file() else []
        rows = [r for r in rows if (r["label"], r["scenes"]) != (label, a.scenes)] + [row]
        jpath.write_text(json.dumps({"rows": rows}, indent=2) + "\n")
        (RESULTS / f"{NAME}.md").write_text(render(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
