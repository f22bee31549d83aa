"""Does the replicated interval of a tuned difference cover the truth? A simulation with known truth.

Two configurations A and B are each tuned over (r, eta, Gamma) -- here the unit cube, x = (r, log eta, log Gamma)
rescaled -- on a synthetic response surface with noisy validation pairs, frozen at the validation optimum and
evaluated on test pairs shared by both and by every replicate:

- true pose accuracy of configuration c at x: q_c(x) = peak_c - curv * ||x - x*_c||^2 (a smooth optimum);
- validation: trial x of a tuning scores mean_j [q_c(x) + d_j + e_{j,x}] over ``val_pairs`` pairs; d_j (the pair's
  difficulty) is shared by every trial and cancels in the argmax, e_{j,x} (estimator seed noise, sd ``seed_sd``)
  is drawn anew per trial: which trial wins is noise -- the tuning variance;
- tuning: ``trials`` trials by random search (or Optuna's TPE, ``--sampler tpe``), the best validation trial frozen;
- test: pair j of replicate k scores q_c(x_k) + t_j + f_{c,j} + g_{c,k,j}: t_j (difficulty, shared by A and B,
  cancels in the paired difference), f (configuration x pair interaction, sd ``pair_sd``: what the pair bootstrap
  covers), g (seed noise per replicate, sd ``seed_sd``); ``test_pairs`` pairs in 3 scenes.

The truth: the expected tuned performance difference E_tuning[q_A(x_A)] - E_tuning[q_B(x_B)], by Monte Carlo over
``truth_tunings`` tunings per configuration (q is known exactly; pair effects have mean 0). Each simulated
comparison tunes K = ``replicates`` replicates of each, and counts whether
:func:`pipeline.metrics.replicates.replicated_difference` (K x N per side) covers it, beside the single-study
interval (replicate 1 of each: K = 1, the pair interval alone: what `tune compare` of two single studies reports).

    python benchmarks/replicate_coverage.py                   # 300 comparisons, random search
    python benchmarks/replicate_coverage.py --sims 200 --sampler tpe

Measured: see benchmarks/results/replicated-tunings-run.md (and the printed table).
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.metrics.replicates import replicated_difference  # noqa: E402


@dataclass(frozen=True)
class Surface:
    """The synthetic problem (scores are mAA-like numbers; sds in the same units)."""
    peak_a: float = 0.74
    peak_b: float = 0.72
    opt_a: tuple = (0.65, 0.35, 0.70)
    opt_b: tuple = (0.45, 0.55, 0.60)
    curv: float = 0.6
    val_pairs: int = 30
    test_pairs: int = 30
    scenes: int = 3
    trials: int = 20
    seed_sd: float = 0.12
    pair_sd: float = 0.08
    difficulty_sd: float = 0.15

    def q(self, c: str, x: np.ndarray) -> np.ndarray:
        """True accuracy of configuration ``c`` at points ``x`` (..., 3)."""
        peak, opt = (self.peak_a, self.opt_a) if c == "a" else (self.peak_b, self.opt_b)
        return peak - self.curv * np.sum((np.asarray(x) - np.asarray(opt)) ** 2, axis=-1)


def tune_random(sf: Surface, c: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` tunings by random search: the frozen x of each (n, 3). The validation score of a trial is q(x) plus the
    mean of its pairs' seed noise (difficulty is shared by all trials and cannot change the argmax)."""
    x = rng.uniform(0, 1, (n, sf.trials, 3))
    val = sf.q(c, x) + rng.normal(0, sf.seed_sd / np.sqrt(sf.val_pairs), (n, sf.trials))
    return x[np.arange(n), val.argmax(axis=1)]


