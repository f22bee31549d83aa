"""`tune compare A B [C ...]`: paired comparison of configurations on the same stereo pairs (or multiview bags).

    tune compare sift-2048-degensac-stereo opencv-defaults.yaml --scenes entry-P10
    tune compare a.yaml b.yaml c.json --json

Each of A, B, ... is a study name (its frozen settings), a frozen.yaml, a configuration file or an IMC
benchmark method JSON. Multiview studies are compared on the same multiview bags (``--task``, ``--bags``, ...):
paired over bags, as `tune results --task multiview` ranks them; without ``--bags``, ``--bag-min-points``,
``--bag-seed`` or ``--mv-intrinsics``, on the bags the studies recorded (those of their test runs) when they agree. Python: :func:`tuner.compare.compare`.
"""
from __future__ import annotations

import json
import sys

from pipeline.errors import ImtuneError
from tuner.commands.evaluate import _jsonable  # the same JSON rendering as tune evaluate
from tuner.options import DATA_HELP


def register(sub) -> None:
    from tuner.argtypes import resamples_int, scene_list, seed_int, unit_float
    ap = sub.add_parser("compare", help="paired comparison of configurations on the same pairs (CI, p-value)",
                        description="Evaluate each configuration (study name, frozen.yaml, config YAML/JSON, IMC method "
                                    "JSON) on the same stereo pairs and compare each with the first: the mAA(10) "
                                    "difference B - A, its bootstrap CI (pairs resampled within each scene, the same "
                                    "pairs for both) and a two-sided paired sign-flip p-value, overall and per scene.")
    ap.add_argument("sources", nargs="+", metavar="SOURCE",
                    help="A B [C ...]: study names or configuration files; each after the first is compared with A")
    d = ap.add_argument_group("data")
    d.add_argument("--data", default=None, help=DATA_HELP)
    d.add_argument("--scenes", type=scene_list, default=None, help="comma-separated scene names (default: every scene of the data)")
    d.add_argument("--covisibility", type=unit_float, default=0.1, help="minimum pair co-visibility where known")
    d.add_argument("--cache", default=None, help="cache folder (else $IMTUNE_CACHE or ~/.cache/imtune)")
    d.add_argument("--studies-dir", default=None, help="where studies live (default $IMTUNE_STUDIES, else studies/)")
    from pipeline.tasks import task_names
    d.add_argument("--task", choices=task_names(), default=None,
                   help="compare on stereo pairs, on multiview bags or on another task's units (default: the task the "
                        "studies were tuned for; configuration files alone: stereo)")
    from tuner.options import add_multiview_options
    add_multiview_options(ap, bags_default="the multiview studies' recorded bags when they agree, else the "
                                           "protocol's 100/50/25")
    s = ap.add_argument_group("statistics")
    s.add_argument("--ci-resamples", type=resamples_int, default=2000, help="bootstrap / sign-flip resamples")
    s.add_argument("--seed", type=seed_int, default=0, help="seed of the resampling (estimator seeds come from each config)")
    o = ap.add_argument_group("output")
    o.add_argument("--json", action="store_true",
                   help='one JSON object {"overall", "scenes"} (a list of them for more than two configurations)')
    o.add_argument("--quiet", action="store_true", help="no progress bars")
    from tuner.options import track_explicit
    track_explicit(ap)  # a multiview option typed while the comparison runs on stereo pairs is refused
    ap.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from tuner.compare import compare, comparison_rows, load_sources
    from tuner.formatting import render
    from tuner.options import resolve_data
    from tuner.storage import default_studies_dir
    if len(args.sources) < 2:
        raise ImtuneError(f"tune compare needs at least two configurations (got one: {args.sources[0]}); "
                          "give A B [C ...], each a study name or a config file")
    sdir = Path(args.studies_dir).expanduser().resolve() if args.studies_dir else default_studies_dir()
    sources = load_sources(args.sources, sdir)
    from tuner.compare import compare_replicated
    rep = compare_replicated(sources, sdir, n_resamples=args.ci_resamples, seed=args.seed)
    if rep is not None:  # replicated studies: compared on their recorded test pairs, with the tuning variance
        return _print_replicated(args, rep)
    objs = {spec: ((src.frozen.get("objective") or {}).get("name", "mAA10") if src.frozen else None)
            for spec, src in zip(args.sources, sources)}
    if len({o for o in objs.values() if o not in (None, "pareto")}) > 1:  # pareto: mAA10 is its first value
        raise ImtuneError("studies tuned for different objectives are never compared as one ("
                          + ", ".join(f"{k}: {o}" for k, o in objs.items() if o) + "); compare studies of one objective")
    from pipeline.tasks import TASKS, is_timed
    from tuner.compare import comparison_task, source_task
    from tuner.options import check_multiview_only, task_options
    task = comparison_task(args.sources, sources, args.task)  # a multiview study is compared on bags
    check_multiview_only(args, [task])
    for spec, src in zip(args.sources, sources):
        tuned_for = source_task(src)
        if not src.frozen or tuned_for == task:
            continue
        tuned = ", ".join((src.frozen or {}).get("params") or {}) or "nothing"
        if not is_timed(tuned_for):  # its eta and Gamma were never tuned (multiview): compared as they are, say so
            print(f"warning: {spec} is a {tuned_for} study: it tuned {tuned} only; on these stereo pairs it "
                  f"runs with its file's eta {src.conf.geometry.threshold:g} px and Gamma {src.conf.geometry.max_iters} "
                  "as they are, untuned", file=sys.stderr)
        else:
            print(f"warning: {spec} is a {tuned_for} study: its {tuned} were tuned on {tuned_for} pairs, not for "
                  f"these {task} {TASKS.get(task).unit}", file=sys.stderr)
    seen: dict = {}
    for spec, src in zip(args.sources, sources):  # the same configuration twice: a difference of 0 by construction
        key = json.dumps(src.conf.to_dict(), sort_keys=True, default=str)
        if key in seen:
            print(f"warning: {spec} and {seen[key]} are the same configuration: their difference is 0 by "
                  "construction (same pairs, same seeds), not a finding", file=sys.stderr)
        seen.setdefault(key, spec)
    data = resolve_data(args.data)
    # the task's options: those the studies of this task recorded (multiview: the bags they were tested on), unless
    # an option setting them is typed (tuner.compare.study_options; a task that reapplies none: the command line's)
    from tuner.compare import study_options
    from tuner.options import TASK_OPTION_DESTS, explicit_options
    given = TASKS.get(task).from_options(None, **task_options(args, seed=0)).options()
    opts, warn = study_options(args.sources, sources, task, given, bool(explicit_options(args) & TASK_OPTION_DESTS))
    if warn:
        print(f"warning: {warn}", file=sys.stderr)
    res = compare(sources, data, args.scenes, cache_dir=args.cache, min_covisibility=args.covisibility,
                  progress=not (args.quiet or args.json), n_resamples=args.ci_resamples, seed=args.seed, task=task,
                  gt_dir=args.gt_dir, task_options=opts, workers=args.workers, keep_models=args.keep_models)
    for note in res.get("notes") or []:  # where the bags could not follow --bags (a small scene)
        print(f"warning: {note}", file=sys.stderr)
    for spec, src in zip(args.sources, sources):  # a tuned study measured on its own validation pairs is favoured
        tuned_on = sorted(set(res["scenes"]) & set(((src.frozen or {}).get("data") or {}).get("val_scenes") or []))
        if tuned_on:
            what = "is a validation scene" if len(tuned_on) == 1 else "are validation scenes"
            print(f"warning: {', '.join(tuned_on)} {what} of {spec}: it was tuned on these pairs, so its numbers there "
                  "are not held out (give --scenes its test scenes for a fair comparison)", file=sys.stderr)
    if args.json:
        from pipeline.metrics.replicates import NOT_MEASURED
        tuned = any(src.frozen for src in sources)  # a single tuning's figure: which optimum it froze is unmeasured
        objs = [{"a": c["a"], "b": c["b"], "overall": c["overall"], "scenes": c["scenes"],
                 "task": res["task"], "verdict_rule": res["verdict_rule"],
                 **({"tuning_variance_measured": False, "tuning_note": NOT_MEASURED} if tuned else {}),
                 **({"adjustment": res["adjustment"]} if res["adjustment"] else {})}
                for c in res["comparisons"]]
        print(json.dumps(_jsonable(objs[0] if len(objs) == 1 else objs), indent=2))
        return 0
    unit, on = TASKS.get(task).unit, TASKS.get(task).units_text()
    print(f"data {res['data']} | scenes {', '.join(res['scenes'])} | {on} | {args.ci_resamples} resamples, "
          f"seed {args.seed}")
    for i, s in enumerate(res["sources"]):
        tag = "A" if i == 0 else ("B" if len(res["sources"]) == 2 else f"B{i}")
        print(f"{tag}: {s['label']}  mAA10 {s['mAA10']:.4f} [{s['mAA10_ci'][0]:.4f}, {s['mAA10_ci'][1]:.4f}] "
              f"({s[unit]} {unit})")
    for i, c in enumerate(res["comparisons"], 1):
        tag = "B" if len(res["comparisons"]) == 1 else f"B{i}"
        what = ("95% bootstrap CI, paired sign-flip p" if len(res["comparisons"]) == 1 else
                f"{100 * c['overall']['ci_level']:.4g}% bootstrap CI, paired sign-flip p Holm-adjusted")
        print(f"\n{tag} vs A: mAA(10) difference {tag} - A (> 0: {tag} better), {what}")
        print(render(comparison_rows(c), "markdown"))
    print(f"verdict: {res['verdict_rule']} (the rule of tune findings"
          + (", adjusted for multiplicity)" if res["adjustment"] else ")"))
    if any(src.frozen for src in sources):  # a tuned figure from a single tuning: which optimum it froze is unmeasured
        from pipeline.metrics.replicates import NOT_MEASURED
        print(f"tuning: {NOT_MEASURED} (studies run with `tune --replicates 3` are compared with it)")
    if res["adjustment"]:
        print(f"multiplicity: {res['adjustment']}")
    return 0


def _print_replicated(args, rep: dict) -> int:
    """`tune compare` of replicated studies: each side's replicates, A - B with interval, p and P(A > B)."""
    if args.scenes and sorted(args.scenes.split(",") if isinstance(args.scenes, str) else args.scenes) != rep["scenes"]:
        raise ImtuneError(f"--scenes: replicated studies are compared on the test pairs they were tested on "
                          f"({', '.join(rep['scenes'])}); drop --scenes, or `tune test` every replicate on those scenes")
    if args.json:
        print(json.dumps(_jsonable(rep), indent=2))
        return 0
    print(f"replicated comparison on the recorded test pairs: {', '.join(rep['scenes'])} ({rep['pairs']} pairs); "
          "t test over replicates x pairs (How sure a number is: tuned comparisons)")
    for tag in ("a", "b"):
        s = rep[tag]
        each = ", ".join(f"{x:.4f}" for x in s["replicate_mAA10"])
        print(f"{tag.upper()}: {s['study']}  mAA10 {s['mAA10']:.4f} over {s['replicates']} replicate"
              f"{'s' if s['replicates'] != 1 else ''} ({each})")
    print(f"verdict: {rep['verdict']}")
    return 0
