"""Search spaces: YAML files in ``search_spaces/``, validated on load.

A file (read with ``yaml.safe_load`` only)::

    description: what this family is
    estimators: [degensac, pyransac, ...]   # which estimators use this file by default
    default: true                           # the file for estimators no file lists (at most one)
    params:                                 # the searched parameters
      ratio:      {type: float, low: 0.6, high: 1.0, grid: [0.6, 0.7, 0.8, 0.9, 1.0]}
      threshold:  {type: float, low: 0.1, high: 2.0, log: true}      # eta, px at <= 1024 px
      max_iters:  {type: int, low: 1000, high: calibrated, log: true} # Gamma, capped by the budget
      strategy:   {type: categorical, choices: [both, either, uni]}   # optional
      # a scalar pins a parameter:  strategy: both
    features:                               # overrides per feature family or feature name
      binary: {ratio: {low: 0.7, high: 1.0}}
    calibration: {ratio: 0.9, threshold: 0.5}  # matches the budget is calibrated on

Parameters: ``ratio`` (Lowe's r in (0, 1]; 1 = off), ``threshold`` (eta, px), ``max_iters`` (Gamma;
``high: calibrated`` = the measured cap Gamma_max(B) for the study's budget B), ``strategy``
(both | either | uni), ``min_confidence`` (a learned matcher's confidence threshold in [0, 1], searched in place of
r and the strategy with ``--matcher lightglue``, dropped otherwise). Unlisted parameters keep the command line's value (``--strategy``) and are
recorded as fixed. Feature families: ``binary`` (Hamming descriptors), ``float``, ``learned``;
a feature name (``orb``) wins over its family. ``grid`` lists the values the grid sampler visits
(default: 5 values over the range; the cap for ``max_iters``).
"""
from __future__ import annotations

import copy
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from pipeline.errors import ImtuneError
from tuner.protocol import PARAMS, TYPES, leaf

SPACES_DIR = Path(__file__).resolve().parents[1] / "search_spaces"
TOP_KEYS = ("description", "estimators", "default", "params", "features", "calibration")
PARAM_KEYS = ("type", "low", "high", "log", "step", "choices", "grid")
FAMILIES = ("binary", "float", "learned")
CALIBRATED = "calibrated"
DEFAULT_GRID_POINTS = 5


@dataclass
class Param:
    """One searched parameter: a float / int range (optionally log-uniform) or categorical choices."""
    name: str
    type: str
    low: float | int | str | None = None
    high: float | int | str | None = None
    log: bool = False
    step: float | int | None = None
    choices: list | None = None
    grid: list | None = None

    def spec(self) -> dict:
        d = {"type": self.type}
        if self.type == "categorical":
            d["choices"] = list(self.choices)
        else:
            d.update(low=self.low, high=self.high, log=bool(self.log))
            if self.step is not None:
                d["step"] = self.step
        if self.grid is not None:
            d["grid"] = list(self.grid)
        return d

    def distribution(self):
        import optuna.distributions as od
        if self.type == "categorical":
            return od.CategoricalDistribution(list(self.choices))
        if self.type == "int":
            return od.IntDistribution(int(self.low), int(self.high), log=bool(self.log), step=int(self.step or 1))
        return od.FloatDistribution(float(self.low), float(self.high), log=bool(self.log), step=self.step)

    def suggest(self, trial):
        if self.type == "categorical":
            return trial.suggest_categorical(self.name, list(self.choices))
        if self.type == "int":
            return trial.suggest_int(self.name, int(self.low), int(self.high), log=bool(self.log),
                                     step=int(self.step or 1))
        return trial.suggest_float(self.name, float(self.low), float(self.high), log=bool(self.log), step=self.step)

    def grid_values(self) -> list:
        if self.grid is not None:
            return list(self.grid)
        if self.type == "categorical":
            return list(self.choices)
        if self.name == "max_iters":
            return [int(self.high)]
        import numpy as np
        lo, hi = float(self.low), float(self.high)
        vals = np.geomspace(lo, hi, DEFAULT_GRID_POINTS) if self.log else np.linspace(lo, hi, DEFAULT_GRID_POINTS)
        if self.step:  # on the step's values (a value between them is out of Optuna's distribution)
            vals = sorted({lo + round((v - lo) / self.step) * self.step for v in vals})
        if self.type == "int":
            return sorted({int(round(v)) for v in vals})
        return [float(f"{v:.4g}") for v in vals]


