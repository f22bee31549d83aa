"""Compare configurations on the same stereo pairs: is B better than A, and how sure is that?

    from tuner.compare import compare, load_sources
    sources = load_sources(["sift-2048-degensac-stereo", "opencv.yaml"], studies_dir)
    result = compare(sources, data_root, scenes=["entry-P10"])
    result["comparisons"][0]["overall"]   # {"mAA10_a", "mAA10_b", "difference", "ci", "p_value", ...}

Each source is a study name (its frozen settings), a frozen.yaml, a configuration file (YAML or JSON with
a ``config:`` mapping, or feature / matching / geometry sections; missing fields take the defaults) or an
official IMC benchmark method JSON (``tuner.sources.resolve_source``). Every source is evaluated on the same
scenes and pairs (identical configurations once: their records are shared, so a configuration compared
with itself gives difference 0 and p = 1 exactly, whether or not its estimator is seeded). Then each
source after the first is compared with the first by
:func:`pipeline.metrics.uncertainty.paired_bootstrap`: ``difference`` = mAA10(B) - mAA10(A) over the pairs
both evaluated, its stratified bootstrap CI, a two-sided sign-flip p-value, overall and per scene, and a verdict
by the rule of `tune findings` (:func:`pipeline.metrics.uncertainty.paired_direction`): "B better" / "A better"
only when the CI excludes 0 and the sign-flip test agrees (p < 0.05), else "no significant difference". With
more than two sources the k - 1 comparisons are adjusted together (:func:`compare_records`: Bonferroni-level CIs,
Holm-adjusted p-values), so that "significant" keeps its 5% over the whole table. Multiview studies are compared
on the same multiview bags, paired over bags (``compare(..., task="multiview")``; :func:`comparison_task`): each
task declares its units, intervals and paired test (``pipeline.tasks.base.Task``).
"""
from __future__ import annotations

from pathlib import Path

from pipeline.errors import ImtuneError
from pipeline.metrics.uncertainty import (
    DEFAULT_LEVEL,
    DEFAULT_RESAMPLES,
    DIRECTION_RULE,
    bonferroni,
    format_p,
    holm,
    is_bag_records,
    paired_bags,
    paired_bootstrap,
    paired_direction,
)
from tuner.evaluate import evaluate_config
from tuner.sources import resolve_source

COMPARISON_KEYS = ("mAA10_a", "mAA10_b", "difference", "ci", "p_value", "significant", "pairs", "dropped_a",
                   "dropped_b")  # + "p_value_unadjusted", "ci_level", "comparisons", "verdict" (compare_records)


def load_sources(specs: list[str], studies_dir: Path | str) -> list:
    """Each spec (study name, frozen.yaml, config file, IMC method JSON) as a source with ``conf`` and
    ``label``; one-line ImtuneError for an unknown study or a missing / invalid file, or fewer than two."""
    if len(specs) < 2:
        raise ImtuneError(f"tune compare needs at least two configurations (got {len(specs)}: "
                          f"{', '.join(specs) or 'none'}); give A B [C ...], each a study name or a config file")
    return [resolve_source(s, Path(studies_dir)) for s in specs]


def _records(section: dict, task) -> list[dict]:
    """The records of a task's evaluation section: under the key the task declares (``records_key``)."""
    recs = section.get(task.records_key)
    if recs is None:
        raise ImtuneError(f"the evaluation returned no {task.unit_one} records under {task.records_key!r} "
                          "(internal: with_pairs ignored)")
    return recs


def source_task(src) -> str:
    """The task a source was tuned for: its study's (frozen.yaml ``task``), else "stereo" (a configuration file)."""
    return (getattr(src, "frozen", None) or {}).get("task") or "stereo"


