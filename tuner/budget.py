"""The time budget: estimator seconds per pair against the iteration cap Gamma, measured on this machine.

The paper caps every estimator's iterations so that it spends at most B seconds per image pair
(B = 0.5 s on validation, 1 s on test). :func:`calibrate` measures the cost curve — median (and 90th
percentile) estimator seconds per pair against max_iters — on a sample of the validation pairs'
tentative matches, and :meth:`Calibration.gamma_max` reads off Gamma_max(B), the largest cap whose
median time per pair stays within B (log-log interpolation between measured points).

Calibrations are stored per machine, estimator, feature configuration, calibration matches and data
in ``<studies dir>/budgets.json`` (written atomically under a file lock, so workers starting together
measure once), and copied into each study's user attributes when the study is created.

The seconds are CPU time (``clock: "cpu"``; :func:`pipeline.geometry.base.timed`): what neighbours on the machine do
not change. The wall time of the same calls is kept beside it (``wall_curve``). A stored calibration without
``clock`` was measured in wall-clock seconds (imtune before the CPU-time budget): it is never used, but measured
again (and replaced) when next needed.

``jobs``: a study evaluates its pairs with ``jobs`` worker processes, so the estimator is timed with ``jobs``
copies of it running at once (each in its own spawned process, started together at a barrier:
:class:`pipeline.tasks.pool.ConcurrentRunner`); the curve's median is over every process's pairs. Gamma_max(B) then
reflects a machine whose cores are all busy (memory bandwidth, caches, turbo shared), not one idle core. The number
of jobs is part of the stored calibration's key.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import fcntl
import json
import math
import socket
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError

GAMMA_START = 100
GAMMA_CEILING = 1_000_000
BUDGETS_FILE = "budgets.json"
CLOCK = "cpu"  # what the budget's seconds are: CPU time of the estimator call (a stored calibration without it: wall)


@dataclass
class Calibration:
    """One measured cost curve.

    curve: [(max_iters, median seconds per pair, 90th-percentile seconds per pair), ...] sorted by
    max_iters, in CPU seconds when ``clock`` is "cpu" (wall seconds in a calibration stored without ``clock``);
    wall_curve: the same in wall-clock seconds (reported, never budgeted); pairs: how many pairs were timed per
    point; ratio / threshold: the matches and eta used; ceiling: the largest cap ever allowed."""
    estimator: str
    feature: dict
    ratio: float
    threshold: float
    pairs: int
    curve: list
    host: str = ""
    created: str = ""
    data_fingerprint: str = ""
    ceiling: int = GAMMA_CEILING
    seconds: float = 0.0  # wall time the measurement took
    jobs: int = 1  # estimator processes timed at once (a study with --jobs N is calibrated with N)
    clock: str = "wall"  # "cpu" (CLOCK) since the CPU-time budget; a stored entry without it is wall-clock seconds
    wall_curve: list = dataclasses.field(default_factory=list)

    def gamma_max(self, budget: float) -> int:
        """Largest max_iters whose median estimator CPU time per pair is <= ``budget`` seconds (on the curve's
        non-decreasing envelope: a larger cap never costs less, a lower median there is timing noise)."""
        pts = _envelope(self.curve)
        if not pts:
            raise ImtuneError(f"calibration of {self.estimator}: empty curve")
        ok = [(g, m) for g, m in pts if m <= budget]
        if not ok:  # even the smallest cap is too slow: extrapolate linearly down
            g0, m0 = pts[0]
            return max(1, _round_down(g0 * budget / max(m0, 1e-9)))
        g_lo, m_lo = ok[-1]
        above = [(g, m) for g, m in pts if g > g_lo and m > budget]
        if not above:
            if g_lo >= self.ceiling or len(pts) < 2:
                return _round_down(min(g_lo, self.ceiling))
            # the curve never crossed B (measurement stopped early or the estimator terminates early)
            g2, m2 = pts[-1]
            if _flat(pts):  # time no longer grows with the cap (early termination)
                return _round_down(self.ceiling if g2 >= self.ceiling else min(self.ceiling, g2 * 10))
            # extrapolate the slope over the last FLAT_SPAN x of caps (a 1.2x step's slope is mostly noise),
            # at most 10x, never past the ceiling
            g1, m1 = _span_start(pts)
            slope = math.log(max(m2, 1e-9) / max(m1, 1e-9)) / math.log(g2 / g1)
            g = g2 * (budget / m2) ** (1.0 / max(slope, 1e-3))
            return _round_down(min(g, g2 * 10, self.ceiling))
        g_hi, m_hi = above[0]
        if m_lo <= 0:
            return _round_down(g_lo)
        t = (math.log(budget) - math.log(m_lo)) / (math.log(m_hi) - math.log(m_lo))
        g = math.exp(math.log(g_lo) + t * (math.log(g_hi) - math.log(g_lo)))
        return _round_down(min(max(g, g_lo), g_hi, self.ceiling))

    def covers(self, budget: float) -> bool:
        """True when the measured curve reaches ``budget`` (so gamma_max(budget) is interpolated, not
        extrapolated), or when the estimator's time no longer grows with the cap."""
        pts = _envelope(self.curve)
        gmax = max((g for g, _ in pts), default=0)
        return bool(pts) and (pts[-1][1] > budget or gmax >= self.ceiling or _flat(pts))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Calibration:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