@dataclass
class SearchSpace:
    """Searched parameters, pinned (fixed) parameters, and the calibration settings.

    ``source`` names the file(s) it came from (for messages)."""
    params: dict[str, Param]
    fixed: dict[str, object] = field(default_factory=dict)
    calibration: dict = field(default_factory=lambda: {"ratio": 0.9, "threshold": 0.5})
    source: str = ""
    description: str = ""

    def spec(self) -> dict:
        """Canonical, JSON-able form (stored in the study; compared when a study is resumed)."""
        return {"params": {k: self.params[k].spec() for k in sorted(self.params)},
                "fixed": {k: self.fixed[k] for k in sorted(self.fixed)}}

    def spec_hash(self) -> str:
        return hashlib.sha1(json.dumps(self.spec(), sort_keys=True).encode()).hexdigest()[:12]

    @property
    def needs_calibration(self) -> bool:
        p = self.params.get("max_iters")
        if self.fixed.get("max_iters") == CALIBRATED:  # --fix max_iters=calibrated: Gamma_max(B) itself
            return True
        return p is not None and (p.high == CALIBRATED or p.low == CALIBRATED)

    def resolve(self, gamma_max: int | None) -> SearchSpace:
        """A copy with ``calibrated`` replaced by ``gamma_max`` (the low bound clipped to it; with a ``step``, the
        largest value low + k step <= gamma_max)."""
        out = copy.deepcopy(self)
        p = out.params.get("max_iters")
        if p is not None and out.needs_calibration:
            if gamma_max is None:
                raise ImtuneError("search space: max_iters high is 'calibrated' but no calibration is available")
            g = int(gamma_max)
            if p.high == CALIBRATED:
                p.high = g
            if p.low == CALIBRATED:
                p.low = g
            p.low = min(int(p.low), g)
            if p.step and p.high == g:  # Gamma_max off the step: Optuna moved high itself, with two UserWarnings
                g = p.low + (g - p.low) // int(p.step) * int(p.step)
                p.high = g
            if p.grid is not None:
                p.grid = [g if v == CALIBRATED else int(v) for v in p.grid]
                p.grid = [v for v in p.grid if p.low <= v <= p.high] or [g]
        if isinstance(out.fixed.get("max_iters"), str):
            out.fixed["max_iters"] = int(gamma_max)
        return out

    def suggest(self, trial) -> dict:
        """Searched values for this trial (fixed values are not trial parameters)."""
        return {name: p.suggest(trial) for name, p in self.params.items()}

    def distributions(self) -> dict:
        return {k: p.distribution() for k, p in self.params.items()}

    def grid(self) -> dict[str, list]:
        return {k: p.grid_values() for k, p in self.params.items()}

    def grid_size(self) -> int:
        n = 1
        for v in self.grid().values():
            n *= len(v)
        return n

    def fix(self, name: str, value) -> None:
        """Pin ``name`` to ``value`` (validated), removing it from the searched parameters."""
        self.params.pop(name, None)
        self.fixed[name] = _check_value(name, value, f"--fix {name}")

    @classmethod
    def from_spec(cls, spec: dict, source: str = "study") -> SearchSpace:
        """Inverse of :meth:`spec` (values already validated)."""
        params = {k: Param(name=k, **v) for k, v in spec.get("params", {}).items()}
        return cls(params=params, fixed=dict(spec.get("fixed", {})), source=source)


# -- loading & validation -------------------------------------------------------------------------

def _err(where: str, msg: str) -> ImtuneError:
    return ImtuneError(f"search space {where}: {msg}")


def _num(where: str, key: str, v, allow_calibrated: bool = False):
    if allow_calibrated and v == CALIBRATED:
        return v
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        from pipeline.config import yaml_number_hint
        extra = " or 'calibrated'" if allow_calibrated else ""
        raise _err(where, f"{key} must be a number{extra}, got {v!r}{yaml_number_hint(v)}")
    return v