def comparison_task(specs: list[str], sources: list, task: str | None = None) -> str:
    """The task `tune compare` evaluates the sources on: ``task`` when given, else the task their studies were tuned
    for (configuration files go with either): a multiview study is compared on bags, as it was tuned. Studies of two
    tasks and no ``task``: one-line ImtuneError naming one of each (neither task is the one the other was tuned
    for)."""
    if task:
        return task
    tuned = {}
    for spec, src in zip(specs, sources):
        if getattr(src, "frozen", None):
            tuned.setdefault(source_task(src), spec)
    if len(tuned) > 1:
        (t1, s1), (t2, s2) = list(tuned.items())[:2]
        raise ImtuneError(f"{s1} is a {t1} study and {s2} a {t2} study: each was tuned for another task; give "
                          f"--task {t1} or --task {t2} to compare them on that task (the other study then runs with "
                          "settings never tuned for it)")
    return next(iter(tuned), "stereo")


def _option_text(value) -> str:
    """An option's value as typed: bags ((5, 100), (10, 50)) as 5:100,10:50."""
    if isinstance(value, (list, tuple)) and value and all(isinstance(x, (list, tuple)) and len(x) == 2 for x in value):
        return ",".join(f"{a}:{b}" for a, b in value)
    return str(value)


def study_options(specs: list[str], sources: list, task: str, given: dict, typed: bool) -> tuple[dict, str | None]:
    """The task options (:meth:`pipeline.tasks.base.Task.options`) `tune compare` evaluates every source with, and a
    warning or None. ``given``: the command line's (the task's defaults where no option is typed); ``typed``: whether
    an option setting them was typed. The task's ``reapplied`` options are taken from what the studies of ``task``
    among the sources recorded (their frozen task options, which their test runs use; multiview: the bags) when they
    all agree and none is typed; else ``given``, with a warning naming a study tested with other settings (its
    numbers here are not its test's). A task that reapplies nothing: ``given``."""
    from pipeline.tasks import TASKS
    cls = TASKS.get(task)

    def normal(opts: dict) -> dict:  # a YAML's lists and a dataclass's tuples compare equal once rebuilt
        return cls.from_options(opts).options()
    given = normal(given)
    recorded = {}
    for spec, src in zip(specs, sources):
        fz = getattr(src, "frozen", None) or {}
        if cls.reapplied and fz.get("task") == task and isinstance(fz.get("task_options"), dict):
            recorded[spec] = normal({**given, **{k: v for k, v in fz["task_options"].items() if k in cls.reapplied}})
    first = next(iter(recorded.values()), None)
    if first is None:
        return given, None
    if not typed and all(o == first for o in recorded.values()):
        return first, None
    other = [spec for spec, o in recorded.items() if o != given]
    if not other:
        return given, None
    o = recorded[other[0]]
    diff = ", ".join(f"{k} {_option_text(o[k])} (here {_option_text(given.get(k))})"
                     for k in cls.reapplied if o.get(k) != given.get(k))
    why = "as given" if typed else "the studies' settings differ: the task's defaults; type its options to choose"
    return given, f"{other[0]} was tested with {diff}; all are compared on these {cls.unit} ({why})"


def task_label(src, task: str) -> str:
    """A source's label naming what verifies its matches on ``task``: a configuration file compared on multiview bags
    was labelled 'degensac η 0.5 px, Γ 50000' (an estimator COLMAP never used), a multiview study on stereo pairs
    'COLMAP from our tentative matches' (its eta and Gamma do run there)."""
    from pipeline.config_files import config_label
    for tail in {config_label(src.conf, source_task(src)), config_label(src.conf)}:
        if src.label.endswith(tail):
            return src.label[: len(src.label) - len(tail)] + config_label(src.conf, task)
    return src.label