FLAT_SPAN = 3.0  # the cap must grow this many times without the median time growing for the curve to count as flat


def _envelope(curve) -> list[tuple[int, float]]:
    """[(max_iters, median s per pair)] sorted by the cap, each median raised to the largest at a smaller cap."""
    out, top = [], 0.0
    for g, m, *_ in sorted(curve, key=lambda c: int(c[0])):
        top = max(top, float(m))
        out.append((int(g), top))
    return out


def _span_start(pts: list[tuple[int, float]]) -> tuple[int, float]:
    """The point of the largest cap at least FLAT_SPAN x below the last one (else the first point)."""
    g2 = pts[-1][0]
    return next(((g, m) for g, m in reversed(pts[:-1]) if g * FLAT_SPAN <= g2), pts[0])


def _flat(pts: list[tuple[int, float]]) -> bool:
    """The median time stopped growing with the cap (an estimator that terminates early): the last median is within 5%
    of the one at a cap FLAT_SPAN x smaller. One step near the budget (1.2-1.35x) cannot show it: a noisy median
    there (DEGENSAC 2k SIFT: 0.48 s at 412k, 0.39 s at 558k) read as flat set Gamma_max to the ceiling, 1,000,000."""
    if len(pts) < 2:
        return False
    g1, m1 = _span_start(pts)
    return g1 * FLAT_SPAN <= pts[-1][0] and pts[-1][1] <= m1 * 1.05


def _round_down(g: float) -> int:
    """Two significant digits, rounded down (a cap is a bound, never rounded up past the budget)."""
    g = max(float(g), 1.0)
    e = max(int(math.floor(math.log10(g))) - 1, 0)
    return int(math.floor(g / 10 ** e) * 10 ** e)


def calibration_key(estimator: str, feature_conf, ratio: float, threshold: float, data_fingerprint: str,
                    jobs: int = 1, matching=None) -> str:
    """The budgets.json key of a calibration. ``matching``: the MatchConfig whose matches are timed; a learned
    matcher's (its name and confidence threshold) is part of the key, the k-NN matcher's r is already."""
    from pipeline.config import config_hash
    parts = [socket.gethostname(), estimator, config_hash(feature_conf, 10), f"r={ratio:g}", f"eta={threshold:g}",
             data_fingerprint]
    if int(jobs) != 1:  # a calibration measured alone keeps its key (stores written before --jobs stay valid)
        parts.append(f"jobs={int(jobs)}")
    if matching is not None and getattr(matching, "learned", False):  # (k-NN keys stay as they were)
        parts.append(f"{matching.method}:c={matching.min_confidence:g}:{sorted(dict(matching.matcher_options).items())}")
    return "|".join(parts)


# -- the store --------------------------------------------------------------------------------------

@contextmanager
def _locked(path: Path):
    from pipeline.fileio import folder_error
    from tuner.storage import STUDIES_DIR_FIX
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(str(path) + ".lock", "a+")
    except OSError as e:  # read-only, a file in the way, full: one line naming the folder
        raise folder_error(path.parent, e, "studies folder", STUDIES_DIR_FIX) from None
    with fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _read_store(path: Path) -> dict:
    """The calibrations stored in ``path`` ({} when there is no file). A file that cannot be read or is no JSON
    object is a one-line ImtuneError: never trusted, and never silently replaced by a file holding only the next
    calibration measured (the others, each a minute of measuring, would be lost without a word)."""
    if not path.is_file():
        return {}
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise ImtuneError(f"cannot read the calibration store {path}: {e.strerror or e}") from None
    try:
        d = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as e:
        why = f"not valid JSON (byte 0x{raw[e.start]:02x} at offset {e.start} is no UTF-8 text)"
    except ValueError as e:  # JSONDecodeError
        why = f"not valid JSON ({str(e).splitlines()[0][:120]})"
    else:
        if isinstance(d, dict):
            return d
        why = f"a JSON {type(d).__name__}, not an object of calibrations"
    raise ImtuneError(f"{path} is {why}; delete it (its calibrations are measured again when next needed) or "
                      "restore it from a copy")