def _check_value(name: str, value, where: str):
    """Validate a pinned value for parameter ``name`` against the protocol table (strings from --fix are
    converted); ``max_iters`` may also be ``calibrated`` (Gamma_max of the study's budget)."""
    if name == "max_iters" and value == CALIBRATED:
        return value
    return leaf(name, where).check(value, where)


def _on_step(v, low, step) -> bool:
    """``v`` is ``low`` + a whole number of ``step`` (to rounding)."""
    k = (v - low) / step
    return abs(k - round(k)) <= 1e-9 * max(1.0, abs(k))


def _check_param(name: str, d, where: str):
    """A validated Param, or a fixed value when ``d`` is a scalar."""
    w = f"{where}: params.{name}"
    if not isinstance(d, dict):
        return _check_value(name, d, w)
    unknown = [k for k in d if k not in PARAM_KEYS]
    if unknown:
        raise ImtuneError(f"{w}: unknown key {unknown[0]!r} (expected {', '.join(PARAM_KEYS)})")
    t = d.get("type", TYPES[name])
    if t not in ("float", "int", "categorical"):
        raise ImtuneError(f"{w}: type must be float, int or categorical, got {t!r}")
    if t not in (TYPES[name], "categorical"):
        raise ImtuneError(f"{w}: type must be {TYPES[name]} or categorical, got {t!r}")
    if t == "categorical":
        ch = d.get("choices")
        if not isinstance(ch, list) or not ch:
            raise ImtuneError(f"{w}: choices must be a non-empty list")
        ch = [_check_value(name, c, f"{w}.choices") for c in ch]
        if len(set(map(str, ch))) != len(ch):
            raise ImtuneError(f"{w}: choices has duplicates")
        for k in ("low", "high", "log", "step"):
            if k in d:
                raise ImtuneError(f"{w}: {k} does not apply to a categorical parameter")
        grid = d.get("grid")
        if grid is not None:
            if not isinstance(grid, list) or not grid or any(g not in ch for g in grid):
                raise ImtuneError(f"{w}: grid must be a non-empty list of the choices")
        return Param(name=name, type=t, choices=ch, grid=grid)
    if "choices" in d:
        raise ImtuneError(f"{w}: choices only applies to type categorical")
    for k in ("low", "high"):
        if k not in d:
            raise ImtuneError(f"{w}: missing {k}")
    calib_ok = name == "max_iters"
    low = _num(w, "low", d["low"], calib_ok)
    high = _num(w, "high", d["high"], calib_ok)
    log = d.get("log", False)
    if not isinstance(log, bool):
        raise ImtuneError(f"{w}: log must be true or false, got {log!r}")
    step = d.get("step")
    if step is not None:
        _num(w, "step", step)
        if step <= 0:
            raise ImtuneError(f"{w}: step must be > 0, got {step}")
        if log:
            raise ImtuneError(f"{w}: step and log cannot be combined")
    if t == "int":
        for k, v in (("low", low), ("high", high)):
            if v != CALIBRATED and float(v) != int(v):
                raise ImtuneError(f"{w}: {k} must be an integer, got {v!r}")
        low = low if low == CALIBRATED else int(low)
        high = high if high == CALIBRATED else int(high)
    if low != CALIBRATED and high != CALIBRATED and low > high:
        raise ImtuneError(f"{w}: low {low} > high {high}")
    if step is not None and t == "int" and float(step) != int(step):
        raise ImtuneError(f"{w}: step must be an integer for an int parameter, got {step!r}")
    stepped = step is not None and CALIBRATED not in (low, high)
    if stepped and not _on_step(high, low, step):  # Optuna moved high (and off-step grid values), with warnings
        raise ImtuneError(f"{w}: step {step} does not divide [{low}, {high}]: make high - low a multiple of step "
                          f"(e.g. high {low + math.floor((high - low) / step) * step:.6g})")
    if low == CALIBRATED and high != CALIBRATED:
        raise ImtuneError(f"{w}: low is 'calibrated' but high is not")
    for k, v in (("low", low), ("high", high)):
        if v == CALIBRATED:
            continue
        if log and v <= 0:
            raise ImtuneError(f"{w}: {k} must be > 0 with log: true, got {v}")
        _check_value(name, v, f"{w}.{k}")
    grid = d.get("grid")
    if grid is not None:
        if not isinstance(grid, list) or not grid:
            raise ImtuneError(f"{w}: grid must be a non-empty list")
        checked = []
        for g in grid:
            if name == "max_iters" and g == CALIBRATED:
                checked.append(g)
                continue
            g = _check_value(name, _num(w, "grid value", g), f"{w}.grid")
            if (low != CALIBRATED and g < low) or (high != CALIBRATED and g > high):
                raise ImtuneError(f"{w}: grid value {g} outside [{low}, {high}]")
            if stepped and not _on_step(g, low, step):
                raise ImtuneError(f"{w}: grid value {g} is not low {low} + a multiple of step {step}")
            checked.append(g)
        grid = checked
    return Param(name=name, type=t, low=low, high=high, log=log, step=step, grid=grid)