def compare(sources: list, data_root: Path | str, scenes=None, *, cache_dir=None, min_covisibility: float | None = 0.1,
            progress: bool = False, n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0,
            level: float = DEFAULT_LEVEL, task: str = "stereo", multiview=None, workers: int | None = None,
            gt_dir=None, keep_models=None, task_options: dict | None = None) -> dict:
    """Evaluate every source on the same stereo pairs (``task`` "stereo") or the same multiview bags ("multiview":
    ``multiview`` a MultiviewConfig, None the protocol's; ``workers`` parallel bag processes; ``keep_models`` a folder
    for COLMAP's models; ``gt_dir`` where built ground truth lives, as for `tune evaluate`; any registered task:
    ``task_options`` its :meth:`~pipeline.tasks.base.Task.options`, e.g. from :func:`study_options`, the other
    options then override them where the task takes them) and compare each with the first by the task's paired test
    (:meth:`~pipeline.tasks.base.Task.paired`; on bags "pairs" counts the common bags, ``units`` "bags")

    sources: objects with ``conf`` (PipelineConfig) and ``label`` (see :func:`load_sources`).
    Returns ``{"data", "scenes", "sources": [{"label", "config", "mAA10", "mAA5", "mAA10_ci", "mAA5_ci",
    "pairs", "scenes": {name: {"mAA10", "mAA10_ci", ...}}}, ...], "comparisons": [{"a": label of the first,
    "b": label, "overall": {COMPARISON_KEYS}, "scenes": {name: {COMPARISON_KEYS}}}, ...]}``."""
    if len(sources) < 2:
        raise ImtuneError("tune compare needs at least two configurations")
    done: list[tuple] = []  # (conf, result): identical configurations are evaluated once
    evaluated = []
    for src in sources:
        hit = next((res for conf, res in done if conf == src.conf), None)
        if hit is None:
            hit = evaluate_config(src.conf, Path(data_root), scenes, cache_dir=cache_dir,
                                  min_covisibility=min_covisibility, progress=progress, with_pairs=True, task=task,
                                  gt_dir=gt_dir, multiview=multiview, workers=workers, keep_models=keep_models,
                                  task_options=task_options)  # each task takes the options it knows
            done.append((src.conf, hit))
        evaluated.append(hit)
    from pipeline.tasks import TASKS
    out_sources = []
    t = TASKS.get(task)
    unit = t.unit
    labels = [task_label(src, task) for src in sources]
    for res, label in zip(evaluated, labels):
        st = res[task]
        ci = t.intervals(_records(st, t), n_resamples=n_resamples, seed=seed, level=level, scenes=list(st["scenes"]))
        out_sources.append({
            "label": label, "config": res["config"], "mAA10": st["mAA10"], "mAA5": st["mAA5"],
            "mAA10_ci": ci["mAA10_ci"], "mAA5_ci": ci["mAA5_ci"], unit: st[unit],
            "scenes": {n: {"mAA10": s["mAA10"], "mAA5": s["mAA5"], unit: s.get(unit), **ci["scenes"].get(n, {})}
                       for n, s in st["scenes"].items()}})
    comparisons = compare_records([(label, _records(res[task], t)) for label, res in zip(labels, evaluated)],
                                  n_resamples=n_resamples, seed=seed, level=level, task=task)
    out = {"data": str(data_root), "scenes": evaluated[0]["scenes"], "task": task, "level": level,
           "n_resamples": n_resamples, "seed": seed, "sources": out_sources, "comparisons": comparisons,
           "verdict_rule": verdict_rule(len(comparisons), level), "adjustment": adjustment_note(len(comparisons), level)}
    if evaluated[0][task].get("notes"):  # where the task could not follow its options (bags above a scene's images)
        out["notes"] = evaluated[0][task]["notes"]
    return out


