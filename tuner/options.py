"""The command line's shared option groups (pipeline, data, output, multiview) and their translation into
the library's objects (``PipelineConfig``, task options). Library calls live in ``tuner.evaluate``,
``tuner.study`` and ``tuner.freeze``; the commands in ``tuner.commands``. The data folder rule is
``pipeline.data.locate`` (re-exported here as ``resolve_data``).
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import math

from pipeline.config import SEED_MAX, FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
from pipeline.config_files import SKIPPED_MATCHER

# The data folder rule lives in the pipeline (one rule for every command; the main job may download):
from pipeline.data.locate import resolve_data  # noqa: E402,F401
from pipeline.errors import ImtuneError
from tuner.argtypes import (
    count_int,
    iters_int,
    nonnegative_float,
    positive_float,
    positive_int,
    probability_float,
    ratio_float,
    scene_list,
    seed_int,
    unit_float,
)

#: --data's help, the same on every command that reads data (the rules of pipeline.data.locate)
DATA_HELP = ("data folder (else $IMTUNE_DATA, imtune.yaml, the download location $IMTUNE_DATA_HOME, then "
             "../shared/data beside the project; `tune data scenes` says which was found)")

#: the searched options' values when a command runs untuned (`tune evaluate`'s defaults: the paper's protocol; a
#: task's ``pipeline_defaults`` override them, :func:`untuned_values`)
UNTUNED = {"ratio": 0.85, "min_confidence": 0.1, "threshold": 0.5, "max_iters": 50000}

def add_pipeline_options(ap: argparse.ArgumentParser, tuning: bool = False, seed_help: str | None = None) -> None:
    """Options that define one pipeline configuration (and, for `tune`, the fixed part of a study: ``tuning``,
    whose --scenes are the validation scenes)."""
    g = ap.add_argument_group("pipeline")
    g.add_argument("--feature", default="sift", help="feature registry name (see `tune list`)")
    g.add_argument("--num-features", type=int, default=8000, help="keypoints per image (paper: 2048 or 8000)")
    g.add_argument("--no-low-threshold", action="store_true", help="keep the detector's default threshold")
    g.add_argument("--upright", action="store_true", help="orientation fixed, duplicates removed")
    g.add_argument("--upright-plus", action="store_true", help="upright, refilled to the budget (upright++)")
    g.add_argument("--clahe", default="none", choices=["none", "detector", "descriptor", "both"],
                   help="CLAHE contrast equalisation of the image the detector and/or the descriptor sees")
    g.add_argument("--mr-size", type=positive_float, default=None,
                   help="descriptor support scale (SIFT mrSize: the patch is 4 x mr_size sigmas) (default: the "
                        "descriptor's own, 3 for SIFT, 6 for the learned ones)")
    g.add_argument("--max-side", type=count_int, default=1024,
                   help="resize so the long side is at most this (px; 0 = keep the original size)")
    g.add_argument("--feature-option", action="append", type=feature_option, default=[], metavar="KEY=VALUE",
                   help="an extractor option, e.g. edge_threshold=10 or contrast_threshold=0.04 for sift (an unknown "
                        "KEY lists the extractor's options); repeatable")
    g.add_argument("--matcher", default="exact", choices=["exact", "flann", "lightglue"],
                   help="nearest neighbours: exact brute force, or OpenCV FLANN (approximate); or lightglue, the "
                        "learned matcher (features aliked and disk; thresholded at --min-confidence instead of r)")
    g.add_argument("--matcher-option", action="append", type=feature_option, default=[], metavar="KEY=VALUE",
                   help="a learned matcher's option: depth_confidence, width_confidence (LightGlue's adaptive depth "
                        "and width, 0.95 and 0.99; -1 = off); repeatable")
    g.add_argument("--strategy", default="both", help="both | either | uni")
    g.add_argument("--distance-threshold", type=nonnegative_float, default=None,
                   help="drop a match whose descriptor distance exceeds this (L2 for float descriptors, bits for "
                        "binary ones) (default: none, no threshold)")
    g.add_argument("--fginn", action="store_true", help="FGINN: 2nd neighbour > 10 px from the first")
    g.add_argument("--prefilter", default="none", metavar="NAME[:k=v,...]",
                   help="outlier pre-filter between matching and the estimator: none | gms | adalam (see `tune list`)")
    g.add_argument("--matches", default=None, metavar="custom:DIR",
                   help="imported matches (IMC h5 layout) instead of the matcher; needs --feature custom:DIR")
    g.add_argument("--ransac", default="degensac", help="estimator registry name (see `tune list`)")
    g.add_argument("--confidence", type=probability_float, default=0.999999,
                   help="RANSAC confidence tau (the protocol fixes 0.999999)")
    if not tuning:
        g.add_argument("--ratio", type=ratio_float, default=UNTUNED["ratio"], help="ratio test r in (0, 1]; 1 = off")
        g.add_argument("--min-confidence", type=nonnegative_float, default=UNTUNED["min_confidence"],
                       help="--matcher lightglue: keep matches of confidence above this, in [0, 1) (LightGlue's "
                            "filter_threshold; takes r's place)")
        g.add_argument("--threshold", type=positive_float, default=UNTUNED["threshold"], help="inlier threshold eta, px")
        g.add_argument("--max-iters", type=iters_int, default=UNTUNED["max_iters"], help="RANSAC iteration cap Gamma")
    g.add_argument("--seed", type=seed_int, default=0, help=seed_help or f"random seed, 0 to {SEED_MAX}")
    d = ap.add_argument_group("data")
    d.add_argument("--data", default=None, help=DATA_HELP)
    d.add_argument("--scenes", type=scene_list, default=None,
                   help="comma-separated validation scenes, each once (default: the data set's validation split)"
                   if tuning else "comma-separated scene names, each once (default: every scene of the data)")
    d.add_argument("--covisibility", type=unit_float, default=0.1, help="minimum pair co-visibility where known")
    d.add_argument("--cache", default=None, help="cache folder (else $IMTUNE_CACHE or ~/.cache/imtune)")
    o = ap.add_argument_group("output")
    o.add_argument("--json", action="store_true", help="print one JSON object")
    o.add_argument("--quiet", action="store_true", help="no progress bars")


#: the matcher's options (argparse dests) -> their values when imported matches skip the matcher (r = 1: no test):
#: pipeline.config_files.SKIPPED_MATCHER under the option names (--matcher sets MatchConfig.method)
MATCHER_OPTIONS = {("matcher" if k == "method" else k): v for k, v in SKIPPED_MATCHER.items()}
#: the k-NN options (argparse dests) a learned matcher skips -> the values its configuration records
LEARNED_SKIPS = {k: v for k, v in MATCHER_OPTIONS.items() if k != "matcher"}


def build_config(args: argparse.Namespace, **overrides) -> PipelineConfig:
    """PipelineConfig from parsed options; ``overrides`` (ratio, threshold, max_iters, strategy, ...)
    win over the options. Validates names against the registries (one-line error if unknown)."""
    from pipeline.features import EXTRACTORS
    from pipeline.geometry import ESTIMATORS
    v = dict(vars(args))
    v.update(overrides)
    for reg, name in ((EXTRACTORS, v["feature"]), (ESTIMATORS, v["ransac"])):
        check = getattr(reg.get(name), "check_available", None)  # unknown name -> one-line error
        if check is not None:
            check()  # known but not runnable here (missing package / weights, non-free) -> one-line error
    from pipeline.features.custom_h5 import PREFIX, parse_custom
    from pipeline.matching.custom_matches import parse_matches_source
    from pipeline.matching.prefilters import parse_prefilter_spec
    if str(v["feature"]).startswith(PREFIX):  # custom:DIR -> absolute DIR (study names, cache keys, resume)
        v["feature"] = PREFIX + str(parse_custom(v["feature"]))
    prefilter, prefilter_options = parse_prefilter_spec(v.get("prefilter"))
    custom_matches = parse_matches_source(v.get("matches"))
    if custom_matches and not str(v["feature"]).startswith(PREFIX):
        raise ImtuneError("--matches custom:DIR needs --feature custom:DIR (the match indices refer to those keypoints)")
    if custom_matches:  # the matcher is skipped: its options were ignored, and r=0.85 shown for a run with no ratio test
        typed = [o for o in MATCHER_OPTIONS if o in explicit_options(args) and o not in overrides]
        if typed:
            raise ImtuneError(f"--{typed[0].replace('_', '-')} does not apply with --matches custom:DIR: imported matches "
                              "skip the matcher (no ratio test, strategy, distance threshold, FGINN); drop it")
        v.update(MATCHER_OPTIONS)
    from pipeline.matching.learned import is_learned
    if is_learned(str(v["matcher"])):  # the network matches: the k-NN options were ignored, and r shown for nothing
        typed = [o for o in LEARNED_SKIPS if o in explicit_options(args) and o not in overrides]
        if typed:
            raise ImtuneError(f"--{typed[0].replace('_', '-')} does not apply with --matcher {v['matcher']}: a learned "
                              "matcher has no ratio test, strategy, distance threshold or FGINN (its threshold is "
                              "--min-confidence); drop it")
        v.update(LEARNED_SKIPS)
    elif "min_confidence" in explicit_options(args) and "min_confidence" not in overrides:
        raise ImtuneError(f"--min-confidence applies to a learned matcher (--matcher lightglue), not to --matcher "
                          f"{v['matcher']} (its threshold is --ratio); drop it")
    fc = FeatureConfig(name=v["feature"], num_features=int(v["num_features"]), low_threshold=not v["no_low_threshold"],
                       upright=bool(v["upright"] or v["upright_plus"]), upright_plus=bool(v["upright_plus"]),
                       clahe=v["clahe"], mr_size=v["mr_size"], max_side=int(v["max_side"]),
                       options=tuple(sorted(feature_options(v.get("feature_option")).items())))
    mc = MatchConfig(ratio=float(v["ratio"]), strategy=v["strategy"], distance_threshold=v["distance_threshold"],
                     fginn=bool(v["fginn"]), method=v["matcher"], prefilter=prefilter,
                     prefilter_options=prefilter_options, custom_matches=custom_matches,
                     min_confidence=float(v.get("min_confidence", 0.1)),
                     matcher_options=tuple(sorted(feature_options(v.get("matcher_option")).items())))
    gc = GeometryConfig(ransac=v["ransac"], threshold=float(v["threshold"]), confidence=float(v["confidence"]),
                        max_iters=int(v["max_iters"]), seed=int(v["seed"]))
    conf = PipelineConfig(feature=fc, matching=mc, geometry=gc)  # a learned matcher without weights for fc: one line
    if mc.learned:
        from pipeline.matching.learned import LEARNED_MATCHERS
        LEARNED_MATCHERS.get(mc.method).check_available()  # its weights here (else one line naming the file)
    if fc.options:
        check_feature_options(conf, "--feature-option")
    return conf


# -- extractor options (--feature-option KEY=VALUE; `config: feature: options:` in a file) -------------------

def option_value(text: str):
    """A typed value from the command line: true/false/yes/no/on/off -> bool, then int, then a finite float,
    else the text itself (the extractor converts it to its option's type, or says why it cannot)."""
    t = text.strip()
    low = t.lower()
    if low in ("true", "yes", "on"):
        return True
    if low in ("false", "no", "off"):
        return False
    try:
        return int(t)
    except ValueError:
        pass
    try:
        f = float(t)
    except ValueError:
        return t
    if not math.isfinite(f):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return f


def feature_option(text: str) -> tuple:
    """``KEY=VALUE`` -> (key, typed value) for ``--feature-option``."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip() or not value.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE (e.g. edge_threshold=10), got {text!r}")
    return key.strip(), option_value(value)


def feature_options(pairs) -> dict:
    """``--feature-option`` (key, value) pairs as a dict; one-line ImtuneError for a key given twice with two values
    (the last one was used, unsaid), as for ``--fix`` and a pre-filter option."""
    out: dict = {}
    for key, value in pairs or ():
        if key in out and out[key] != value:
            raise ImtuneError(f"--feature-option {key} is given twice ({key}={out[key]} and {key}={value}): give it once")
        out[key] = value
    return out


def check_feature_options(conf: PipelineConfig, where: str) -> None:
    """The extractor accepts ``conf.feature.options`` (names and values): it is built once here — OpenCV and
    kornia extractors check their options when built, cheaply (weights load at the first image) — so that a
    wrong name fails now, in one line listing the valid ones, and not at the first uncached image."""
    if not conf.feature.options:
        return
    from pipeline.features import get_extractor
    try:
        get_extractor(conf.feature)
    except ImtuneError as e:
        raise ImtuneError(f"{where}: {e}") from None


# -- which options the user typed (so that a configuration file's values give way only to those) ------------

EXPLICIT = "_explicit_options"


@functools.cache
def _tracked(cls):
    class Tracked(cls):
        """Records its dest on the namespace: argparse calls an action only for an option on the command line."""

        def __call__(self, parser, namespace, values, option_string=None):
            seen = set(getattr(namespace, EXPLICIT, ()) or ())
            seen.add(self.dest)
            setattr(namespace, EXPLICIT, frozenset(seen))
            super().__call__(parser, namespace, values, option_string)
    Tracked.__name__ = f"Tracked{cls.__name__}"
    return Tracked


def track_explicit(ap: argparse.ArgumentParser) -> None:
    """Make ``ap`` record the options given on its command line (:func:`explicit_options`). An option typed
    with its default value (``--ratio 0.85``) counts as given; argparse's defaults never do."""
    for action in ap._actions:
        if action.option_strings and action.dest not in (argparse.SUPPRESS, "help"):
            action.__class__ = _tracked(type(action))


def explicit_options(args: argparse.Namespace) -> frozenset:
    """The dests of the options typed on the command line (needs :func:`track_explicit` on the parser)."""
    return frozenset(getattr(args, EXPLICIT, ()) or ())


#: pipeline options (argparse dests of :func:`add_pipeline_options`) -> the PipelineConfig fields they set
OPTION_FIELDS: dict[str, tuple[tuple[str, str], ...]] = {
    "feature": (("feature", "name"),), "num_features": (("feature", "num_features"),),
    "no_low_threshold": (("feature", "low_threshold"),), "upright": (("feature", "upright"),),
    "upright_plus": (("feature", "upright"), ("feature", "upright_plus")), "clahe": (("feature", "clahe"),),
    "mr_size": (("feature", "mr_size"),), "max_side": (("feature", "max_side"),),
    "feature_option": (("feature", "options"),),
    "matcher": (("matching", "method"),), "strategy": (("matching", "strategy"),),
    "min_confidence": (("matching", "min_confidence"),), "matcher_option": (("matching", "matcher_options"),),
    "distance_threshold": (("matching", "distance_threshold"),), "fginn": (("matching", "fginn"),),
    "prefilter": (("matching", "prefilter"), ("matching", "prefilter_options")),
    "matches": (("matching", "custom_matches"),),
    "ransac": (("geometry", "ransac"),), "confidence": (("geometry", "confidence"),),
    "ratio": (("matching", "ratio"),), "threshold": (("geometry", "threshold"),),
    "max_iters": (("geometry", "max_iters"),), "seed": (("geometry", "seed"),),
}


def untuned_values(task: str) -> dict:
    """The values of the searched options an untuned run (`tune evaluate`) of ``task`` uses: :data:`UNTUNED` with the
    task's own defaults (``Task.pipeline_defaults``) over it."""
    from pipeline.tasks import task_class
    decl = task_class(task).pipeline_defaults
    return {k: decl.get(k, v) for k, v in UNTUNED.items()}


def apply_task_defaults(args: argparse.Namespace, tasks: list[str]) -> list[str]:
    """Set each pipeline option the command line did not type (:func:`explicit_options`) to the default the tasks
    that run declare (``Task.pipeline_defaults``: the reconstruction task runs COLMAP's SIFT at eta 1 px, the
    command line's defaults being the stereo protocol's). Nothing with ``--config`` (the file's values stand) or when
    the tasks declare different defaults. Returns the options set (argparse dests)."""
    from pipeline.tasks import task_class
    if getattr(args, "config", None) or not tasks:
        return []
    decl = [task_class(t).pipeline_defaults for t in tasks]
    if any(d != decl[0] for d in decl):
        return []
    typed = explicit_options(args)
    done = []
    for dest, value in decl[0].items():
        if dest not in typed and hasattr(args, dest):
            setattr(args, dest, value)
            done.append(dest)
    return done


def config_over(base: PipelineConfig, args: argparse.Namespace, where: str = "configuration") -> tuple:
    """``base`` (a configuration file's) with the pipeline options typed on the command line on top; returns
    (config, the option names that overrode the file). Fields no option sets (``fginn_px``, ...) keep the
    file's. Extractor options: the file's (kept only while the feature stays the file's), then each
    ``--feature-option`` over them."""
    given = explicit_options(args)
    cli = build_config(args)
    kw: dict[str, dict] = {"feature": {}, "matching": {}, "geometry": {}}
    used = []
    for dest, fields in OPTION_FIELDS.items():
        if dest in given:
            used.append("--" + dest.replace("_", "-"))
            for sec, f in fields:
                kw[sec][f] = getattr(getattr(cli, sec), f)
    name = kw["feature"].get("name", base.feature.name)
    opts = dict(base.feature.options or ()) if name == base.feature.name else {}
    if "feature_option" in given:
        opts.update(dict(cli.feature.options or ()))
    kw["feature"]["options"] = tuple(sorted(opts.items()))
    try:
        conf = dataclasses.replace(base, **{sec: dataclasses.replace(getattr(base, sec), **v) for sec, v in kw.items()})
    except (TypeError, ValueError) as e:
        raise ImtuneError(f"{where} with {' '.join(used)}: {e}") from None
    check_feature_options(conf, where if "feature_option" not in given else f"{where} with --feature-option")
    return conf, used


def add_multiview_options(ap: argparse.ArgumentParser, bags_default: str = "the protocol's 100/50/25") -> None:
    """Options of the multiview task (`tune evaluate --task multiview`); ``bags_default``: --bags' default, as its
    help says it."""
    g = ap.add_argument_group("multiview")
    g.add_argument("--bags", default=None,
                   help=f"bag sizes[:counts], e.g. 5,10,25 or 5:100,10:50,25:25 (default: {bags_default})")
    g.add_argument("--bag-min-points", type=count_int, default=100, help="each image must see this many of the bag's 3D points")
    g.add_argument("--bag-seed", type=seed_int, default=0, help="seed of the bag sampling")
    g.add_argument("--mv-intrinsics", default="colmap", choices=["colmap", "prior", "fixed"],
                   help="colmap: COLMAP estimates them (official); prior: known K, refined; fixed: known K")
    g.add_argument("--workers", type=positive_int, default=None, help="bags in parallel (default: available CPUs)")
    g.add_argument("--keep-models", default=None, help="keep every bag's COLMAP database and model in this folder")
    g.add_argument("--gt-dir", default=None, help="built ground truth folder (default $IMTUNE_GT, $IMTUNE_CACHE/gt or ~/.cache/imtune/gt)")
    r = ap.add_argument_group("reconstruction (IMC 2024/2025 datasets: --task reconstruction)")
    r.add_argument("--mapper", default=None, choices=["incremental", "global"],
                   help="pycolmap mapper: incremental (default) or global (GLOMAP)")
    r.add_argument("--submission", default=None, metavar="PATH",
                   help="where submission.csv is written (a .csv file or a folder; default: a folder per "
                        "configuration under the cache, printed in the result)")


#: the multiview task's options (dest -> default): given while no multiview task runs, each was ignored, unsaid
MULTIVIEW_ONLY = {"bags": None, "bag_min_points": 100, "bag_seed": 0, "mv_intrinsics": "colmap", "workers": None,
                  "keep_models": None, "bag_records": False}


#: the options that set a task's recorded options (what a study's task_options keep): typed, they override a study's
TASK_OPTION_DESTS = frozenset({"bags", "bag_min_points", "bag_seed", "mv_intrinsics"})


def check_multiview_only(args: argparse.Namespace, tasks: list[str]) -> None:
    """One-line ImtuneError for a multiview option (``--bags``, ``--workers``, ...) given while ``tasks`` (the task
    names that run) hold no task taking them (whose constructor takes ``mv``: the multiview settings)."""
    from pipeline.tasks import TASKS, task_class
    if any(task_class(t).takes("mv") for t in tasks):
        return
    takers = " / ".join(n for n in TASKS.names() if TASKS.get(n).takes("mv"))
    typed = explicit_options(args)
    for dest, default in MULTIVIEW_ONLY.items():
        if any(task_class(t).takes(dest) for t in tasks):  # --workers of the reconstruction task
            continue
        if hasattr(args, dest) and (dest in typed or getattr(args, dest) != default):
            flag = "--" + dest.replace("_", "-")
            raise ImtuneError(f"{flag} is an option of the {takers} task, and only the {' and '.join(tasks)} task "
                              f"runs here (--task {getattr(args, 'task', None) or tasks[0]}): add --task {takers}, or "
                              f"drop {flag}")


def multiview_config(args: argparse.Namespace, **overrides):
    """MultiviewConfig from parsed options (see ``add_multiview_options``)."""
    from pipeline.data.bags import parse_bags
    from pipeline.tasks.multiview import MultiviewConfig
    v = dict(vars(args))
    v.update(overrides)
    return MultiviewConfig(bags=tuple(parse_bags(v.get("bags")).items()), min_points=int(v.get("bag_min_points", 100)),
                           bag_seed=int(v.get("bag_seed", 0)), intrinsics=v.get("mv_intrinsics", "colmap"),
                           seed=int(v.get("seed", 0) or 0))


def task_choices() -> list[str]:
    """`--task` values: every registered task, and ``both`` (all of them)."""
    from pipeline.tasks import TASKS
    return TASKS.names() + ["both"]


def jobs_count(s: str) -> int:
    """``--jobs N``: an integer >= 1 (argparse's one-line error otherwise); above the CPUs this process may use it
    is allowed, with a one-line note (the estimators then share cores, and their measured seconds grow)."""
    import sys

    from pipeline.cpus import available_cpus
    n = positive_int(s)
    cpus = available_cpus()
    if n > cpus:
        print(f"note: --jobs {n} is more than the {cpus} CPUs this process may use; the pair workers will share "
              "cores (estimator seconds then include waiting for one)", file=sys.stderr)
    return n


def add_jobs_option(ap: argparse.ArgumentParser) -> None:
    """``--jobs N``: stereo pairs evaluated by N worker processes (default: $IMTUNE_JOBS, else every CPU this process
    may use)."""
    ap.add_argument("--jobs", type=jobs_count, default=None, metavar="N",
                    help="worker processes evaluating stereo pairs, and estimators timed at once by the budget "
                         "calibration (default: $IMTUNE_JOBS, else every CPU this process may use; 1: no pool)")


def task_options(args: argparse.Namespace, **overrides) -> dict:
    """Every task option the parsed command line gives (``pipeline.tasks.make_task`` hands each task the ones
    it takes): min_covisibility, max_pairs, mv (the multiview settings), workers, keep_models."""
    v = dict(vars(args))
    v.update(overrides)
    return {"min_covisibility": v.get("covisibility"), "max_pairs": v.get("max_pairs"),
            "mv": multiview_config(args, **overrides) if "bags" in v else None, "mapper": v.get("mapper"),
            "submission": v.get("submission"),
            "workers": v.get("workers"), "keep_models": v.get("keep_models"), "jobs": v.get("jobs")}
