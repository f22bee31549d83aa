"""Tuning replicates: K independent tunings of one configuration, each frozen and tested on the same test pairs,
and the tuned figure with an interval that holds the tuning variance (issue 32).

    from tuner.replicates import tune_replicates
    out = tune_replicates(settings, 3)        # studies NAME, NAME-r2, NAME-r3
    out["replicated"]["mAA10"], out["replicated"]["mAA10_ci"]

Replicate 1 is exactly the study ``tune`` runs without ``--replicates`` (same name, same seed); replicate k >= 2 is
the study ``<name>-r<k>`` with seed :func:`replicate_seed` (``--seed`` hashed with k), which seeds its sampler (each
worker deriving its own from it, :mod:`tuner.seeding`) and its estimator. Every replicate uses the same cache (features
and k-NN tables are computed once), the same calibration (``budgets.json`` is keyed without the seed, so every
replicate has the same Gamma_max) and the same test pairs. A rerun of the command resumes: a finished replicate runs no
trial and reuses its test.json; an unfinished one runs its missing trials.

Where it is recorded: the first study's ``test.json`` gets ``replicates`` (one entry per replicate: study, seed, frozen
trial and parameters, test mAA10 with its own interval) and ``replicated`` (the mean over replicates, the two-level
interval, the spread of the frozen r, eta, Gamma). test.json and not a new file: it is the file every reader of a
study's test already opens, and the first study's own figures (``mean``, ``runs``) stay where they were, so a reader
that knows nothing of replicates reads the single study as before (`tune results` and `tune compare` read it there).
The same block is stored in the first study's user attribute ``replicated`` (optuna-dashboard shows it).

The interval (``pipeline.metrics.replicates.replicated_maa_interval``): each replicate's per-pair mAA(10) score
(averaged over its test runs) forms a K x N matrix on the same N test pairs; pair sampling (the single test interval's
scene-stratified bootstrap with pseudo-scores, of the replicate-averaged scores) and the replicate-to-replicate spread
(t-based, s^2 / K) add. With K = 1 it is the pair
interval alone, and every verdict says the tuning variance was not measured.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import textwrap
from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError
from pipeline.metrics.replicates import METHOD, NOT_MEASURED, ReplicatedInterval, replicated_maa_interval, scene_weights

#: the frozen parameters whose spread over replicates is reported (r, eta, Gamma)
SPREAD_PARAMS = ("min_confidence", "ratio", "threshold", "max_iters")  # c: a learned matcher's r
MAX_REPLICATES = 20
REPLICATED_ATTR = "replicated"
INTERVAL_METHOD = METHOD


def replicate_name(name: str, k: int) -> str:
    """The study of replicate ``k`` (1-based): ``name`` for k = 1 (today's study), ``name-r<k>`` after."""
    return name if k == 1 else f"{name}-r{k}"


def replicate_seed(seed: int | None, k: int) -> int | None:
    """Seed of replicate ``k``: ``seed`` itself for k = 1 (so K = 1 is exactly today's run); for k >= 2 the first 31
    bits of sha256("imtune-replicate:<seed>:<k>") (``seed`` None counts as 0: replicate 1 keeps its unseeded
    sampler, the others are seeded so that a rerun resumes them with the same seed). 31 bits: ``--seed``'s range
    (``pipeline.config.SEED_MAX``)."""
    if k == 1:
        return seed
    digest = hashlib.sha256(f"imtune-replicate:{int(seed or 0)}:{int(k)}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def replicate_settings(s, k: int, name: str):
    """``s`` (a ``tuner.study.TuneSettings``) for replicate ``k`` of the study ``name``: its name and seed (the
    pipeline's estimator seed is set from it by ``setup_study``)."""
    seed = replicate_seed(s.seed, k)
    base = dataclasses.replace(s.base, geometry=dataclasses.replace(s.base.geometry, seed=int(seed or 0)))
    return dataclasses.replace(s, study_name=replicate_name(name, k), seed=seed, base=base,
                               name_warnings=s.name_warnings or k > 1, warm_start=list(s.warm_start))


def tune_replicates(s, replicates: int) -> dict:
    """Run (or resume) the ``replicates`` studies of ``s``, each tuned, frozen and tested; returns
    ``{"study": first name, "replicates": [tune()'s dict per replicate], "replicated": summary or None}`` (None when
    a replicate was not tested: --no-test, or trials still running elsewhere). K = 1: today's ``tune`` plus the
    replicated block (which says the tuning variance was not measured)."""
    from tuner.study import study_name, tune
    k_max = int(replicates)
    if not 1 <= k_max <= MAX_REPLICATES:
        raise ImtuneError(f"--replicates {replicates}: give 1 to {MAX_REPLICATES}")
    name = study_name(s)
    from pipeline.tasks import task_class
    unit = task_class(s.task).unit
    if k_max > 1 and unit not in ("pairs", "datasets"):  # before any tuning: what the replicates are combined over
        raise ImtuneError(f"--replicates {k_max}: the {s.task} task is measured on {unit}, and replicates are "
                          "combined over stereo test pairs or reconstruction datasets so far; drop --replicates")
    if k_max > 1 and s.warm_start:
        raise ImtuneError("--warm-start with --replicates: every replicate would start from the same trials and the "
                          "replicates would not be independent tunings; drop one of them")
    outs = []
    for k in range(1, k_max + 1):
        sk = replicate_settings(s, k, name)
        if k_max > 1:
            s.say(f"replicate {k}/{k_max}: study {sk.study_name}, seed {sk.seed}")
        outs.append(tune(sk))
    out = {"study": name, "replicates": outs, "replicated": None}
    if all(o.get("test") for o in outs):
        tests, seeds = [o["test"] for o in outs], [replicate_seed(s.seed, k) for k in range(1, k_max + 1)]
        summary = (dataset_replicated_summary(tests, seeds) if unit == "datasets"
                   else replicated_summary(tests, seeds, n_boot=s.ci_resamples or 2000))
        record_replicated(s.studies_dir, name, summary)
        _store_attr(s, name, summary)
        out["replicated"] = summary
    return out


# -- the figures ----------------------------------------------------------------------------------------------

def _pair_key(p):
    return json.dumps(p) if isinstance(p, (list, tuple)) else str(p)


def score_matrix(tests: list[dict], tau: int = 10, scaled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(K x N per-pair mAA(tau) scores, averaged over each replicate's test runs, with each column scaled so that the
    plain mean is the scene-weighted mean; N scene labels). Why scaled: a test's mAA is the mean over scenes of the
    per-scene mAA, i.e. sum_p w_p s_p with w_p = 1 / (n_scenes n_scene_pairs); multiplying s_p by N w_p makes
    ``scores.mean()`` that figure, and a bootstrap within scenes (sizes kept) of the scaled mean is exactly the
    stratified bootstrap of the weighted one (``scaled`` False: the scores as they are). One-line ImtuneError when the replicates were not tested on the same
    pairs or a test has no per-pair errors."""
    from pipeline.metrics.uncertainty import pair_scores
    rows, keys = [], None
    for t in tests:
        per_run = []
        for r in t.get("runs") or []:
            errs = r.get("pair_errors")
            if errs is None:
                raise ImtuneError(f"study {t.get('study')}: its test.json has no per-pair errors (a multiview or an "
                                  "earlier imtune's test): rerun `tune test --study "
                                  f"{t.get('study')}`; replicates are combined over stereo pairs")
            sc = pair_scores([float("inf") if e[2] in (None, "inf") else float(e[2]) for e in errs], tau)
            per_run.append({(str(e[0]), _pair_key(e[1])): float(v) for e, v in zip(errs, sc)})
        if not per_run:
            raise ImtuneError(f"study {t.get('study')}: its test.json holds no runs")
        k0 = sorted(per_run[0])
        if any(sorted(d) != k0 for d in per_run):
            raise ImtuneError(f"study {t.get('study')}: its test runs scored different pairs")
        if keys is None:
            keys = k0
        elif k0 != keys:
            raise ImtuneError(f"study {t.get('study')} was tested on other pairs than {tests[0].get('study')}: "
                              "replicates are combined on the same test pairs (rerun with the same --test-scenes "
                              "and --max-pairs, or `tune test` each replicate with the same options)")
        rows.append([np.mean([d[key] for d in per_run]) for key in keys])
    assert keys is not None
    scenes = np.array([key[0] for key in keys])
    scores = np.asarray(rows, float)
    return (scores * scene_weights(scenes)[None, :] if scaled else scores), scenes


def replicated_summary(tests: list[dict], seeds: list, *, tau: int = 10, n_boot: int = 2000) -> dict:
    """The ``replicated`` block of test.json from the K replicates' test results (same pairs)."""
    scores, strata = score_matrix(tests, tau, scaled=False)
    iv: ReplicatedInterval = replicated_maa_interval(scores, strata)
    reps = []
    for t, seed in zip(tests, seeds):
        m = t.get("mean") or {}
        reps.append({"study": t.get("study"), "seed": seed, "trial": t.get("trial"), "params": t.get("params"),
                     "mAA10": m.get("mAA10"), "mAA10_ci": m.get("mAA10_ci")})
    spread = {p: {"min": lo, "max": hi} for p, (lo, hi) in param_spread([r.get("params") for r in reps]).items()}
    return {"replicates": reps, "K": len(reps), "mAA10": iv.mean, "mAA10_ci": [iv.low, iv.high],
            "se_pairs": iv.se_pairs, "se_between": iv.se_between,
            "tuning_variance_measured": iv.tuning_variance_measured,
            "note": "" if iv.tuning_variance_measured else NOT_MEASURED, "figure_note": iv.note,
            "spread": spread, "pairs": int(scores.shape[1]), "method": INTERVAL_METHOD, "level": 0.95,
            "reference": reference_comparison(tests, tau=tau, n_boot=n_boot,
                                              tuned=(scores * scene_weights(strata)[None, :], strata))}


def dataset_replicated_summary(tests: list[dict], seeds: list, *, alpha: float = 0.05) -> dict:
    """The ``replicated`` block of a task measured on datasets (reconstruction: the challenge's score per dataset,
    no per-pair errors). Replicate k's figure y_k is its test's mean over datasets and runs; its reference (COLMAP
    out of the box, run beside it at replicate k's seeds) r_k; d_k = y_k - r_k. The K replicates are independent
    draws of the whole procedure (tuning, then test runs at new seeds), so the figure is mean(y) with a Student t
    interval on K - 1 df, and frozen - reference is scipy's one-sample t test of the d_k (K - 1 df). Both hold the
    tuning variance and the run-to-run noise, conditional on the test datasets (they are not a sample of datasets).
    "Could detect" is the difference the test reaches with 80% power at the median-unbiased variance
    (:func:`pipeline.metrics.replicates.detectable`). Why not the pair model of :func:`replicated_summary`: there are
    no pairs, only datasets, and one test dataset is common. A verdict needs K >= 3 (as for pairs)."""
    from pipeline.metrics.replicates import POWER, detectable, median_unbiased, one_sample_t
    k = len(tests)
    named = tests[0].get("objective")  # test.json's {"name": ...}; the reference block names it as a string
    candidates = [(tests[0].get("reference") or {}).get("objective"),
                  named.get("name") if isinstance(named, dict) else named, "score"]
    objective = next((c for c in candidates if isinstance(c, str) and c in (tests[0].get("mean") or {})), "score")
    y = np.array([float((t.get("mean") or {})[objective]) for t in tests])
    datasets = list((tests[0].get("data") or {}).get("scenes") or [])
    if any(list((t.get("data") or {}).get("scenes") or []) != datasets for t in tests):
        raise ImtuneError(f"study {tests[0].get('study')}: its replicates were tested on different datasets; rerun "
                          "them with the same --test-scenes")
    reps = [{"study": t.get("study"), "seed": seed, "trial": t.get("trial"), "params": t.get("params"),
             objective: float(v), "runs": len(t.get("runs") or [])} for t, seed, v in zip(tests, seeds, y)]

    _, ci, se_y, _ = one_sample_t(y, alpha)
    out = {"unit": "datasets", "objective": objective, "replicates": reps, "K": k, objective: float(y.mean()),
           f"{objective}_ci": ci, "se_between": se_y, "datasets": datasets, "tuning_variance_measured": k >= 2,
           "note": "" if k >= 2 else "the tuning variance was not measured (1 replicate)",
           "spread": {p: {"min": lo, "max": hi} for p, (lo, hi) in param_spread([r["params"] for r in reps]).items()},
           "method": "replicates as independent draws: Student t interval on K - 1 df of the replicates' figures; "
                     "frozen - reference by the one-sample t test of the K differences", "level": 1 - alpha,
           "reference": None}
    refs = [t.get("reference") for t in tests]
    if all(isinstance(r, dict) and (r.get("mean") or {}).get(objective) is not None for r in refs):
        r_k = np.array([float(r["mean"][objective]) for r in refs])  # type: ignore[index]
        d = y - r_k
        _, dci, se_d, p = one_sample_t(d, alpha)
        per_ds = {}
        for ds in datasets:
            pairs = [(_dataset_mean(t, ds, objective), _dataset_mean(r, ds, objective)) for t, r in zip(tests, refs)]
            if all(a is not None and b is not None for a, b in pairs):  # a run without the dataset: no figure
                per_ds[ds] = float(np.mean([a - b for a, b in pairs]))  # type: ignore[operator]
        mde = (detectable(se_d * math.sqrt(median_unbiased(k - 1)), k - 1, alpha) if se_d else None)
        if k < 3:
            verdict = f"K = {k}: no verdict (a verdict about tuning needs --replicates 3 or more)"
        elif p is not None and p < alpha:
            verdict = f"significant: the tuned configuration {'beats' if d.mean() > 0 else 'loses to'} the reference"
        else:
            verdict = "inconclusive" + (f": could detect |difference| >= {mde:.3f} ({POWER:.0%} power)"
                                        if mde is not None and math.isfinite(mde) else "")
        out["reference"] = {"label": refs[0].get("label"), objective: float(r_k.mean()),  # type: ignore[union-attr]
                            "difference": float(d.mean()), "ci": dci, "p_value": p, "se": se_d, "df": k - 1,
                            "detectable": mde, "verdict": verdict, "datasets": per_ds,
                            "per_replicate": [float(x) for x in d]}
    return out


def _dataset_mean(test: dict, ds: str, objective: str) -> float | None:
    """A test's (or reference's) mean ``objective`` on dataset ``ds`` over its runs; None where a run lacks it."""
    vals = [((r.get("scenes") or {}).get(ds) or {}).get(objective) for r in test.get("runs") or []]
    if not vals or any(v is None for v in vals):
        return None
    return float(np.mean([float(v) for v in vals]))


def param_spread(params: list) -> dict:
    """{parameter: (min, max)} of the frozen :data:`SPREAD_PARAMS` over the replicates' parameter dicts (a
    replicate without a parameter, or without parameters, is left out of that parameter's range)."""
    out = {}
    for p in SPREAD_PARAMS:
        vals = [x[p] for x in params if isinstance(x, dict) and p in x]
        if vals:
            out[p] = (min(vals), max(vals))
    return out


def reference_comparison(tests: list[dict], *, tau: int = 10, n_boot: int = 2000,
                         tuned: tuple[np.ndarray, np.ndarray] | None = None) -> dict | None:
    """The tuned configuration (its K replicates) against the reference every replicate's test ran beside it (the
    paper defaults unless --reference said otherwise), on the same pairs:
    :func:`pipeline.metrics.replicates.replicated_difference` of tuned - reference (scene-weighted scores), with
    P(tuned > reference) over replicate pairs. The reference's own replicates differ only in their estimator seeds.
    None when a replicate's test has no reference (``--reference none``) or they differ. ``tuned``: the tests' scaled
    :func:`score_matrix`, when the caller has it already."""
    from pipeline.metrics.replicates import difference_block, replicated_difference
    refs = [t.get("reference") for t in tests]
    if not all(isinstance(r, dict) and r.get("runs") for r in refs):
        return None
    def unseeded(r: dict) -> str:  # the reference of replicate k runs with replicate k's estimator seeds
        conf = json.loads(json.dumps(r.get("config") or {}, default=str))
        (conf.get("geometry") or {}).pop("seed", None)
        return json.dumps(conf, sort_keys=True)
    if len({unseeded(r) for r in refs}) != 1:  # type: ignore[arg-type]
        return None
    tuned, strata = tuned if tuned is not None else score_matrix(tests, tau)
    try:
        ref, _ = score_matrix(refs, tau)  # type: ignore[arg-type]
    except ImtuneError:
        return None
    if ref.shape[1] != tuned.shape[1]:
        return None
    d = replicated_difference(tuned, ref, strata, seed=0)
    block = difference_block(d, "tuned", "reference", b_tuned=False)
    block["p_tuned_beats_reference"] = block.pop("p_a_beats_b")
    block["p_tuned_beats_reference_ci"] = block.pop("p_a_beats_b_ci")
    return {"label": refs[0].get("label"), "mAA10": float(ref.mean()), **block}  # type: ignore[union-attr]


def record_replicated(studies_dir, name: str, summary: dict) -> Path:
    """Write ``replicates`` and ``replicated`` into the first study's test.json (atomically), and the study's user
    attribute ``replicated`` when the storage is at hand. Returns the test.json path."""
    from pipeline.fileio import atomic_write
    from tuner.freeze import _plain, load_test_file, study_dir
    path = study_dir(studies_dir, name) / "test.json"
    d, why = load_test_file(path, name, refresh=False)
    if d is None:
        raise ImtuneError(f"{path}: {why or 'missing'}; rerun the command")
    d["replicates"] = summary["replicates"]
    d["replicated"] = {k: v for k, v in summary.items() if k != "replicates"}
    atomic_write(path, json.dumps(_plain(d), indent=2))
    return path


def _store_attr(s, name: str, summary: dict) -> None:
    """The ``replicated`` block (each replicate's study, seed, figure; the mean and interval) in the first study's
    user attribute ``replicated``: what optuna-dashboard shows beside the study."""
    import optuna

    from tuner.freeze import _plain
    from tuner.storage import open_storage
    storage = open_storage(s.storage, heartbeat=None, studies_dir=s.studies_dir)
    block = {k: v for k, v in summary.items() if k != "method"}
    optuna.load_study(study_name=name, storage=storage).set_user_attr(REPLICATED_ATTR, _plain(block))


def load_replicated(studies_dir, name: str) -> dict | None:
    """The ``replicated`` block (with its ``replicates`` list) of study ``name``'s test.json, or None."""
    from tuner.freeze import load_test_file, study_dir
    d, _ = load_test_file(study_dir(studies_dir, name) / "test.json", name, refresh=False)
    return replicated_block(d)


def replicated_block(test: dict | None) -> dict | None:
    """The ``replicated`` block of a test.json's content with its ``replicates`` list, or None when it has none."""
    if not test or not isinstance(test.get("replicated"), dict):
        return None
    return {**test["replicated"], "replicates": test.get("replicates") or []}


def replicate_tests(studies_dir, name: str) -> list[dict] | None:
    """The test results of every replicate of study ``name`` (its test.json's ``replicates``), in order; None when
    the study was not run with replicates. One-line ImtuneError when a replicate's test.json is gone."""
    from tuner.freeze import load_test_file, study_dir
    rep = load_replicated(studies_dir, name)
    if rep is None:
        return None
    out = []
    for r in rep["replicates"]:
        d, why = load_test_file(study_dir(studies_dir, r["study"]) / "test.json", r["study"], refresh=False)
        if d is None:
            raise ImtuneError(f"replicate {r['study']} of {name}: its test.json is {why or 'missing'}; rerun the "
                              "replicated `tune` command")
        out.append(d)
    return out


# -- printing -------------------------------------------------------------------------------------------------

#: the frozen settings a replicate line names, as the pages write them (LightGlue's c takes r's place)
PARAM_LABELS = (("min_confidence", "c"), ("ratio", "r"), ("threshold", "eta"), ("max_iters", "Gamma"))


def _param_text(p: dict | None) -> str:
    if not isinstance(p, dict):
        return "-"
    parts = []
    for k, label in PARAM_LABELS:
        if k in p:
            v = p[k]
            parts.append(f"{label} {v:.3g}" if isinstance(v, float) else f"{label} {v}")
    return ", ".join(parts)


def replicated_text(summary: dict) -> str:
    """Each replicate's figure, the replicated interval and the spread of the frozen settings, one line each."""
    if summary.get("unit") == "datasets":
        return _dataset_replicated_text(summary)
    lines = []
    for r in summary["replicates"]:
        ci = r.get("mAA10_ci")
        lines.append(f"  {r['study']} (seed {r['seed']}): trial #{r['trial']} ({_param_text(r.get('params'))}) "
                     f"test mAA10 {r['mAA10']:.4f}" + (f" [{ci[0]:.4f}, {ci[1]:.4f}]" if ci else ""))
    lo, hi = summary["mAA10_ci"]
    head = (f"replicated test mAA10 over {summary['K']} replicate{'s' if summary['K'] != 1 else ''} x "
            f"{summary['pairs']} pairs: {summary['mAA10']:.4f} [{lo:.4f}, {hi:.4f}] (95%; pairs se "
            f"{summary['se_pairs']:.4f}, replicates se {summary['se_between']:.4f})")
    sp = summary.get("spread") or {}
    spread = "; ".join(f"{label} {_fmt(sp[k]['min'])} .. {_fmt(sp[k]['max'])}"
                       for k, label in PARAM_LABELS if k in sp)
    out = [head, *lines]
    if spread:
        out.append(f"frozen settings over the replicates: {spread}")
    ref = summary.get("reference")
    if ref:
        lo, hi = ref["ci"]
        line = f"against the reference ({ref.get('label')}, mAA10 {ref['mAA10']:.4f}): "
        line += ref.get("verdict") or (f"{ref['difference']:+.4f} [{lo:+.4f}, {hi:+.4f}], p = {ref['p_value']:.3g}")
        out.append(line)
    if not summary.get("tuning_variance_measured"):
        out.append(f"note: {NOT_MEASURED}; rerun with --replicates 3 to measure it")
    if summary.get("figure_note"):  # a design the calibration benchmark measured short (few pairs near 1)
        out.extend(textwrap.wrap(f"note: {summary['figure_note']}", 100, subsequent_indent="  "))
    return "\n".join(out)


def _dataset_replicated_text(summary: dict) -> str:
    """:func:`replicated_text` of a task measured on datasets (:func:`dataset_replicated_summary`)."""
    obj = summary["objective"]
    out = []
    ci = summary.get(f"{obj}_ci")
    out.append(f"replicated test {obj} over {summary['K']} replicate{'s' if summary['K'] != 1 else ''} on "
               f"{', '.join(summary['datasets'])}: {summary[obj]:.4f}"
               + (f" [{ci[0]:.4f}, {ci[1]:.4f}] (95%, t over replicates)" if ci else ""))
    for r in summary["replicates"]:
        out.append(f"  {r['study']} (seed {r['seed']}): trial #{r['trial']}, {obj} {r[obj]:.4f} over "
                   f"{r['runs']} run{'s' if r['runs'] != 1 else ''}")
    ref = summary.get("reference")
    if ref:
        line = f"frozen - reference ({ref.get('label')}, {obj} {ref[obj]:.4f}): {ref['difference']:+.4f}"
        if ref.get("ci"):
            line += f" [{ref['ci'][0]:+.4f}, {ref['ci'][1]:+.4f}], p = {ref['p_value']:.3g}"
        out.append(line + f"; {ref['verdict']}")
        if len(ref.get("datasets") or {}) > 1:
            out.append("  per dataset: " + ", ".join(f"{k} {v:+.4f}" for k, v in ref["datasets"].items()))
    if summary.get("note"):
        out.append(f"note: {summary['note']}; rerun with --replicates 3 to measure it")
    return "\n".join(textwrap.fill(x, 100, subsequent_indent="    ") for x in out)


def _fmt(v) -> str:
    return f"{v:.3g}" if isinstance(v, float) else str(v)


__all__ = ["MAX_REPLICATES", "dataset_replicated_summary", "load_replicated", "param_spread", "record_replicated", "replicate_name", "replicate_seed",
           "replicate_settings", "replicate_tests", "replicated_block", "replicated_summary", "replicated_text",
           "score_matrix", "tune_replicates"]
