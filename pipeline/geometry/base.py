"""Robust estimator interface: matched points, inlier threshold (px), confidence, max iterations ->
fundamental matrix, inlier mask, seconds spent.

Every backend subclasses :class:`Estimator` and implements only ``_solve`` (the library call). The
shared ``estimate`` wrapper does what must be identical across backends, so that estimators are
compared on equal terms:

- input validation: fewer than ``min_matches`` (8) correspondences, non-finite coordinates, mismatched
  shapes, fewer than 8 distinct correspondences or an image whose points are all identical ->
  ``F=None`` and an all-False mask, without calling the library (``seconds`` is then 0);
- image sizes: ``sizes=((w1, h1), (w2, h2))`` in px, or derived from the point extents;
- output normalisation: F as (3, 3) float64 with ``x2^T F x1 = 0`` (x1 in image 1, x2 in image 2,
  homogeneous pixel coordinates) and Frobenius norm 1; a stacked (3k, 3) output (several 7-point
  solutions) is reduced to the solution with most inliers; a non-finite or zero F, a library
  exception, or a model with fewer than 8 inliers is a failure (``F=None``, all-False mask);
- timing: ``seconds`` is CPU time (``time.process_time``: every thread of the process, so the threads a
  library starts count too) around the library call only (no validation, no array packing, no
  post-processing); it is what the time budget B bounds, and it does not grow when other processes
  share the cores. ``wall_seconds`` is ``time.perf_counter`` around the same call, recorded beside it.
  In the main process (``--jobs 1``) other threads of ours (tqdm's monitor, Optuna's heartbeat) also
  count, but they sleep almost all the time; the calling thread's CPU alone (``time.thread_time``) would
  miss the library's own threads (OpenCV, COLMAP), which is worse.
"""
from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from pipeline.config import MAX_ITERS

Sizes = tuple[tuple[float, float], tuple[float, float]]
"""((w1, h1), (w2, h2)): image widths and heights in px at the working resolution."""


@dataclass
class EstimateResult:
    """F: (3, 3) float64 fundamental matrix with x2^T F x1 = 0 and ||F||_F = 1, or None when the
    estimator failed; inliers: (M,) bool mask over the input matches (all False on failure);
    seconds: CPU time (s, all threads of the process) of the library call alone, the budgeted figure;
    wall_seconds: wall time (s) of the same call."""
    F: np.ndarray | None
    inliers: np.ndarray
    seconds: float
    wall_seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.F is not None

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers)) if self.F is not None else 0


@dataclass
class RawSolution:
    """What a backend's ``_solve`` hands back: the library's F (any (3k, 3) stack, any convention
    already converted to x2^T F x1 = 0, or None), its inlier mask (None: recompute from F by
    Sampson distance <= threshold), and the CPU seconds of the library call (``timed``)."""
    F: np.ndarray | None
    mask: np.ndarray | None
    seconds: float


class _Timer:
    seconds: float = 0.0  # CPU time (process_time)
    wall_seconds: float = 0.0  # wall time (perf_counter)


_LAST = threading.local()  # the last timer a thread stopped: ``estimate`` reads its wall time from there


@contextmanager
def timed() -> Iterator[_Timer]:
    """``with timed() as t: lib_call()`` -> ``t.seconds`` (CPU time of the process, every thread: the budgeted
    figure) and ``t.wall_seconds``; the timer stops even if the call raises."""
    t = _Timer()
    _LAST.timer = t
    w0, c0 = time.perf_counter(), time.process_time()
    try:
        yield t
    finally:
        t.seconds = time.process_time() - c0
        t.wall_seconds = time.perf_counter() - w0