def compare_records(named: list[tuple[str, list]], *, n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0,
                    level: float = DEFAULT_LEVEL, task: str | None = None) -> list[dict]:
    """Each of ``named[1:]`` (label, records) compared with ``named[0]`` by ``task``'s paired test
    (:meth:`pipeline.tasks.base.Task.paired`; None: bag records by :func:`~pipeline.metrics.uncertainty.paired_bags`,
    pair records by the paired bootstrap): the ``comparisons`` of :func:`compare`.

    Multiplicity: the m = k - 1 comparisons are one family, held at ``level`` together. Each CI is at the Bonferroni
    level 1 - (1 - level) / m (``ci_level``; with at least 20 / alpha_each resamples:
    :func:`pipeline.metrics.uncertainty.bonferroni`, as the ranks of `tune results` do) and ``p_value`` is Holm's
    adjusted p over the m comparisons (``p_value_unadjusted`` the comparison's own; per scene, Holm over the m
    comparisons on that scene); the verdict needs both (CI excluding 0, adjusted p < 1 - level). At 5% each, five
    identical methods compared with the first had at least one "significant" difference in ~14% of simulated tables
    (tests/test_uncertainty_synthetic.py); m = 1 (two sources) is the plain comparison."""
    m = len(named) - 1
    level_each, _, resamples_each = bonferroni(level, m, n_resamples)
    if m <= 1:
        resamples_each = int(n_resamples)
    label_a, recs_a = named[0]
    if task is not None:
        from pipeline.tasks import TASKS
        paired = TASKS.get(task).paired
    else:  # records without their task (a caller of old): bag records are the multiview task's
        paired = paired_bags if is_bag_records(recs_a) else paired_bootstrap
    comparisons = []
    for label, recs in named[1:]:
        pb = paired(recs_a, recs, tau=10, n_resamples=resamples_each, seed=seed, level=level_each)
        comparisons.append({"a": label_a, "b": label, "units": pb.get("units", "pairs"),
                            "overall": {k: pb[k] for k in COMPARISON_KEYS},
                            "scenes": {n: {k: s[k] for k in COMPARISON_KEYS} for n, s in pb["scenes"].items()}})
    families = [[c["overall"] for c in comparisons]]
    for name in dict.fromkeys(n for c in comparisons for n in c["scenes"]):
        families.append([c["scenes"][name] for c in comparisons if name in c["scenes"]])
    for fam in families:
        for c, p_adj in zip(fam, holm([c["p_value"] for c in fam])):
            c["p_value_unadjusted"], c["p_value"] = c["p_value"], p_adj
            c["ci_level"], c["comparisons"] = level_each, m
            c["significant"] = paired_direction(c["ci"], p_adj, level) != 0
            _with_verdict(c, level)
    return comparisons


def adjustment_note(m: int, level: float = DEFAULT_LEVEL) -> str:
    """How the m comparisons with the first source were adjusted for multiplicity, in words ('' for one)."""
    if m <= 1:
        return ""
    level_each, alpha_each, _ = bonferroni(level, m)
    return (f"{m} comparisons with A, held at {1 - level:.2g} together: each CI at the Bonferroni level "
            f"{100 * level_each:.4g}% (1 - {1 - level:.2g} / {m}), each p Holm-adjusted over the {m} (per scene: over "
            f"the {m} on that scene) and compared with {1 - level:.2g}")


def verdict_rule(m: int, level: float = DEFAULT_LEVEL) -> str:
    """The verdict rule in words at the levels it is applied with m comparisons with the first source:
    DIRECTION_RULE for one; for m > 1 the Bonferroni level of each CI and the Holm-adjusted p (the printed
    rule read '95% CI ... p < 0.05' above a table of 98.33% CIs and adjusted p-values)."""
    if m <= 1:
        return DIRECTION_RULE
    level_each = bonferroni(level, m)[0]
    return (f"Bi or A is better only when the {100 * level_each:.4g}% CI of Bi - A excludes 0 and the paired sign-flip "
            f"test agrees (its p Holm-adjusted over the {m} comparisons < {1 - level:.2g}); otherwise no significant "
            "difference")


def _with_verdict(c: dict, level: float) -> dict:
    c["verdict"] = verdict(c, level)
    return c