def _check_feature_key(path: Path, key) -> None:
    """A ``features:`` key is a family (binary, float, learned) or a feature name: a misspelt one (``sfit``) applied
    to no feature, its ranges never searched, unsaid."""
    if key in FAMILIES or str(key).startswith("custom:"):
        return
    from pipeline.features import EXTRACTORS
    try:
        EXTRACTORS.get(str(key))
    except ImtuneError:
        from pipeline.registry import did_you_mean
        raise ImtuneError(f"search space {path}: features.{key}: not a feature family ({', '.join(FAMILIES)}) nor "
                          f"a feature name{did_you_mean(str(key), list(FAMILIES) + EXTRACTORS.names())} (see `tune "
                          "list`)") from None


def read_yaml(path: Path) -> dict:
    """Parse one search-space file (yaml.safe_load) and check its top-level shape."""
    from pipeline.fileio import load_yaml, read_text
    path = Path(path)
    text = read_text(path, "search space")
    try:
        data = load_yaml(text, f"search space {path}")
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ImtuneError(f"search space {path}: invalid YAML ({where}{problem})") from None
    if not isinstance(data, dict):
        raise ImtuneError(f"search space {path}: expected a mapping with a 'params' key")
    unknown = [k for k in data if k not in TOP_KEYS]
    if unknown:
        raise ImtuneError(f"search space {path}: unknown key {unknown[0]!r} (expected {', '.join(TOP_KEYS)})")
    if "params" not in data or not isinstance(data["params"], dict):
        raise ImtuneError(f"search space {path}: 'params' must be a mapping of parameter -> range")
    for k in data["params"]:
        if k not in PARAMS:
            raise ImtuneError(f"search space {path}: unknown parameter params.{k} (expected {', '.join(PARAMS)})")
    feats = data.get("features", {}) or {}
    if not isinstance(feats, dict):
        raise ImtuneError(f"search space {path}: 'features' must be a mapping of family or feature -> params")
    for fam, over in feats.items():
        if not isinstance(over, dict):
            raise ImtuneError(f"search space {path}: features.{fam} must be a mapping of parameter -> range")
        _check_feature_key(path, fam)
        for k in over:
            if k not in PARAMS:
                raise ImtuneError(f"search space {path}: unknown parameter features.{fam}.{k} (expected {', '.join(PARAMS)})")
    est = data.get("estimators", [])
    if not isinstance(est, list) or not all(isinstance(e, str) for e in est):
        raise ImtuneError(f"search space {path}: 'estimators' must be a list of estimator names")
    cal = data.get("calibration", {}) or {}
    if not isinstance(cal, dict) or any(k not in ("ratio", "threshold") for k in cal):
        raise ImtuneError(f"search space {path}: 'calibration' takes only ratio and threshold")
    for k, v in cal.items():
        _check_value(k, v, f"search space {path}: calibration.{k}")
    if not isinstance(data.get("default", False), bool):
        raise ImtuneError(f"search space {path}: 'default' must be true or false")
    return data


def feature_families(feature: str) -> list[str]:
    """Override keys that apply to a feature, most general first: its family tags, then its name."""
    fams = []
    try:
        from pipeline.features import EXTRACTORS
        cls = EXTRACTORS.get(feature)
        fams.append("binary" if getattr(cls, "binary", False) else "float")
        mod = getattr(cls, "__module__", "")
        if getattr(cls, "learned", False) or "learned" in mod or "kornia" in mod:
            fams.append("learned")
    except ImtuneError:
        pass
    return fams + [feature]


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = {**out[k], **v}
        else:
            out[k] = copy.deepcopy(v)
    return out