def sampson_distance(F: np.ndarray, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
    """First-order geometric (Sampson) distance in px of each correspondence to F (x2^T F x1 = 0),
    i.e. |x2^T F x1| / sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2). Shape (M,)."""
    F = np.asarray(F, dtype=np.float64)
    h1 = np.concatenate([pts1, np.ones((len(pts1), 1))], axis=1)
    h2 = np.concatenate([pts2, np.ones((len(pts2), 1))], axis=1)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.abs(np.sum(h2 * Fx1, axis=1))
    den = np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = num / den
    return np.where(np.isfinite(d), d, np.inf)


def packed_correspondences(pts1: np.ndarray, pts2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Matches as the (M, 4) [x1 y1 x2 y2] array pymagsac / pygcransac take, plus uniform per-match
    probabilities (M,) (their uniform sampler ignores them, but the argument is required)."""
    corr = np.ascontiguousarray(np.concatenate([pts1, pts2], axis=1))
    return corr, np.ones(len(corr), dtype=np.float64)


def sizes_from_points(pts1: np.ndarray, pts2: np.ndarray) -> Sizes:
    """Default image sizes when the caller gives none: the smallest image (integer px, at least 1)
    that holds every point, i.e. w = floor(max x) + 1, h = floor(max y) + 1."""
    def one(p: np.ndarray) -> tuple[float, float]:
        if len(p) == 0:
            return 1.0, 1.0
        m = np.max(p, axis=0)
        return float(max(np.floor(m[0]) + 1, 1)), float(max(np.floor(m[1]) + 1, 1))
    return one(pts1), one(pts2)


class Estimator(ABC):
    """Base of every robust estimator. Register with ``ESTIMATORS.register(name)``.

    ``estimate`` never raises on degenerate input: it returns F=None and an all-False mask.

    Class attributes describe what a backend does with the protocol's knobs, so the tuner can skip
    searching a parameter an estimator ignores:

    - ``uses_threshold``: the inlier threshold eta (px) is used (False for LMedS and the 8-point fit);
    - ``uses_iterations``: the iteration cap Gamma is used (False for the 8-point fit);
    - ``seedable``: results are reproducible for a fixed ``seed`` (False: the library draws its own
      randomness and exposes no seed, so repeated runs differ);
    - ``seed_used``: the seed reaches the library, so different seeds give different random runs
      (False for OpenCV, whose robust methods use a fixed internal seed: reproducible, but the
      protocol's repeated test runs are identical; and for the non-seedable backends);
    - ``threshold_kind``: what eta bounds ("sampson": Sampson distance; "epipolar-line": distance to
      the epipolar line in both images; "none");
    - ``model``: "F" (fundamental matrix, this interface) or "E" (calibrated essential matrix and pose,
      :class:`pipeline.geometry.essential.EssentialEstimator`, which also takes K1, K2);
    - ``package``: the pip package behind the backend (for ``check_available`` messages).
    """
    min_matches: int = 8
    model: str = "F"  # what it estimates: "F" (this interface) or "E" (pipeline.geometry.essential)
    uses_threshold: bool = True
    uses_iterations: bool = True
    seedable: bool = True
    seed_used: bool = True
    threshold_kind: str = "sampson"
    package: str = ""
    name: str = ""

    @classmethod
    def check_available(cls) -> None:
        """Raise ``UnavailableError`` when the backing package is not installed."""

    def _checked_points(self, pts1, pts2) -> tuple[np.ndarray | None, np.ndarray | None, int]:
        """(p1, p2, M): the matches as contiguous (M, 2) float64 arrays, or (None, None, M) when they are not two
        (M, 2) arrays of one length or are degenerate (``_degenerate``): the estimate is then a recorded failure."""
        try:
            p1 = np.asarray(pts1, dtype=np.float64)
            p2 = np.asarray(pts2, dtype=np.float64)
        except (TypeError, ValueError):
            return None, None, 0
        m = p1.shape[0] if p1.ndim >= 1 else 0
        if p1.ndim != 2 or p2.ndim != 2 or p1.shape != p2.shape or p1.shape[1] != 2:
            return None, None, m
        p1, p2 = np.ascontiguousarray(p1), np.ascontiguousarray(p2)
        if self._degenerate(p1, p2):
            return None, None, m
        return p1, p2, m

    def estimate(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
                 max_iters: int, seed: int = 0, *, sizes: Sizes | None = None) -> EstimateResult:
        """Estimate F from tentative matches.

        pts1, pts2: (M, 2) px at the working resolution, row k of each being one match.
        threshold: eta in px (see ``threshold_kind``). confidence: RANSAC confidence in (0, 1).
        max_iters: iteration cap Gamma. seed: random seed for backends that accept one (``seedable``).
        sizes: ((w1, h1), (w2, h2)) image sizes in px, used by backends that need them (MAGSAC,
        GC-RANSAC samplers and neighbourhood grids); default: derived from the point extents
        (``sizes_from_points``).
        Returns an :class:`EstimateResult`; never raises on degenerate input or library errors.
        """
        p1, p2, m = self._checked_points(pts1, pts2)
        if p1 is None or p2 is None:
            return self._failure(m)
        if sizes is None:
            sizes = sizes_from_points(p1, p2)
        try:
            max_iters = min(max(int(max_iters), 1), MAX_ITERS)
            _LAST.timer = None
            raw = self._solve(p1, p2, float(threshold), float(confidence), max_iters, int(seed), sizes)
        except Exception:  # noqa: BLE001 - a library error is a recorded failure, never a crash
            return self._failure(m)
        res = self._finish(raw, p1, p2, float(threshold))
        t = getattr(_LAST, "timer", None)  # the backend's ``timed()`` (None: it timed nothing)
        res.wall_seconds = float(t.wall_seconds) if t is not None else 0.0
        return res

    @abstractmethod
    def _solve(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
               max_iters: int, seed: int, sizes: Sizes) -> RawSolution:
        """The library call. pts are validated (M >= 8, finite, C-contiguous float64 (M, 2)).
        Time the call itself with ``with timed() as t:`` and return ``RawSolution(F, mask, t.seconds)``,
        F already converted to x2^T F x1 = 0. May raise: ``estimate`` turns that into a failure."""

    # -- shared helpers -------------------------------------------------------------------------
    def _failure(self, m: int, seconds: float = 0.0) -> EstimateResult:
        return EstimateResult(F=None, inliers=np.zeros(max(int(m), 0), dtype=bool), seconds=float(seconds))

    def _degenerate(self, p1: np.ndarray, p2: np.ndarray) -> bool:
        m = p1.shape[0]
        if m < self.min_matches:
            return True
        if not (np.all(np.isfinite(p1)) and np.all(np.isfinite(p2))):
            return True
        both = np.concatenate([p1[:64], p2[:64]], axis=1)  # cheap common case: a prefix suffices
        if len(np.unique(both, axis=0)) < self.min_matches and \
                len(np.unique(np.concatenate([p1, p2], axis=1), axis=0)) < self.min_matches:
            return True
        if np.all(np.ptp(p1, axis=0) == 0) or np.all(np.ptp(p2, axis=0) == 0):
            return True  # every point of one image identical: F is not determined
        return False

    def _finish(self, raw: RawSolution, p1: np.ndarray, p2: np.ndarray, threshold: float) -> EstimateResult:
        m = p1.shape[0]
        F = raw.F
        if F is None:
            return self._failure(m, raw.seconds)
        F = np.asarray(F, dtype=np.float64)
        if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] < 3 or F.shape[0] % 3 != 0:
            return self._failure(m, raw.seconds)
        mask = None if raw.mask is None else np.asarray(raw.mask).reshape(-1).astype(bool)
        if mask is not None and mask.shape[0] != m:
            mask = None
        if F.shape[0] > 3:  # stacked 7-point solutions: keep the one with most inliers
            cands = [F[i:i + 3] for i in range(0, F.shape[0], 3)]
            cands = [c for c in cands if np.all(np.isfinite(c)) and np.linalg.norm(c) > 0]
            if not cands:
                return self._failure(m, raw.seconds)
            counts = [int(np.count_nonzero(sampson_distance(c, p1, p2) <= threshold)) for c in cands]
            F = cands[int(np.argmax(counts))]
            mask = None  # the library mask belongs to no single solution
        n = np.linalg.norm(F)
        if not np.all(np.isfinite(F)) or not np.isfinite(n) or n <= 0:
            return self._failure(m, raw.seconds)
        F = F / n
        if mask is None:
            mask = sampson_distance(F, p1, p2) <= threshold
        if int(np.count_nonzero(mask)) < self.min_matches:
            return self._failure(m, raw.seconds)
        return EstimateResult(F=F, inliers=mask, seconds=float(raw.seconds))


def require(module: str, package: str) -> None:
    """Import ``module`` or raise a one-line ``UnavailableError`` naming the pip ``package``."""
    from pipeline.errors import UnavailableError
    try:
        if module == "pycolmap":  # its import takes SIGTERM over: the adapter gives it back
            from pipeline.colmap_db import import_pycolmap
            import_pycolmap()
        else:
            __import__(module)
    except Exception as e:  # ImportError, or a broken binary wheel (OSError, ...)
        raise UnavailableError(f"{module} is not importable ({type(e).__name__}); "
                               f"install it with `pip install {package}`") from None