def tune_tpe(sf: Surface, c: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` tunings by Optuna's TPE (seeded from ``rng``), each ``sf.trials`` trials on the noisy validation."""
    import optuna
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    out = []
    for _ in range(n):
        noise = np.random.default_rng(int(rng.integers(2**31)))
        study = optuna.create_study(direction="maximize",
                                    sampler=optuna.samplers.TPESampler(seed=int(rng.integers(2**31)),
                                                                       n_startup_trials=min(10, sf.trials // 2)))

        def objective(trial, noise=noise):
            x = np.array([trial.suggest_float(k, 0, 1) for k in ("r", "eta", "gamma")])
            return float(sf.q(c, x) + noise.normal(0, sf.seed_sd / np.sqrt(sf.val_pairs)))
        study.optimize(objective, n_trials=sf.trials)
        out.append([study.best_params[k] for k in ("r", "eta", "gamma")])
    return np.array(out)


TUNERS = {"random": tune_random, "tpe": tune_tpe}


def true_difference(sf: Surface, tuner, n: int, rng: np.random.Generator) -> tuple[float, float, float]:
    """(E[q_A(x_A)] - E[q_B(x_B)], sd of q_A(x_A), sd of q_B(x_B)) over ``n`` tunings each."""
    qa = sf.q("a", tuner(sf, "a", n, rng))
    qb = sf.q("b", tuner(sf, "b", n, rng))
    return float(qa.mean() - qb.mean()), float(qa.std()), float(qb.std())


def one_comparison(sf: Surface, tuner, k: int, rng: np.random.Generator, n_boot: int) -> dict:
    """One simulated comparison: K replicates of A and of B on the same test pairs; both intervals."""
    n = sf.test_pairs
    strata = np.repeat(np.arange(sf.scenes), int(np.ceil(n / sf.scenes)))[:n]
    t = rng.normal(0, sf.difficulty_sd, n)
    sides = {}
    for c in ("a", "b"):
        x = tuner(sf, c, k, rng)
        f = rng.normal(0, sf.pair_sd, n)
        g = rng.normal(0, sf.seed_sd, (k, n))
        sides[c] = sf.q(c, x)[:, None] + t[None, :] + f[None, :] + g
    rep = replicated_difference(sides["a"], sides["b"], strata, n_boot=n_boot, seed=int(rng.integers(2**31)))
    one = replicated_difference(sides["a"][:1], sides["b"][:1], strata, n_boot=n_boot,
                                seed=int(rng.integers(2**31)))
    return {"rep": (rep.low, rep.high), "one": (one.low, one.high), "p_ab": rep.p_a_beats_b}


def coverage(sf: Surface, sims: int, k: int = 3, sampler: str = "random", seed: int = 0, n_boot: int = 1000,
             truth_tunings: int = 20000) -> dict:
    """Coverage of the truth by the replicated (K replicates) and the single-study interval over ``sims``
    comparisons, and their mean widths."""
    rng = np.random.default_rng(seed)
    tuner = TUNERS[sampler]
    truth, sd_a, sd_b = true_difference(sf, tuner, truth_tunings, rng)
    hits = {"rep": 0, "one": 0}
    widths: dict[str, list] = {"rep": [], "one": []}
    for _ in range(sims):
        r = one_comparison(sf, tuner, k, rng, n_boot)
        for key in hits:
            lo, hi = r[key]
            hits[key] += int(lo <= truth <= hi)
            widths[key].append(hi - lo)
    return {"truth": truth, "tuning_sd_a": sd_a, "tuning_sd_b": sd_b, "sims": sims, "replicates": k,
            "coverage_replicated": hits["rep"] / sims, "coverage_single": hits["one"] / sims,
            "width_replicated": float(np.mean(widths["rep"])), "width_single": float(np.mean(widths["one"]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sims", type=int, default=300, help="simulated comparisons (default 300)")
    ap.add_argument("--replicates", type=int, default=3)
    ap.add_argument("--sampler", choices=list(TUNERS), default="random")
    ap.add_argument("--trials", type=int, default=20, help="trials per tuning (default 20)")
    ap.add_argument("--truth-tunings", type=int, default=None,
                    help="tunings per configuration for the true expected tuned performance (default 20000 random, "
                         "1000 tpe)")
    ap.add_argument("--resamples", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    sf = Surface(trials=a.trials)
    t0 = time.perf_counter()
    r = coverage(sf, a.sims, a.replicates, a.sampler, a.seed, a.resamples,
                 a.truth_tunings or (20000 if a.sampler == "random" else 1000))
    sd_cov = np.sqrt(0.95 * 0.05 / a.sims)
    print(f"tuned difference A - B: truth {r['truth']:+.4f} (tuning sd of the frozen q: A {r['tuning_sd_a']:.4f}, "
          f"B {r['tuning_sd_b']:.4f}); {a.sims} comparisons, {a.sampler} search, {a.trials} trials, "
          f"{sf.val_pairs} validation / {sf.test_pairs} test pairs; binomial sd of a coverage near 0.95: {sd_cov:.3f}")
    print("| interval (95% nominal)              | coverage | mean width |")
    print("|-------------------------------------|---------:|-----------:|")
    print(f"| replicated, K = {a.replicates} per configuration  | {r['coverage_replicated']:8.3f} | "
          f"{r['width_replicated']:10.4f} |")
    print(f"| single study (K = 1, pairs only)    | {r['coverage_single']:8.3f} | {r['width_single']:10.4f} |")
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
