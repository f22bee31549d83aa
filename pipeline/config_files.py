"""Configuration files -> ``PipelineConfig``: what `tune evaluate --config`, `tune compare` and `tune viz` read.

    from pipeline.config_files import load_config_file, pipeline_from_dict
    cf = load_config_file("frozen.yaml")        # ConfigFile(conf, label, kind, frozen, path)

Accepted (YAML through ``yaml.safe_load``, or JSON by suffix):

- a frozen.yaml (``config:`` holding the complete pipeline, written by `tune`);
- a configuration file: ``config:`` (or the top level) with ``feature``, ``matching``, ``geometry`` sections as in
  frozen.yaml; missing fields take the defaults; ``feature: {options: {edge_threshold: 10}}`` reaches the
  extractor;
- flat option names as on the command line (``feature: sift``, ``num_features: 2048``, ``ratio: 0.85``,
  ``ransac: degensac``, ``threshold: 0.5``, ``max_iters: 10000``, ...; :data:`FLAT`);
- an official IMC benchmark method JSON (``config_common`` + ``config_<dataset>_stereo``; a list of methods: the
  first), as its users already have them.

Every value is validated by the stage dataclasses (one-line ImtuneError naming the file and the problem).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from pipeline.config import FeatureConfig, GeometryConfig, MapperConfig, MatchConfig, PipelineConfig
from pipeline.errors import ImtuneError

SECTIONS = {"feature": FeatureConfig, "matching": MatchConfig, "geometry": GeometryConfig, "mapper": MapperConfig}
#: flat (command-line) names -> (section, field); names equal to a field of exactly one section are added below
FLAT: dict[str, tuple[str, str]] = {"feature": ("feature", "name"), "matcher": ("matching", "method"),
                                    "ransac": ("geometry", "ransac"), "matches": ("matching", "custom_matches"),
                                    "feature_options": ("feature", "options")}
for _sec, _cls in SECTIONS.items():
    for _f in dataclasses.fields(_cls):
        FLAT.setdefault(_f.name, (_sec, _f.name))


@dataclass
class ConfigFile:
    """A configuration read from a file: ``conf``, a one-line ``label``, its ``kind`` ("frozen", "config",
    "flat", "imc"), the frozen dict when it is a frozen.yaml, and the ``path``."""
    conf: PipelineConfig
    label: str
    kind: str
    frozen: dict | None = None
    path: Path | None = None


def config_label(conf: PipelineConfig, task: str | None = None) -> str:
    """One line naming a configuration: feature (count), matching (r, strategy), estimator (eta, Gamma). For a
    ``task`` that times no estimator of ours (multiview: COLMAP's own RANSAC) the estimator part says what verifies
    the matches instead of eta and Gamma it never used."""
    f, mt, g = conf.feature, conf.matching, conf.geometry
    feat = f"{f.name} {f.num_features}" + (" upright" if f.upright else "")
    match = f"r {mt.ratio:g} {mt.strategy}" + (" fginn" if mt.fginn else "") + \
        (f" d≤{mt.distance_threshold:g}" if mt.distance_threshold is not None else "")
    if mt.learned:  # no ratio test: the learned matcher and its confidence threshold
        match = f"{mt.method} c {mt.min_confidence:g}" + "".join(f" {k}={v:g}" for k, v in mt.matcher_options)
    geo = f"{g.ransac} η {g.threshold:g} px, Γ {g.max_iters}"
    if task is not None:
        from pipeline.tasks import TASKS, is_timed
        if task in TASKS and not is_timed(task):  # e.g. "COLMAP from our tentative matches"
            geo = (getattr(TASKS.get(task), "note", "") or f"{task}: its own estimator").split(";")[0]
    return f"{feat} · {match} · {geo}"


def _options(v, what: str):
    """Extractor options as sorted (key, value) pairs, from a mapping or a list of [key, value] pairs (one-line
    ImtuneError naming ``what`` for anything else: a number, a list of three, ...)."""
    if isinstance(v, dict):
        return tuple(sorted((str(k), x) for k, x in v.items()))
    if not isinstance(v, (list, tuple)) or \
            not all(isinstance(x, (list, tuple)) and len(x) == 2 and isinstance(x[0], str) for x in v):
        raise ImtuneError(f"{what} must be a mapping of option: value (e.g. {{edge_threshold: 10}}), got {v!r}")
    return tuple(sorted((tuple(x) for x in v), key=lambda kv: kv[0]))


def pipeline_from_dict(d: dict, base: PipelineConfig | None = None, where: str = "configuration") -> PipelineConfig:
    """PipelineConfig from its ``to_dict()`` form; fields missing or None keep ``base``'s (default: the dataclass
    defaults). Unknown sections or fields are a one-line ImtuneError naming ``where``."""
    base = base or PipelineConfig()
    if not isinstance(d, dict):
        raise ImtuneError(f"{where}: expected a mapping with feature / matching / geometry sections")
    unknown = [k for k in d if k not in SECTIONS]
    if unknown:
        raise ImtuneError(f"{where}: unknown section {unknown[0]!r} (expected {', '.join(SECTIONS)})")
    kw = {}
    for sec, cls in SECTIONS.items():
        sub = d.get(sec) or {}
        if not isinstance(sub, dict):
            raise ImtuneError(f"{where}: {sec} must be a mapping, got {sub!r}")
        names = {f.name for f in dataclasses.fields(cls)}
        bad = [k for k in sub if k not in names]
        if bad:
            raise ImtuneError(f"{where}: unknown field {sec}.{bad[0]} (expected {', '.join(sorted(names))})")
        vals = {k: v for k, v in sub.items() if v is not None}
        for f in dataclasses.fields(cls):  # YAML's 2 for a float field is 2.0 (configs hash by their JSON form)
            if f.name in vals and isinstance(f.default, float) and isinstance(vals[f.name], int) \
                    and not isinstance(vals[f.name], bool):
                vals[f.name] = float(vals[f.name])
        for k in ("options", "prefilter_options", "matcher_options"):
            if k in vals:
                vals[k] = _options(vals[k], f"{where}: {sec}.{k}")
        try:
            kw[sec] = dataclasses.replace(getattr(base, sec), **vals)
        except (TypeError, ValueError) as e:
            raise ImtuneError(f"{where}: invalid {sec} section ({e})") from None
        except ImtuneError as e:  # a value the stage rejects: the message names the file too
            raise ImtuneError(f"{where}: {e}") from None
    return PipelineConfig(**kw)


def config_from_flat(d: dict, base: PipelineConfig | None = None, where: str = "configuration") -> PipelineConfig:
    """Flat command-line names (:data:`FLAT`; ``-`` or ``_``) -> PipelineConfig over ``base``."""
    nested: dict[str, dict] = {}
    for k, v in d.items():
        key = str(k).replace("-", "_")
        if key not in FLAT:
            raise ImtuneError(f"{where}: unknown option {k!r} (expected pipeline option names such as feature, "
                              f"num_features, ratio, strategy, ransac, threshold, max_iters)")
        sec, field = FLAT[key]
        nested.setdefault(sec, {})[field] = v
    return pipeline_from_dict(nested, base, where)


def config_from_imc(method: dict, where: str = "IMC method") -> PipelineConfig:
    """An official IMC benchmark method (config_common + config_<dataset>_stereo) -> PipelineConfig; one-line
    ImtuneError naming ``where`` for a section that is no mapping or a value the stages reject."""
    try:
        return _imc(method)
    except ImtuneError as e:
        raise ImtuneError(f"{where}: {e}") from None


#: the benchmark's matcher.symmetric.reduce values (its validator takes these two) -> imtune strategies
IMC_REDUCE = {"both": "both", "any": "either"}
#: the benchmark's matcher.filtering types (with num_nn 1 its snn_ratio_vs_last compares with the second neighbour)
IMC_FILTERING = ("none", "snn_ratio_pairwise", "snn_ratio_vs_last", "fginn_ratio_pairwise")
#: the benchmark's outlier_filter methods -> imtune pre-filters (cne: listed, needs trained weights)
IMC_OUTLIER_FILTERS = {"none": "none", "cne-bp-nd": "cne"}


def _section(d: dict, key: str, what: str) -> dict:
    v = d.get(key)
    if v is None:
        return {}
    if not isinstance(v, dict):
        raise ImtuneError(f"{what} must be an object, got {v!r}")
    return v


def _imc(method: dict) -> PipelineConfig:
    from pipeline.geometry import imc_geom_to_config
    common = _section(method, "config_common", "config_common")
    key = next((k for k in method if k.startswith("config_") and k.endswith("_stereo")), None)
    if key is None or not isinstance(method[key], dict):
        raise ImtuneError("IMC method config has no config_<dataset>_stereo section")
    task = method[key]
    if task.get("use_custom_matches") is True:  # was evaluated with imtune's own matcher instead, unsaid
        raise ImtuneError(f"{key}.use_custom_matches is true: the method's matches are its own h5 files, not in "
                          "this file; evaluate them with --feature custom:DIR --matches custom:DIR (IMC h5 layout)")
    name = str(common.get("descriptor") or common.get("keypoint") or "sift").lower()
    name = {"siftdef": "sift", "rootsiftdef": "rootsift"}.get(name, name)
    from pipeline.features import EXTRACTORS
    EXTRACTORS.get(name)
    fc = FeatureConfig(name=name, num_features=common.get("num_keypoints", 8000))
    m = _section(task, "matcher", f"{key}.matcher")
    filt = _section(m, "filtering", f"{key}.matcher.filtering")
    ftype = str(filt.get("type", "none")).lower()
    if ftype not in IMC_FILTERING:  # was no ratio test at all (an unknown type) or the pairwise one, unsaid
        raise ImtuneError(f"{key}.matcher.filtering: type {filt.get('type')!r} is not supported "
                          f"(supported: {', '.join(IMC_FILTERING)})")
    if str(m.get("distance", "l2")).lower() == "l1":
        raise ImtuneError(f"{key}.matcher: distance 'L1' is not supported (imtune matches float descriptors by L2, "
                          "binary ones by Hamming)")
    if m.get("num_nn", 1) != 1:  # the benchmark then keeps up to num_nn matches per keypoint
        raise ImtuneError(f"{key}.matcher: num_nn {m['num_nn']!r} is not supported (imtune keeps the nearest "
                          "neighbour only: num_nn 1)")
    ratio = filt.get("threshold", 1.0) if "ratio" in str(filt.get("type", "")) else 1.0
    if isinstance(ratio, (int, float)) and not isinstance(ratio, bool) and ratio > 1.0:
        ratio = 1.0  # IMC's r above 1 tests nothing, as r = 1 (nan is no number > 1: MatchConfig rejects it)
    sym = _section(m, "symmetric", f"{key}.matcher.symmetric")
    strategy = str(sym.get("reduce", "both")) if sym.get("enabled", True) else "uni"
    strategy = IMC_REDUCE.get(strategy.lower(), strategy)
    def num(v):  # an integer as the float field it fills; anything else as written (MatchConfig checks it)
        return float(v) if isinstance(v, int) and not isinstance(v, bool) else v
    ddf = _section(m, "descriptor_distance_filter", f"{key}.matcher.descriptor_distance_filter")
    extra = {"distance_threshold": num(ddf["threshold"])} if ddf.get("threshold") is not None else {}
    if "fginn" in str(filt.get("type", "")) and filt.get("fginn_radius") is not None:
        extra["fginn_px"] = num(filt["fginn_radius"])
    mc = MatchConfig(ratio=num(ratio),
                     strategy=strategy, fginn="fginn" in str(filt.get("type", "")),
                     method="flann" if m.get("flann") else "exact", **extra)
    of = _section(task, "outlier_filter", f"{key}.outlier_filter")
    of_method = str(of.get("method", "none")).lower()
    if of_method not in IMC_OUTLIER_FILTERS:
        raise ImtuneError(f"{key}.outlier_filter: method {of.get('method')!r} is not supported "
                          f"(supported: {', '.join(IMC_OUTLIER_FILTERS)})")
    mc = dataclasses.replace(mc, prefilter=IMC_OUTLIER_FILTERS[of_method])
    gc = GeometryConfig(**imc_geom_to_config(task.get("geom") or {}))
    return PipelineConfig(feature=fc, matching=mc, geometry=gc)


def read_mapping(path: str | Path):
    """The parsed file (JSON by suffix, else YAML with safe_load); one-line ImtuneError if unreadable."""
    import yaml

    from pipeline.fileio import load_json, load_yaml, read_text
    path = Path(path)
    text = read_text(path, "config file")
    is_json = path.suffix.lower() == ".json"
    try:
        return load_json(text, str(path)) if is_json else load_yaml(text, str(path))
    except (ValueError, yaml.YAMLError) as e:
        raise ImtuneError(f"{path}: invalid {'JSON' if is_json else 'YAML'} ({str(e).strip().splitlines()[0]})") from None


def check_names(conf: PipelineConfig, where: str) -> PipelineConfig:
    """The feature and estimator names are registered (one-line ImtuneError naming ``where`` otherwise)."""
    from pipeline.features import EXTRACTORS
    from pipeline.geometry import ESTIMATORS
    for reg, name in ((EXTRACTORS, conf.feature.name), (ESTIMATORS, conf.geometry.ransac)):
        try:
            reg.get(name)
        except ImtuneError as e:
            raise ImtuneError(f"{where}: {e}") from None
    return conf


def load_config_file(path: str | Path, base: PipelineConfig | None = None) -> ConfigFile:
    """A configuration from a file (see the module docstring); one-line ImtuneError if invalid."""
    cf = _load(Path(path), base)
    check_names(cf.conf, str(path))
    check_custom_matches(cf.conf, str(path))
    return cf


#: the matcher's fields when imported matches skip it (no ratio test): what a run with custom_matches is recorded as
SKIPPED_MATCHER = {"ratio": 1.0, "strategy": "both", "distance_threshold": None, "fginn": False, "method": "exact"}


def check_custom_matches(conf: PipelineConfig, where: str) -> PipelineConfig:
    """A configuration with ``matching.custom_matches`` whose matcher fields say something else than "skipped"
    (ratio 0.8, ...) was run without that ratio test and recorded, labelled and compared as r 0.8: one line naming
    ``where`` and the field."""
    m = conf.matching
    if m.custom_matches:
        for k, v in SKIPPED_MATCHER.items():
            if getattr(m, k) != v:
                raise ImtuneError(f"{where}: matching.{k} {getattr(m, k)!r} with custom_matches: imported matches skip "
                                  f"the matcher (no ratio test, strategy, distance threshold, FGINN); drop it or set "
                                  f"{k}: {'null' if v is None else str(v).lower()}")
    return conf


def _load(path: Path, base: PipelineConfig | None) -> ConfigFile:
    d = read_mapping(path)
    if isinstance(d, list) and d and isinstance(d[0], dict) and "config_common" in d[0]:
        d = d[0]
    if not isinstance(d, dict) or not d:
        raise ImtuneError(f"{path}: expected a mapping of configuration values")
    where = str(path)
    if "config_common" in d:
        conf = config_from_imc(d, where)
        common = d["config_common"] or {}  # null is read as {} (the defaults), as config_from_imc reads it
        return ConfigFile(conf, f"{common.get('json_label') or path.stem}: {config_label(conf)}", "imc", path=path)
    if isinstance(d.get("config"), dict):
        conf = pipeline_from_dict(d["config"], base, where)
        if "study" in d and "trial" in d:  # a frozen.yaml
            label = f"{d.get('study') or path.stem}: {config_label(conf, d.get('task'))}"
            return ConfigFile(conf, label, "frozen", frozen=d, path=path)
        beside = [k for k in d if k != "config" and (k in SECTIONS or str(k).replace("-", "_") in FLAT)]
        if beside:  # read as nothing: `geometry: {threshold: 2}` next to `config:` left eta at its default, unsaid
            raise ImtuneError(f"{where}: {beside[0]!r} is beside 'config:' and would be ignored: move it under "
                              "config: (or drop the config: level)")
        return ConfigFile(conf, f"{path.stem}: {config_label(conf)}", "config", path=path)
    if any(isinstance(d.get(k), dict) for k in ("matching", "geometry")) or isinstance(d.get("feature"), dict):
        conf = pipeline_from_dict(d, base, where)
        return ConfigFile(conf, f"{path.stem}: {config_label(conf)}", "config", path=path)
    conf = config_from_flat(d, base, where)
    return ConfigFile(conf, f"{path.stem}: {config_label(conf)}", "flat", path=path)