def _write_store(path: Path, data: dict) -> None:
    from pipeline.fileio import atomic_write  # one atomic writer (temp name, fsync, rename) for all result files
    atomic_write(path, json.dumps(data, indent=1, sort_keys=True))


def _is_int(v, lo: int) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _is_real(v, lo: float = 0.0, strict: bool = False) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and \
        (v > lo if strict else v >= lo)


def calibration_problem(d) -> str | None:
    """What is wrong with a stored calibration (a budgets.json entry), or None when it can be used: every cap of the
    curve a positive integer, every time a finite number >= 0 s, the ceiling a positive integer, r in (0, 1],
    eta > 0, jobs a positive integer, pairs an integer >= 0. NaN, strings or negative numbers there gave a crash ("cannot
    convert float NaN to integer") or, worse, a silent Gamma_max of 1 for every trial."""
    if not isinstance(d, dict):
        return f"expected a mapping, got {type(d).__name__}"
    missing = [k for k in ("estimator", "curve", "ratio", "threshold", "pairs") if k not in d]
    if missing:
        return f"no {missing[0]!r}"
    curve = d["curve"]
    if not isinstance(curve, list) or not curve:
        return "'curve' must be a non-empty list of [max_iters, median seconds, p90 seconds]"
    for i, pt in enumerate(curve):
        if not isinstance(pt, (list, tuple)) or len(pt) < 2:
            return f"curve[{i}] must be [max_iters, median seconds, p90 seconds], got {pt!r}"
        if not _is_int(pt[0], 1):
            return f"curve[{i}]: the cap max_iters must be a positive integer, got {pt[0]!r}"
        for j, v in enumerate(pt[1:3], 1):
            if not _is_real(v):
                what = ("median", "p90")[j - 1]
                return f"curve[{i}]: the {what} seconds per pair must be a finite number >= 0, got {v!r}"
    checks = (("ceiling", lambda v: _is_int(v, 1), "a positive integer"),
              ("ratio", lambda v: _is_real(v, 0.0, strict=True) and v <= 1.0, "a number in (0, 1]"),
              ("threshold", lambda v: _is_real(v, 0.0, strict=True), "a number > 0"),
              ("pairs", lambda v: _is_int(v, 0), "an integer >= 0"),
              ("jobs", lambda v: _is_int(v, 1), "a positive integer"),
              ("seconds", _is_real, "a finite number >= 0"),
              ("clock", lambda v: v in ("cpu", "wall"), '"cpu" or "wall"'))
    for key, ok, what in checks:
        if key in d and not ok(d[key]):
            return f"{key!r} must be {what}, got {d[key]!r}"
    if not isinstance(d["estimator"], str) or not isinstance(d.get("feature", {}), dict):
        return "'estimator' must be a name and 'feature' a mapping"
    return None


def _checked(path: Path, key: str, d) -> Calibration:
    """The stored calibration ``key`` of ``path``, validated (:func:`calibration_problem`): never silently used when
    invalid, a one-line ImtuneError naming the file and the entry and saying how to measure it again."""
    why = calibration_problem(d)
    if why is None:
        try:
            return Calibration.from_dict(d)
        except TypeError as e:  # an unexpected shape of an otherwise valid-looking entry
            why = str(e)
    raise ImtuneError(f"{path}: the stored calibration {key!r} is invalid ({why}); delete that entry (or the file) "
                      "or measure it again with `tune calibrate --force` (`tune run --recalibrate`)")


def stored_calibration(studies_dir: Path, key: str) -> Calibration | None:
    path = Path(studies_dir) / BUDGETS_FILE
    store = _read_store(path)
    if key not in store:
        return None
    return _checked(path, key, store[key])


def list_calibrations(studies_dir: Path) -> dict[str, Calibration]:
    path = Path(studies_dir) / BUDGETS_FILE
    return {k: _checked(path, k, v) for k, v in _read_store(path).items()}


# -- measuring --------------------------------------------------------------------------------------