def build_space(data: dict, source: str, feature: str | None = None, estimator: str | None = None,
                matcher: str | None = None) -> SearchSpace:
    """Validate a parsed file and apply the feature's overrides, the estimator's capabilities and the matcher's: a
    learned ``matcher`` (``lightglue``) searches its confidence threshold ``min_confidence`` in place of r and the
    strategy; any other (None: exact) the reverse (``tuner.protocol.KNN_ONLY`` / ``LEARNED_ONLY``)."""
    raw = dict(data["params"])
    for key in feature_families(feature) if feature else []:
        over = (data.get("features") or {}).get(key)
        if over:
            raw = _merge(raw, over)
    params, fixed = {}, {}
    for name, d in raw.items():
        p = _check_param(name, d, source)
        if isinstance(p, Param):
            params[name] = p
        else:
            fixed[name] = p
    calibration = {"ratio": 0.9, "threshold": 0.5, **(data.get("calibration") or {})}
    space = SearchSpace(params=params, fixed=fixed, calibration=calibration, source=source,
                        description=str(data.get("description", "")))
    from pipeline.matching.learned import is_learned
    from tuner.protocol import KNN_ONLY, LEARNED_ONLY
    for name in KNN_ONLY if matcher and is_learned(matcher) else LEARNED_ONLY:
        space.params.pop(name, None)
        space.fixed.pop(name, None)
    if estimator:
        try:
            from pipeline.geometry import ESTIMATORS
            cls = ESTIMATORS.get(estimator)
        except ImtuneError:
            cls = None
        if cls is not None:
            if not getattr(cls, "uses_threshold", True) and "threshold" in space.params:
                space.params.pop("threshold")
            if not getattr(cls, "uses_iterations", True) and "max_iters" in space.params:
                space.params.pop("max_iters")
    return space


def space_files() -> list[Path]:
    return sorted(SPACES_DIR.glob("*.yaml"))


def default_space_file(estimator: str) -> Path:
    """The file in ``search_spaces/`` whose ``estimators`` lists ``estimator`` (else the default file)."""
    default = None
    for f in space_files():
        data = read_yaml(f)
        if estimator in (data.get("estimators") or []):
            return f
        if data.get("default"):
            default = f
    if default is None:
        raise ImtuneError(f"no search space for estimator {estimator!r} in {SPACES_DIR} and no default file")
    return default


def load_space(path: str | Path | None = None, *, feature: str | None = None, estimator: str | None = None,
               fixes: list[str] | dict | None = None, matcher: str | None = None) -> SearchSpace:
    """The search space: ``path`` (``--space``) or the default file for ``estimator``; the feature's
    overrides applied; the parameters ``matcher`` does not use dropped (:func:`build_space`); ``fixes``
    (``["name=value", ...]`` or a dict) pinned. Raises ImtuneError naming the file and key on any problem."""
    f = Path(path) if path else default_space_file(estimator or "degensac")
    data = read_yaml(f)
    # imtune's own file by its place in the project: the label is stored with a study, and an absolute path named
    # the checkout that created it on every other machine reading the storage (/work/ci/x/search_spaces/...)
    label = str(f) if path else f"{SPACES_DIR.name}/{f.name}"
    space = build_space(data, label, feature=feature, estimator=estimator, matcher=matcher)
    for name, value in parse_fixes(fixes).items():
        space.fix(name, value)
    return space


def parse_fixes(fixes) -> dict:
    if not fixes:
        return {}
    if isinstance(fixes, dict):
        items = list(fixes.items())
    else:
        items = []
        for s in fixes:
            if "=" not in s:
                raise ImtuneError(f"--fix {s!r}: expected name=value (names: {', '.join(PARAMS)})")
            k, v = s.split("=", 1)
            items.append((k.strip(), v.strip()))
    out = {}
    for k, v in items:
        if k not in PARAMS:
            raise ImtuneError(f"--fix {k}: unknown parameter (expected {', '.join(PARAMS)})")
        if k in out and out[k] != v:  # the last one won without a word
            raise ImtuneError(f"--fix {k} is given twice ({k}={out[k]} and {k}={v}): give it once")
        out[k] = v
    return out
