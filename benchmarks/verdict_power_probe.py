"""Does "could detect |A - B| >= mde" hold? The power at the median mde in the 27 verdict cells, alone and fast.

The same simulated world and the same two steps as the ``power_at_mde`` column of
``benchmarks/verdict_calibration.py`` (which see for the world): per cell (K_A, K_B in {3, 5}, 8 / 30 / 200 test
pairs, tuning sd small / medium / large), the median ``ReplicatedDifference.mde`` over null data sets in which B is
another method of equal quality, then the share of data sets with the true difference at that median whose test
rejects (p < .05, right sign). Nothing else is computed (no bootstrap, no P(A > B) draws, no figures), so a fresh
seed at 1000 data sets per cell takes about a minute on 2 cores: the check of a change to ``se_at`` / ``df_at`` on
seeds the calibration run does not use.

    python benchmarks/verdict_power_probe.py --sims 1000 --seed 101
    python benchmarks/verdict_power_probe.py --sims 1000 --seed 101 --seed 202 --out benchmarks/results/verdict_power_probe.md
"""
from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.verdict_calibration import (  # noqa: E402
    METHOD_PAIR_SD,
    PAIR_SD,
    PAIRS,
    TUNING_SD,
    bisect,
    draw_side,
    expected,
    scene_means,
    tuning_sd_of,
)
from pipeline.metrics.replicates import replicated_difference, scene_weights  # noqa: E402

KINDS = ((3, 3), (3, 5), (5, 5))


def cell(args) -> tuple:
    ka, kb, n_pairs, sd_name, sims, seed = args
    tau = bisect(tuning_sd_of, TUNING_SD[sd_name], 0.0, 0.6, 30)
    n_scenes, per_scene = PAIRS[n_pairs]
    strata = np.repeat(np.arange(n_scenes), per_scene)
    means = np.repeat(scene_means(n_scenes), per_scene)
    wts = scene_weights(strata)[None, :]
    rng = np.random.default_rng(seed)

    def pair(shift: float):
        b = rng.normal(means, PAIR_SD)
        a = draw_side(rng, b, ka, tau)
        return a * wts, draw_side(rng, b, kb, tau, shift, rng.normal(0, METHOD_PAIR_SD, n_pairs)) * wts

    med = float(np.median([replicated_difference(*pair(0.0), strata).mde for _ in range(sims)]))
    mu = expected(tau, 0.0, n_scenes, False)
    shift = bisect(lambda s: mu - expected(tau, s, n_scenes, True), med, 0.0, 1.5, 40)
    rej = []
    for _ in range(sims):
        d = replicated_difference(*pair(shift), strata)
        rej.append(d.p_value < 0.05 and d.diff > 0)
    return ka, kb, n_pairs, sd_name, med, float(np.mean(rej))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sims", type=int, default=1000, help="data sets per cell and step (default 1000)")
    ap.add_argument("--seed", type=int, action="append", help="seed (repeatable; default 101)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: all CPUs)")
    ap.add_argument("--out", type=Path, help="also write the markdown table there")
    a = ap.parse_args(argv)
    if a.sims < 10:
        print(f"error: --sims {a.sims}: give at least 10 data sets per cell", file=sys.stderr)
        return 2
    seeds = a.seed or [101]
    cells = [(ka, kb, n, sd) for sd in TUNING_SD for n in PAIRS for ka, kb in KINDS]
    res = {}
    with ProcessPoolExecutor(max_workers=max(1, a.jobs)) as ex:
        for s in seeds:
            jobs = [(*c, a.sims, s * 1000 + i) for i, c in enumerate(cells)]
            res[s] = list(ex.map(cell, jobs))
    lines = ["<!-- --8<-- [start:power-probe] -->",
             f"Power at the median \"could detect\" figure, {a.sims} data sets per cell and step, seeds "
             f"{', '.join(map(str, seeds))} (`python benchmarks/verdict_power_probe.py`):", "",
             "| pairs | tuning sd | " + " | ".join(f"{x} vs {y}" for x, y in KINDS) + " |",
             "|" + "---|" * (2 + len(KINDS))]
    for i in range(0, len(cells), len(KINDS)):
        n, sd = cells[i][2], cells[i][3]
        row = [" / ".join(f"{res[s][i + j][5]:.3f}" for s in seeds) for j in range(len(KINDS))]
        lines.append(f"| {n} | {sd} | " + " | ".join(row) + " |")
    for s in seeds:
        p = [r[5] for r in res[s]]
        inside = sum(0.74 <= x <= 0.88 for x in p)
        lines.append(f"\nSeed {s}: {min(p):.3f}-{max(p):.3f}, {inside} of {len(p)} cells within 0.74-0.88.")
    lines.append("<!-- --8<-- [end:power-probe] -->")
    text = "\n".join(lines)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