def calibration_matches(scenes, conf, cache, max_pairs: int = 8, progress: bool = False):
    """Tentative matches of up to ``max_pairs`` validation pairs (evenly spread over all pairs), at
    the working resolution: list of (pts1, pts2, sizes, K1, K2) (K: intrinsics at the working resolution, or
    None when the scene has none)."""
    from pipeline.tasks.prepare import tentative_matches
    from pipeline.tasks.stereo import prepare_scene
    allp = [(s, p) for s, pairs in scenes for p in pairs]
    if not allp:
        raise ImtuneError("calibration: no validation pairs")
    idx = np.unique(np.linspace(0, len(allp) - 1, min(max_pairs, len(allp))).round().astype(int))
    chosen: dict[str, tuple] = {}
    for k in idx:
        s, p = allp[k]
        chosen.setdefault(s.name, (s, []))[1].append(p)
    out = []
    for s, pairs in chosen.values():
        feats, tables = prepare_scene(s, conf, cache, pairs, progress=progress)
        for p in pairs:
            tab, _ = tables[p.key]
            fi, fj = feats[p.i], feats[p.j]
            m, _ = tentative_matches(tab, conf.matching, fi, fj, task="stereo")  # same matches a trial sees
            if len(m) < 8:
                continue
            from pipeline.tasks.stereo import working_intrinsics
            K1, K2 = working_intrinsics(s, p, fi, fj)  # an E estimator is timed with the pair's intrinsics
            out.append((fi.keypoints[m[:, 0]].astype(np.float64), fj.keypoints[m[:, 1]].astype(np.float64),
                        ((fi.width, fi.height), (fj.width, fj.height)), K1, K2))
    if not out:
        at = f"confidence > {conf.matching.min_confidence:g}" if conf.matching.learned else f"r={conf.matching.ratio}"
        raise ImtuneError(f"calibration: no validation pair has 8 or more tentative matches at {at}; cannot time the "
                          "estimator")
    return out


def _time_cap(payload, g: int) -> list[tuple[float, float]]:
    """(CPU seconds, wall seconds) of the estimator on every calibration pair at cap ``g`` (``payload``: name, matches,
    eta, confidence, seed)."""
    from pipeline.geometry import get_estimator
    name, matches, threshold, confidence, seed = payload
    est = get_estimator(name)
    calibrated = getattr(est, "model", "F") == "E"  # calibrated: takes the pair's intrinsics
    out = []
    for p1, p2, sz, *K in matches:
        if calibrated:
            r = est.estimate(p1, p2, threshold, confidence, int(g), seed=seed, sizes=sz,  # type: ignore[call-arg]
                             K1=K[0], K2=K[1])
        else:
            r = est.estimate(p1, p2, threshold, confidence, int(g), seed=seed, sizes=sz)
        out.append((float(r.seconds), float(r.wall_seconds)))
    return out


@contextmanager
def cap_timer(estimator_name: str, matches, threshold: float, confidence: float, seed: int = 0, jobs: int = 1):
    """``with cap_timer(...) as time_cap: time_cap(g)`` -> [(CPU s, wall s) per pair] of the estimator at cap ``g``;
    ``jobs`` > 1: timed in ``jobs`` processes at once, each on all the pairs (their lists concatenated)."""
    payload = (estimator_name, matches, threshold, confidence, seed)
    if int(jobs) > 1:
        from pipeline.tasks.pool import ConcurrentRunner
        with ConcurrentRunner(int(jobs), payload) as run:
            yield lambda g: [s for part in run(_time_cap, int(g)) for s in part]
    else:
        from pipeline.tasks.pool import one_thread_here
        with one_thread_here():  # timed as in a worker: no idle BLAS thread spinning on this process's CPU clock
            yield lambda g: _time_cap(payload, int(g))


def measure_curve(estimator_name: str, matches, threshold: float, confidence: float, budget: float,
                  seed: int = 0, ceiling: int = GAMMA_CEILING, progress: bool = False, jobs: int = 1,
                  wall_curve: list | None = None) -> list:
    """Time the estimator at increasing caps until the median CPU time per pair exceeds ``budget``
    (the next cap is aimed just past the budget, so measuring costs a few times B per pair). ``jobs`` > 1: every
    cap is timed in ``jobs`` processes at once, each on all the pairs; the statistics are over all of them.
    ``wall_curve``: a list that receives the same points in wall-clock seconds."""
    with cap_timer(estimator_name, matches, threshold, confidence, seed=seed, jobs=jobs) as time_cap:
        return _measure(estimator_name, time_cap, budget, ceiling, progress, wall_curve=wall_curve)


def _stats(secs) -> tuple[float, float]:
    return float(np.median(secs)), float(np.percentile(secs, 90))


