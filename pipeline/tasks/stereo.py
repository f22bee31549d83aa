"""The stereo task: tentative matches -> robust F -> E = K2^T F K1 -> recoverPose on the inliers in
normalised coordinates -> pose error vs ground truth (see ``pipeline.metrics.pose``). A calibrated estimator
(``model = "E"``, ``pipeline.geometry.essential``) is given K1, K2 and its own pose is used instead.

Every evaluated pair yields one record; a pair that cannot be solved (no keypoints, < 8 matches,
estimator failure, < 5 inliers) is a recorded failure with error +inf, never dropped.
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from pipeline.cache import H5Cache
from pipeline.config import PipelineConfig
from pipeline.data.resize import scaled_K
from pipeline.data.scene import Pair, Scene
from pipeline.errors import ImtuneError
from pipeline.metrics.auc import auc_intervals, auc_summary
from pipeline.metrics.pose import accuracy_curve, mean_average_accuracy, pose_error_deg
from pipeline.metrics.uncertainty import maa_intervals
from pipeline.tasks.base import TASKS, Task, TaskResult
from pipeline.tasks.prepare import ImageFeatures, image_features, pair_knn, tentative_matches

MIN_MATCHES = 8
CI_RESAMPLES = 2000  # default bootstrap resamples of the mAA intervals (pipeline.metrics.uncertainty)
CI_SEED = 0  # the intervals are seeded: the same records always give the same interval
CI_KEYS = ("mAA5_ci", "mAA10_ci", "auc5_ci", "auc10_ci", "auc20_ci")
AUC_KEYS = ("auc5", "auc10", "auc20")  # pose AUC (pipeline.metrics.auc), beside mAA


def add_intervals(summary: dict, per_scene: dict, ci: dict, n_resamples: int) -> None:
    """Copy the ``mAA<tau>_ci`` intervals of ``ci`` (``maa_intervals`` / ``bag_intervals``) into a task's final
    summary and per-scene summaries, and record how they were made (``ci``: method, resamples, level)."""
    for k in CI_KEYS:
        if k in ci:
            summary[k] = ci[k]
        for name, s in per_scene.items():
            if k in (ci.get("scenes") or {}).get(name, {}):
                s[k] = ci["scenes"][name][k]
    summary["ci"] = {"level": 0.95, "resamples": int(n_resamples), "seed": CI_SEED,
                     "method": "percentile bootstrap, resampling units within each scene"}


def pose_from_F(F: np.ndarray, K1: np.ndarray, K2: np.ndarray, pts1: np.ndarray, pts2: np.ndarray):
    """Relative pose (R, t) of camera 2 w.r.t. camera 1 from F and the inlier points (px).

    E = K2^T F K1; cv2.recoverPose on the points normalised by K^-1 (cheirality picks one of the four
    decompositions). Returns (None, None) when fewer than 5 points or the decomposition fails."""
    if F is None or len(pts1) < 5:
        return None, None
    E = K2.T @ F @ K1
    p1 = cv2.undistortPoints(pts1.reshape(-1, 1, 2).astype(np.float64), K1, None).reshape(-1, 2)
    p2 = cv2.undistortPoints(pts2.reshape(-1, 1, 2).astype(np.float64), K2, None).reshape(-1, 2)
    try:
        _, R, t, _ = cv2.recoverPose(E, p1, p2, np.eye(3))
    except cv2.error:
        return None, None
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None, None
    return R, t.reshape(3)


@dataclass
class PairResult:
    """One stereo pair through the task's stages: what figures draw and what the record summarises.

    matches: (M, 2) int32 tentative matches [index in image i, index in image j]; pts1, pts2: (M, 2) float64 px
    at the working resolution; inliers: (M,) bool (all False when the estimator failed); F: the estimated
    fundamental matrix or None; R, t: the recovered relative pose (None on failure); K1, K2: intrinsics at the
    working resolution (None when unknown); sizes: ((w1, h1), (w2, h2)) working px; record: the JSON-able
    record (NM, NI, err, err_R, err_t in degrees, seconds, failure). ``ransac_seconds`` is the estimator's CPU time
    (the budgeted figure), ``ransac_wall_seconds`` its wall time; a record without the latter was written before
    the budget became CPU time, and its ``ransac_seconds`` is wall time."""
    record: dict
    matches: np.ndarray
    pts1: np.ndarray
    pts2: np.ndarray
    inliers: np.ndarray
    F: np.ndarray | None = None
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    K1: np.ndarray | None = None
    K2: np.ndarray | None = None
    sizes: tuple = ()


def has_ground_truth(scene: Scene, pair: Pair) -> bool:
    """True when the pair has intrinsics (3x3) for both images and a ground-truth relative pose."""
    try:
        Ki, Kj = scene.intrinsics(pair)
        if np.shape(Ki) != (3, 3) or np.shape(Kj) != (3, 3) or not (np.isfinite(Ki).all() and np.isfinite(Kj).all()):
            return False
        R, t = scene.relative_pose(pair)
        return bool(np.isfinite(R).all() and np.isfinite(t).all())
    except (ValueError, KeyError, TypeError, AttributeError):
        return False


def working_intrinsics(scene: Scene, pair: Pair, fi: ImageFeatures, fj: ImageFeatures):
    """Both images' intrinsics at the working resolution, or (None, None) when the scene has none (an E
    estimator then refuses the pair with a one-line error)."""
    try:
        Ki, Kj = scene.intrinsics(pair)
    except (ValueError, KeyError, TypeError, AttributeError):
        return None, None
    if np.shape(Ki) != (3, 3) or np.shape(Kj) != (3, 3) or not (np.isfinite(Ki).all() and np.isfinite(Kj).all()):
        return None, None
    return scaled_K(Ki, fi.sx, fi.sy), scaled_K(Kj, fj.sx, fj.sy)


def evaluate_pair(scene: Scene, pair: Pair, fi: ImageFeatures, fj: ImageFeatures, tables, knn_seconds: float,
                  conf: PipelineConfig, estimator) -> PairResult:
    """One stereo pair: tentative matches (:func:`pipeline.tasks.prepare.tentative_matches`) -> estimator
    -> pose -> errors (deg) against the ground truth. A pair without ground truth (no K or pose) still runs the
    estimator; its errors are NaN and ``record["no_ground_truth"]`` is True (figures draw such pairs)."""
    g = conf.geometry
    t0 = time.perf_counter()
    matches, _ = tentative_matches(tables, conf.matching, fi, fj)  # matcher (or custom matches), then pre-filter
    filter_seconds = time.perf_counter() - t0
    matches = np.asarray(matches, np.int32).reshape(-1, 2)
    rec = {"pair": pair.key, "scene": scene.name, "NM": int(len(matches)), "NI": 0,
           "err": math.inf, "err_R": math.inf, "err_t": math.inf,
           "match_seconds": knn_seconds + filter_seconds, "filter_seconds": filter_seconds,
           "ransac_seconds": 0.0, "ransac_wall_seconds": 0.0, "covisibility": pair.covisibility, "failure": None}
    pts1 = fi.keypoints[matches[:, 0]].astype(np.float64).reshape(-1, 2)
    pts2 = fj.keypoints[matches[:, 1]].astype(np.float64).reshape(-1, 2)
    sizes = ((fi.width, fi.height), (fj.width, fj.height))
    out = PairResult(record=rec, matches=matches, pts1=pts1, pts2=pts2, inliers=np.zeros(len(matches), bool),
                     sizes=sizes)
    gt = has_ground_truth(scene, pair)
    if gt:
        Ki, Kj = scene.intrinsics(pair)
        out.K1, out.K2 = scaled_K(Ki, fi.sx, fi.sy), scaled_K(Kj, fj.sx, fj.sy)
    else:
        rec.update(err=math.nan, err_R=math.nan, err_t=math.nan, no_ground_truth=True)
    if len(fi.keypoints) == 0 or len(fj.keypoints) == 0:
        rec["failure"] = "no keypoints in " + (pair.i if len(fi.keypoints) == 0 else pair.j)
        return out
    if len(matches) < MIN_MATCHES:
        rec["failure"] = f"fewer than {MIN_MATCHES} matches ({len(matches)})"
        return out
    calibrated = getattr(estimator, "model", "F") == "E"
    if calibrated:  # an E estimator takes both cameras' intrinsics and returns the pose itself
        K1, K2 = out.K1, out.K2
        if K1 is None or K2 is None:
            K1, K2 = working_intrinsics(scene, pair, fi, fj)
        res = estimator.estimate(pts1, pts2, g.threshold, g.confidence, g.max_iters, seed=g.seed, sizes=sizes,
                                 K1=K1, K2=K2)
    else:
        res = estimator.estimate(pts1, pts2, g.threshold, g.confidence, g.max_iters, seed=g.seed, sizes=sizes)
    rec["ransac_seconds"] = float(res.seconds)  # CPU time: what the budget bounds
    rec["ransac_wall_seconds"] = float(res.wall_seconds)
    if res.F is None:
        rec["failure"] = "estimator found no model"
        return out
    inl = np.asarray(res.inliers, bool).reshape(-1)
    out.F, out.inliers = res.F, inl
    rec["NI"] = int(inl.sum())
    if not gt or out.K1 is None or out.K2 is None:  # K1, K2: set above with the ground truth
        return out
    if calibrated:
        R, t = getattr(res, "R", None), getattr(res, "t", None)
    else:  # the paper's protocol: F, E = K2^T F K1, recoverPose on the inliers
        R, t = pose_from_F(res.F, out.K1, out.K2, pts1[inl], pts2[inl])
    if R is None:
        rec["failure"] = f"pose recovery failed ({rec['NI']} inliers)"
        return out
    out.R, out.t = R, t
    R_gt, t_gt = scene.relative_pose(pair)
    rec["err"], rec["err_R"], rec["err_t"] = pose_error_deg(R_gt, t_gt, R, t)
    return out


def failed_pair(scene: Scene, pair: Pair, why: str) -> dict:
    """The record of a pair that could not be evaluated at all (its worker process died): error +inf, counted."""
    return {"pair": pair.key, "scene": scene.name, "NM": 0, "NI": 0, "err": math.inf, "err_R": math.inf,
            "err_t": math.inf, "match_seconds": 0.0, "filter_seconds": 0.0, "ransac_seconds": 0.0,
            "ransac_wall_seconds": 0.0, "covisibility": pair.covisibility, "failure": why}


def summarize(records: list[dict], nf: float) -> dict:
    """Per-scene (or any group of records) summary: mAA(5), mAA(10), accuracy at 1..10 deg, NF, NM, NI,
    pair count, failures, seconds per pair (matching, wall; estimator CPU time mean, median and 90th percentile;
    ``ransac_wall_seconds_median``: the estimator's median wall time)."""
    errs = [r["err"] for r in records]
    rs = np.array([r["ransac_seconds"] for r in records]) if records else np.zeros(0)
    ms = np.array([r["match_seconds"] for r in records]) if records else np.zeros(0)

    def stat(f, a):
        return float(f(a)) if len(a) else 0.0
    out = {"mAA5": mean_average_accuracy(errs, 5), "mAA10": mean_average_accuracy(errs, 10),
           **auc_summary(errs), "accuracy": [float(x) for x in accuracy_curve(errs, 10)],
           "NF": float(nf), "NM": stat(np.mean, [r["NM"] for r in records]),
           "NI": stat(np.mean, [r["NI"] for r in records]), "pairs": len(records),
           "failed": int(sum(1 for r in records if not math.isfinite(r["err"]))),
           "match_seconds": stat(np.mean, ms), "ransac_seconds": stat(np.mean, rs),
           "ransac_seconds_median": stat(np.median, rs),
           "ransac_seconds_p90": stat(lambda a: np.percentile(a, 90), rs),
           "ransac_wall_seconds_median": stat(np.median, [r.get("ransac_wall_seconds", 0.0) for r in records])}
    if any(r.get("covisibility") is not None for r in records):  # the paper's breakdown (0+, 0.1+, ..., 0.6+)
        from pipeline.metrics.breakdown import by_covisibility
        out["covisibility"] = by_covisibility(records)
    return out


def combine(scene_summaries: dict[str, dict], records: list[dict]) -> dict:
    """Overall = mean over scenes of each per-scene figure (the benchmark averages scenes); pairs summed."""
    if not scene_summaries:
        return summarize([], 0.0)
    keys = ["mAA5", "mAA10", *AUC_KEYS, "NF", "NM", "NI", "match_seconds", "ransac_seconds"]
    out: dict[str, Any] = {k: float(np.mean([s[k] for s in scene_summaries.values()])) for k in keys}
    out["accuracy"] = [float(x) for x in np.mean([s["accuracy"] for s in scene_summaries.values()], axis=0)]
    out["pairs"] = int(sum(s["pairs"] for s in scene_summaries.values()))
    out["failed"] = int(sum(s["failed"] for s in scene_summaries.values()))
    rs = np.array([r["ransac_seconds"] for r in records]) if records else np.zeros(1)
    out["ransac_seconds_median"] = float(np.median(rs))
    out["ransac_seconds_p90"] = float(np.percentile(rs, 90))
    out["ransac_wall_seconds_median"] = float(np.median([r.get("ransac_wall_seconds", 0.0) for r in records] or [0.0]))
    parts = [s["covisibility"] for s in scene_summaries.values() if "covisibility" in s]
    if parts:  # co-visibility breakdown: mean over scenes per bin
        from pipeline.metrics.breakdown import mean_breakdown
        out["covisibility"] = mean_breakdown(parts)
    return out


def prepare_scene(scene: Scene, conf: PipelineConfig, cache: H5Cache, pairs: list[Pair] | None = None,
                  progress: bool = False):
    """Features of every image used by the pairs, and k-NN tables of every pair (cached)."""
    from tqdm.auto import tqdm
    pairs = scene.select_pairs() if pairs is None else pairs
    names = sorted({p.i for p in pairs} | {p.j for p in pairs})
    feats = {}
    for n in tqdm(names, desc=f"{scene.name}: features", disable=not progress, leave=False):
        feats[n] = image_features(cache, scene.images[n], conf.feature)
    tables = {}
    for p in tqdm(pairs, desc=f"{scene.name}: matching", disable=not progress, leave=False):
        tables[p.key] = pair_knn(cache, feats[p.i], feats[p.j], conf.matching)
    return feats, tables


def subsample_pairs(pairs: list, max_pairs: int | None) -> list:
    """At most ``max_pairs`` pairs, evenly spread (deterministic); None / 0 = all."""
    if not max_pairs or len(pairs) <= max_pairs:
        return list(pairs)
    idx = np.unique(np.linspace(0, len(pairs) - 1, max_pairs).round().astype(int))
    return [pairs[i] for i in idx]


def stratified_steps(counts: list[int], step_pairs: int | None) -> list[list[tuple[int, int]]]:
    """Split the pairs of several scenes (``counts[s]`` pairs in scene s) into evaluation steps of about
    ``step_pairs`` pairs, each step holding the same share of every scene, and within a scene pairs spread
    over its whole list (a golden-ratio stride, deterministic), so that an early step is representative of
    the whole set (what a pruner needs). Returns steps of (scene index, pair index); None / 0 = one step."""
    total = sum(counts)
    if total == 0:
        return []
    n = 1 if not step_pairs else max(1, -(-total // int(step_pairs)))
    steps: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for si, c in enumerate(counts):
        order = sorted(range(c), key=lambda i: ((i * 0.6180339887498949) % 1.0, i))
        for k in range(n):
            lo, hi = (k * c) // n, ((k + 1) * c) // n
            steps[k].extend((si, i) for i in order[lo:hi])
    return [sorted(st) for st in steps if st]


@TASKS.register("stereo", "two-view pose from F (E = K2^T F K1, recoverPose) or from an E estimator given K1, K2; "
                "mAA over pose errors")
class StereoTask(Task):
    """The paper's stereo task over each scene's pairs with co-visibility >= ``min_covisibility`` (all listed
    pairs where it is unknown), at most ``max_pairs`` per scene (evenly spread; None = all).

    ``step_pairs``: pairs per ``on_step`` call (stratified over scenes, see :func:`stratified_steps`; None = one
    step). ``keep_pairs``: keep every :class:`PairResult` in ``TaskResult.pairs`` (figures). ``progress``: tqdm bars.
    Overall figures are the mean over scenes of the per-scene figures (the benchmark averages scenes).

    ``jobs``: worker processes evaluating the pairs (:mod:`pipeline.tasks.pool`; None: every CPU this process may
    use; 1: in this process). Each worker keeps the scenes' features and k-NN tables in memory for as long as the
    same data is evaluated (a whole study), measures the estimator's CPU seconds (and wall seconds) around the library
    call alone, and
    the records are the same, in the same order, for any ``jobs`` (each pair is evaluated alone with the
    estimator's seed; steps are reported in order with the pairs of the steps so far). A pair whose worker died
    is a recorded failure (``"worker process died"``)."""

    name = "stereo"
    uses = ("ratio", "strategy", "threshold", "max_iters", "min_confidence")
    summary_keys = ("mAA5", "mAA10", *AUC_KEYS, "NF", "NM", "NI", "match_seconds", "ransac_seconds", "ransac_seconds_median",
                    "ransac_seconds_p90", "failed", "pairs")
    std_keys = ("mAA5", "mAA10", "NI")
    columns = ("pairs", "NF", "NM", "NI", "mAA5", "mAA10", "auc10", "failed", "match_seconds", "ransac_seconds")
    records_key = "pair_records"
    timed = True
    search_seconds = 300.0  # the main job: 50 trials or 5 min of them, whichever comes first (docs/budgets.md)
    note = "pose from F (or E, calibrated estimators); mAA over 1..5 / 1..10 deg; auc10: pose AUC@10 deg (SuperGlue's trapezoid); seconds per pair"
    units_label = "stereo pairs"
    test_figures = ("NF: features per image; per estimator NI: inliers per pair and mAA(10°) [95% interval over pairs "
                    "and runs]")

    def __init__(self, min_covisibility: float | None = 0.1, max_pairs: int | None = None,
                 step_pairs: int | None = None, keep_pairs: bool = False, progress: bool = False,
                 ci_resamples: int = CI_RESAMPLES, jobs: int | None = None):
        from pipeline.tasks.pool import resolve_jobs
        # worker processes evaluating the pairs (None: every CPU this process may use); not in options(): the
        # records are the same for any number of jobs (each pair is evaluated alone, with the estimator's seed)
        self.jobs = resolve_jobs(jobs)
        self._data = None  # (data key, PairData): the scenes' features and k-NN tables, read once
        # seconds per pair (scene index, pair index) of the last evaluation (the pool's order)
        self._costs_key: str | None = None
        self._costs: dict[tuple[int, int], float] = {}
        self.min_covisibility = min_covisibility
        self.max_pairs = max_pairs
        self.step_pairs = step_pairs
        self.keep_pairs = keep_pairs
        self.progress = progress
        # bootstrap resamples of the final summary's mAA intervals (0 = none); not in options(): an interval
        # describes the numbers, it never changes them (a study resumed with another count stays the same study)
        self.ci_resamples = int(ci_resamples or 0)

    def options(self) -> dict:
        return {"min_covisibility": self.min_covisibility, "max_pairs": self.max_pairs}

    def evaluation_units(self, scene: Scene) -> list[Pair]:
        return subsample_pairs(scene.select_pairs(self.min_covisibility), self.max_pairs)

    #: a principal point farther than this fraction of the image's width / height from its centre is said
    OFF_CENTRE = 0.1

    def scene_notes(self, scene: Scene) -> list[str]:
        """Pairs an SfM ground truth left out (an image it did not register: no pose, no pair), with the count of
        pairs evaluated out of those listed (pairs with their own listed poses stay, at co-visibility 0); and images whose principal point lies far from their centre (more than
        OFF_CENTRE of their size): intrinsics for another image size (images resized, K not) that the formats
        stating no size cannot refuse."""
        return self._dropped_notes(scene) + self._off_centre_notes(scene)

    def _dropped_notes(self, scene: Scene) -> list[str]:
        b = scene.built or {}
        dropped = int(b.get("pairs_dropped") or 0)
        gone = list(b.get("unregistered") or [])
        on_own = int(b.get("pairs_unregistered") or 0)
        if not dropped and not on_own:
            return []
        listed = int(b.get("pairs_listed") or 0)
        kept = len(scene.pairs)
        selected = len(scene.select_pairs(self.min_covisibility))
        evaluated = len(self.evaluation_units(scene))
        if dropped:
            shown = ", ".join(gone[:10]) + (f" and {len(gone) - 10} more" if len(gone) > 10 else "")
            why = [f"{dropped} dropped because the SfM ground truth (tune data build-gt) did not register "
                   f"{len(gone)} image{'s' if len(gone) != 1 else ''}: {shown}"]
        else:  # pairs on their own listed poses: the co-visibility filter decides
            paired = {n for q in scene.pairs for n in (q.i, q.j)}
            held = [n for n in gone if n in paired]
            shown = ", ".join(held[:10]) + (f" and {len(held) - 10} more" if len(held) > 10 else "")
            why = [f"{on_own} hold{'s' if on_own == 1 else ''} {'an image' if len(held) == 1 else 'images'} the SfM "
                   f"ground truth (tune data build-gt) did not register ({shown}): co-visibility 0"]
        if kept > selected:
            why.append(f"{kept - selected} below co-visibility {self.min_covisibility:g}")
        if selected > evaluated:
            why.append(f"{selected - evaluated} left out by max_pairs {self.max_pairs}")
        return [f"scene {scene.name}: {evaluated} of {listed} listed pairs evaluated ({'; '.join(why)})"]

    def _off_centre_notes(self, scene: Scene) -> list[str]:
        off: dict[str, tuple] = {}  # image -> (size, cx, cy, distance), in the order found
        for p in self.evaluation_units(scene):
            for n, K in zip((p.i, p.j), scene.intrinsics(p)):
                size = scene.images[n].size
                if n in off or size is None or not np.all(np.isfinite(K)):
                    continue
                d = max(abs(K[0, 2] - (size[0] - 1) / 2) / size[0], abs(K[1, 2] - (size[1] - 1) / 2) / size[1])
                if d > self.OFF_CENTRE:
                    off[n] = (size, K[0, 2], K[1, 2], d)
        if not off:
            return []
        n, ((w, h), cx, cy, d) = next(iter(off.items()))
        more = f" (and {len(off) - 1} more image(s))" if len(off) > 1 else ""
        return [f"scene {scene.name}: image {n} ({w}x{h} px) has its principal point ({cx:.1f}, {cy:.1f}) "
                f"{100 * d:.0f}% of its size from its centre{more}: are its intrinsics for another image size "
                "(images resized, K not)? Such poses are wrong; check them"]

    def budget_seconds(self, summary: dict) -> float | None:
        return float(summary.get("ransac_seconds_median", 0.0))

    def figures(self, result: TaskResult) -> dict:
        s = result.summary
        keys = ("mAA5", "mAA10", *AUC_KEYS, "NF", "NM", "NI", "ransac_seconds_median", "ransac_seconds_p90", "match_seconds",
                "ransac_seconds", "ransac_wall_seconds_median", "failed", "pairs", "accuracy", "covisibility")
        out: dict[str, Any] = {k: s.get(k) for k in keys}
        out["scenes"] = {k: {kk: v.get(kk) for kk in ("mAA5", "mAA10", *AUC_KEYS, "NF", "NM", "NI", "pairs", "failed",
                                                     "match_seconds", "ransac_seconds", "ransac_seconds_median",
                                                     "accuracy", "covisibility")}
                         for k, v in result.scenes.items()}
        for part, src in [(out, s)] + [(out["scenes"][k], v) for k, v in result.scenes.items()]:
            part.update({k: v for k, v in src.items() if k in CI_KEYS})  # intervals, where computed
        return out

    def _checked_pairs(self, scenes: list[Scene]) -> list[list[Pair]]:
        out = []
        for scene in scenes:
            pairs = self.evaluation_units(scene)
            why = scene.missing_ground_truth(pairs)
            if why:
                raise ImtuneError(f"scene {scene.name} has no ground truth to evaluate against ({why}); "
                                  f"build it first: tune data build-gt --data {scene.root}")
            why = scene.zero_baseline(pairs)
            if why:
                raise ImtuneError(f"scene {scene.name}: {why}")
            out.append(pairs)
        return out

    def prepare(self, scenes: list[Scene], conf: PipelineConfig, cache, progress: bool = False) -> dict[str, float]:
        nf = {}
        for scene, pairs in zip(scenes, self._checked_pairs(scenes)):
            feats, _ = prepare_scene(scene, conf, cache, pairs, progress=progress)
            nf[scene.name] = float(np.mean([len(f.keypoints) for f in feats.values()])) if feats else 0.0
        return nf

    def evaluate(self, scenes: list[Scene], conf: PipelineConfig, cache: H5Cache | None = None,
                 on_step=None) -> TaskResult:
        """Every selected pair of every scene -> one record (a failure has error +inf and still counts);
        ``on_step(step, n_steps, summary_so_far)`` after each step of ``step_pairs`` pairs."""
        from tqdm.auto import tqdm

        from pipeline.geometry import get_estimator
        from pipeline.tasks.pool import WORKER_DIED, PairSpec, one_thread_here, pair_pool
        cache = cache if cache is not None else H5Cache()
        estimator = get_estimator(conf.geometry.ransac)
        t0 = time.perf_counter()
        all_pairs = self._checked_pairs(scenes)
        spec = PairSpec(scenes=list(scenes), pairs=all_pairs, conf=conf, cache_root=str(cache.root),
                        evaluate=evaluate_pair)
        data = self._pair_data(spec, cache)
        nf = data.nf
        t1 = time.perf_counter()
        steps = stratified_steps([len(p) for p in all_pairs], self.step_pairs)
        order = [sp for step in steps for sp in step]  # the serial order; a pool completes in any order
        step_of = {sp: k for k, step in enumerate(steps) for sp in step}
        left = [len(step) for step in steps]
        done: dict[tuple[int, int], dict] = {}
        kept = {}
        bar = tqdm(total=len(order), desc="stereo", disable=not self.progress, leave=False)
        # no more workers than pairs: each worker holds the scenes' features and k-NN tables (~250 MB at 8k SIFT on
        # fountain-P11), and a worker without a pair would only hold memory (--jobs 64 on 6 pairs started 64)
        jobs = min(self.jobs, len(order))
        pool = pair_pool(jobs, spec) if jobs > 1 else None
        if pool is not None:
            # submitted step by step, within a step the pairs that took longest in the previous evaluation of the
            # same data first: the workers finish a trial together (a trial's last pairs are its cheap ones)
            last = self._costs if self._costs_key == spec.key else {}
            sub = sorted(range(len(order)), key=lambda k: (step_of[order[k]], -last.get(order[k], 0.0), k))
            results = ((sub[j], r) for j, r in pool.imap([order[k] for k in sub], conf, keep=self.keep_pairs))
        else:
            results = ((k, self._inline_pair(data, scenes, all_pairs, order[k], conf, estimator))
                       for k in range(len(order)))
        next_step = 0
        # in-process (--jobs 1): one BLAS / OpenMP / OpenCV thread while the estimators run, as in a pool worker
        threads = one_thread_here() if pool is None else contextlib.nullcontext()
        with threads:
            try:
                for k, out in results:
                    si, pi = order[k]
                    scene, pair = scenes[si], all_pairs[si][pi]
                    if out is WORKER_DIED:
                        out = failed_pair(scene, pair, WORKER_DIED)
                    rec = out.record if isinstance(out, PairResult) else out
                    done[(si, pi)] = rec
                    if self.keep_pairs and isinstance(out, PairResult):
                        kept[(scene.name, pair.key)] = out
                    bar.update(1)
                    left[step_of[(si, pi)]] -= 1
                    # steps report in order, each with exactly the records of the steps so far (what a serial run
                    # reports, whatever a pool finished early): the pruner sees the same values for any jobs
                    while next_step < len(steps) and left[next_step] == 0:
                        if on_step is not None:
                            so_far = {sp: r for sp, r in done.items() if step_of[sp] <= next_step}
                            summary = self._summaries(scenes, so_far, nf)[0]
                            summary["units_total"] = len(order)  # what a budget rule may prove from the pairs so far
                            summary["budget_seconds_units"] = [r["ransac_seconds"] for r in so_far.values()]
                            on_step(next_step, len(steps), summary)
                        next_step += 1
            except KeyboardInterrupt:
                if pool is not None:
                    pool.terminate()  # Ctrl-C: the workers stop now, not after their pairs
                raise
            finally:
                if hasattr(results, "close"):
                    results.close()  # a pruned trial: what has not started is cancelled
                bar.close()
        self._costs_key = spec.key
        self._costs = {sp: float(r.get("ransac_seconds", 0.0)) + float(r.get("filter_seconds", 0.0))
                       for sp, r in done.items()}
        summary, per_scene, records = self._summaries(scenes, done, nf)
        if self.ci_resamples:  # the final summary only: never on a pruner's step
            names = [sc.name for sc in scenes]
            ci = maa_intervals(records, n_resamples=self.ci_resamples, seed=CI_SEED, scenes=names)
            auc = auc_intervals(records, n_resamples=self.ci_resamples, seed=CI_SEED, scenes=names)
            ci.update({k: v for k, v in auc.items() if k != "scenes"})
            for n, part in auc["scenes"].items():
                ci["scenes"].setdefault(n, {}).update(part)
            add_intervals(summary, per_scene, ci, self.ci_resamples)
        return TaskResult(summary=summary, scenes=per_scene, records=records, pairs=kept,
                          seconds={"prepare": t1 - t0, "pairs": time.perf_counter() - t1},
                          records_key=self.records_key)

    def _pair_data(self, spec, cache):
        """The scenes' features and k-NN tables, read from the cache once per data (every trial of a study
        reuses them; :func:`pipeline.tasks.pool.pair_data_key`)."""
        from pipeline.tasks.pool import load_pair_data
        if self._data is None or self._data[0] != spec.key:
            self._data = (spec.key, load_pair_data(spec, cache, progress=self.progress))
        return self._data[1]

    @staticmethod
    def _inline_pair(data, scenes, all_pairs, sp, conf, estimator) -> PairResult:
        si, pi = sp
        scene, pair = scenes[si], all_pairs[si][pi]
        tab, knn_s = data.tables[si][pair.key]
        feats = data.feats[si]
        return evaluate_pair(scene, pair, feats[pair.i], feats[pair.j], tab, knn_s, conf, estimator)

    @staticmethod
    def _summaries(scenes, done: dict, nf: dict):
        """(overall, per scene, records in scene / pair order) of the records evaluated so far."""
        records = [done[k] for k in sorted(done)]
        by_scene: dict[str, list] = {}
        for (si, _), rec in sorted(done.items()):
            by_scene.setdefault(scenes[si].name, []).append(rec)
        per_scene = {name: summarize(recs, nf.get(name, 0.0)) for name, recs in by_scene.items()}
        return combine(per_scene, records), per_scene, records


def evaluate_stereo(scenes: list[Scene], conf: PipelineConfig, cache: H5Cache | None = None,
                    min_covisibility: float | None = 0.1, progress: bool = False, keep_pairs: bool = False) -> TaskResult:
    """``StereoTask(min_covisibility, ...).evaluate(scenes, conf, cache)``: one configuration, every scene."""
    return StereoTask(min_covisibility=min_covisibility, keep_pairs=keep_pairs, progress=progress).evaluate(
        scenes, conf, cache)