def verdict(c: dict, level: float = DEFAULT_LEVEL) -> str:
    """'B better' / 'A better' / 'no significant difference' from a comparison's CI and p-value: the rule of
    `tune findings` (:func:`pipeline.metrics.uncertainty.paired_direction`; DIRECTION_RULE in words). The CI
    alone called 'A better' at p = 0.24."""
    return {1: "B better", -1: "A better", 0: "no significant difference"}[
        paired_direction(c["ci"], c.get("p_value"), level)]


def comparison_rows(comp: dict, level: float = DEFAULT_LEVEL) -> list[dict]:
    """Table rows of one comparison: one per scene, then "overall" (a "bags" column in place of "pairs" on bags)."""
    pct = f"{100 * comp['overall'].get('ci_level', level):.4g}%"
    adjusted = comp["overall"].get("comparisons", 1) > 1
    rows = []
    for name, c in list(comp["scenes"].items()) + [("overall", comp["overall"])]:
        rows.append({"scene": name, comp.get("units", "pairs"): c["pairs"], "mAA10 A": f"{c['mAA10_a']:.4f}",
                     "mAA10 B": f"{c['mAA10_b']:.4f}", "B - A": f"{c['difference']:+.4f}",
                     f"{pct} CI": f"[{c['ci'][0]:+.4f}, {c['ci'][1]:+.4f}]",
                     "p (Holm)" if adjusted else "p": format_p(c["p_value"], 1.0 - level),
                     "verdict": verdict(c, level)})
    return rows


# -- replicated studies (issue 32) ------------------------------------------------------------------------------

def _source_tests(src, sdir: Path) -> list[dict] | None:
    """A study source's test results: every replicate's (tuner.replicates), else its own test.json as one replicate;
    None for a configuration file or an untested study."""
    from tuner.freeze import load_test_file, study_dir
    from tuner.replicates import replicate_tests
    if not src.study:
        return None
    reps = replicate_tests(sdir, src.study)
    if reps is not None:
        return reps
    d, _ = load_test_file(study_dir(sdir, src.study) / "test.json", src.study, refresh=False)
    return [d] if d else None


def compare_replicated(sources: list, sdir: Path | str, *, n_resamples: int = 2000, seed: int = 0) -> dict | None:
    """A - B of two studies from their recorded test results when at least one was run with ``--replicates``
    (:func:`pipeline.metrics.replicates.replicated_difference` on the K_A x N and K_B x N per-pair scores of the
    same test pairs: interval, t-test p, P(A > B) with its interval, the detectable difference; no verdict when a
    side has K = 1); None when it does not apply (not two
    studies, no replicates on either side, or a side untested): then `tune compare` evaluates them as before. The
    scores are scene-weighted as the test's mAA (:func:`tuner.replicates.score_matrix`). One-line ImtuneError when the
    two were tested on other pairs."""
    from pipeline.metrics.replicates import METHOD, difference_block, replicated_difference
    from tuner.replicates import score_matrix
    if len(sources) != 2:
        return None
    tests = [_source_tests(s, Path(sdir)) for s in sources]
    if any(t is None for t in tests) or all(len(t) == 1 for t in tests):
        return None
    ta, tb = tests
    scores, strata = score_matrix(list(ta) + list(tb))
    a, b = scores[:len(ta)], scores[len(ta):]
    d = replicated_difference(a, b, strata, seed=int(seed))
    sides = []
    for src, t, m in ((sources[0], ta, a), (sources[1], tb, b)):
        sides.append({"study": src.study, "replicates": len(t), "mAA10": float(m.mean()),
                      "replicate_mAA10": [float(x) for x in m.mean(axis=1)],
                      "studies": [x.get("study") for x in t]})
    block = difference_block(d)
    block["difference_a_minus_b"] = block.pop("difference")
    return {"a": sides[0], "b": sides[1], **block, "pairs": int(scores.shape[1]),
            "scenes": sorted(set(strata.tolist())), "method": METHOD}