def _measure(estimator_name: str, time_cap, budget: float, ceiling: int, progress: bool,
             wall_curve: list | None = None) -> list:
    """``time_cap(g)``: per pair, CPU seconds or (CPU seconds, wall seconds) at cap ``g``."""
    curve = []
    g = GAMMA_START
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(desc=f"calibrating {estimator_name}", unit="cap", leave=False)
    try:
        while True:
            got = time_cap(g)
            secs = [x[0] if isinstance(x, tuple) else x for x in got]
            med, p90 = _stats(secs)
            curve.append((int(g), med, p90))
            if wall_curve is not None:
                wall_curve.append((int(g), *_stats([x[1] if isinstance(x, tuple) else x for x in got])))
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(f"Gamma={g} median={med * 1000:.1f} CPU ms/pair")
            if med > budget or g >= ceiling:
                break
            if g >= 100_000 and _flat(_envelope(curve)):
                break  # flat: the estimator terminates early whatever the cap
            # aim 1.3 x past the budget assuming time ~ cap: by 3x..10x per step far below the budget; within 3x of
            # it by what the aim asks (at least 1.2x), so the cap past the budget costs ~1.3 B per pair, not 3 B
            # (8k SIFT, DEGENSAC: 473 ms at 183k led to a 550k cap timed at 1.37 s per pair, 34 s of calibration)
            grow = 1.3 * budget / max(med, 1e-6)
            g = int(min(ceiling, g * min(max(grow, 3.0 if med < budget / 3 else 1.2), 10.0)))
    finally:
        if bar is not None:
            bar.close()
    return curve


def calibrate(estimator_name: str, base_conf, scenes, cache, data_fingerprint: str, *,
              budgets: tuple[float, ...] = (0.5,), ratio: float = 0.9, threshold: float = 0.5,
              max_pairs: int = 8, studies_dir: Path | str | None = None, force: bool = False,
              progress: bool = False, seed: int = 0, jobs: int = 1) -> Calibration:
    """Gamma_max calibration for ``estimator_name`` (reused from ``budgets.json`` unless ``force``).

    scenes: [(Scene, [Pair, ...]), ...] validation scenes and their selected pairs; base_conf: the
    study's PipelineConfig (feature and matching settings); ratio / threshold: the matches and eta
    timed. The curve is measured up to the largest of ``budgets``; ``jobs``: estimator processes timed at once
    (the study's ``--jobs``)."""
    from pipeline.geometry import ESTIMATORS
    cls = ESTIMATORS.get(estimator_name)
    conf = dataclasses.replace(base_conf, matching=dataclasses.replace(base_conf.matching, ratio=float(ratio)))
    key = calibration_key(estimator_name, conf.feature, ratio, threshold, data_fingerprint, jobs=jobs,
                          matching=conf.matching)
    store = Path(studies_dir) / BUDGETS_FILE if studies_dir is not None else None
    bmax = max(budgets)

    def usable(c: Calibration | None) -> bool:  # a wall-clock calibration (stored before CPU time) is measured again
        return c is not None and c.clock == CLOCK and c.covers(bmax)

    if store is not None:
        _read_store(store)  # a damaged store is one line before the measuring, not after it
    if store is not None and not force:
        c = stored_calibration(store.parent, key)
        if usable(c):
            return c
    lock = _locked(store) if store is not None else _nullctx()
    with lock:
        if store is not None and not force:
            c = stored_calibration(store.parent, key)  # another worker may have measured meanwhile
            if usable(c):
                return c
        t0 = time.perf_counter()
        wall: list = []
        if not getattr(cls, "uses_iterations", True):
            curve = [(1, 0.0, 0.0)]
        else:
            matches = calibration_matches(scenes, conf, cache, max_pairs=max_pairs, progress=progress)
            curve = measure_curve(estimator_name, matches, threshold, conf.geometry.confidence, bmax,
                                  seed=seed, progress=progress, jobs=jobs, wall_curve=wall)
        cal = Calibration(estimator=estimator_name, feature=dataclasses.asdict(conf.feature), ratio=float(ratio),
                          threshold=float(threshold), pairs=int(min(max_pairs, sum(len(p) for _, p in scenes))),
                          curve=[list(c) for c in curve], host=socket.gethostname(),
                          created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                          data_fingerprint=data_fingerprint, seconds=time.perf_counter() - t0, jobs=int(jobs),
                          clock=CLOCK, wall_curve=[list(c) for c in wall])
        if store is not None:
            data = _read_store(store)
            data[key] = cal.to_dict()
            _write_store(store, data)
    return cal


@contextmanager
def _nullctx():
    yield
