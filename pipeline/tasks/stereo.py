"""The stereo task: tentative matches -> robust F -> E = K2^T F K1 -> recoverPose on the inliers in
normalised coordinates -> pose error vs ground truth (see ``pipeline.metrics.pose``).

Every evaluated pair yields one record; a pair that cannot be solved (no keypoints, < 8 matches,
estimator failure, < 5 inliers) is a recorded failure with error +inf, never dropped.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from pipeline.cache import H5Cache
from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError
from pipeline.data.resize import scaled_K
from pipeline.data.scene import Pair, Scene
from pipeline.metrics.pose import accuracy_curve, mean_average_accuracy, pose_error_deg
from pipeline.tasks.prepare import ImageFeatures, image_features, pair_knn

MIN_MATCHES = 8


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


def evaluate_pair(scene: Scene, pair: Pair, fi: ImageFeatures, fj: ImageFeatures, tables, knn_seconds: float,
                  conf: PipelineConfig, estimator) -> dict:
    """One stereo record: NM, NI, errors (deg), seconds for matching and for the estimator, failure reason."""
    from pipeline.tasks.prepare import pair_matches
    g = conf.geometry
    t0 = time.perf_counter()
    matches, _ = pair_matches(tables, conf.matching, fi, fj)  # matcher (or custom matches), then pre-filter
    filter_seconds = time.perf_counter() - t0
    rec = {"pair": pair.key, "scene": scene.name, "NM": int(len(matches)), "NI": 0,
           "err": math.inf, "err_R": math.inf, "err_t": math.inf,
           "match_seconds": knn_seconds + filter_seconds, "filter_seconds": filter_seconds,
           "ransac_seconds": 0.0, "covisibility": pair.covisibility, "failure": None}
    if len(fi.keypoints) == 0 or len(fj.keypoints) == 0:
        rec["failure"] = "no keypoints in " + (pair.i if len(fi.keypoints) == 0 else pair.j)
        return rec
    if len(matches) < MIN_MATCHES:
        rec["failure"] = f"fewer than {MIN_MATCHES} matches ({len(matches)})"
        return rec
    pts1 = fi.keypoints[matches[:, 0]].astype(np.float64)
    pts2 = fj.keypoints[matches[:, 1]].astype(np.float64)
    res = estimator.estimate(pts1, pts2, g.threshold, g.confidence, g.max_iters, seed=g.seed,
                             sizes=((fi.width, fi.height), (fj.width, fj.height)))
    rec["ransac_seconds"] = float(res.seconds)
    inl = np.asarray(res.inliers, bool).reshape(-1)
    rec["NI"] = int(inl.sum()) if res.F is not None else 0
    if res.F is None:
        rec["failure"] = "estimator found no model"
        return rec
    Ki, Kj = scene.intrinsics(pair)
    Ki = scaled_K(Ki, fi.sx, fi.sy)
    Kj = scaled_K(Kj, fj.sx, fj.sy)
    R, t = pose_from_F(res.F, Ki, Kj, pts1[inl], pts2[inl])
    if R is None:
        rec["failure"] = f"pose recovery failed ({rec['NI']} inliers)"
        return rec
    R_gt, t_gt = scene.relative_pose(pair)
    rec["err"], rec["err_R"], rec["err_t"] = pose_error_deg(R_gt, t_gt, R, t)
    return rec


def summarize(records: list[dict], nf: float) -> dict:
    """Per-scene (or any group of records) summary: mAA(5), mAA(10), accuracy at 1..10 deg, NF, NM, NI,
    pair count, failures, seconds per pair (matching; estimator mean, median and 90th percentile)."""
    errs = [r["err"] for r in records]
    rs = np.array([r["ransac_seconds"] for r in records]) if records else np.zeros(0)
    ms = np.array([r["match_seconds"] for r in records]) if records else np.zeros(0)

    def stat(f, a):
        return float(f(a)) if len(a) else 0.0
    out = {"mAA5": mean_average_accuracy(errs, 5), "mAA10": mean_average_accuracy(errs, 10),
           "accuracy": [float(x) for x in accuracy_curve(errs, 10)],
           "NF": float(nf), "NM": stat(np.mean, [r["NM"] for r in records]),
           "NI": stat(np.mean, [r["NI"] for r in records]), "pairs": len(records),
           "failed": int(sum(1 for r in records if not math.isfinite(r["err"]))),
           "match_seconds": stat(np.mean, ms), "ransac_seconds": stat(np.mean, rs),
           "ransac_seconds_median": stat(np.median, rs),
           "ransac_seconds_p90": stat(lambda a: np.percentile(a, 90), rs)}
    if any(r.get("covisibility") is not None for r in records):  # the paper's breakdown (0+, 0.1+, ..., 0.6+)
        from pipeline.metrics.breakdown import by_covisibility
        out["covisibility"] = by_covisibility(records)
    return out


@dataclass
class StereoResult:
    """Overall metrics (scene means), per-scene summaries and every pair record."""
    summary: dict
    scenes: dict[str, dict]
    records: list[dict] = field(default_factory=list)

    def to_dict(self, with_pairs: bool = False) -> dict:
        d = dict(self.summary)
        d["scenes"] = self.scenes
        if with_pairs:
            d["pair_records"] = self.records
        return d


def combine(scene_summaries: dict[str, dict], records: list[dict]) -> dict:
    """Overall = mean over scenes of each per-scene figure (the benchmark averages scenes); pairs summed."""
    if not scene_summaries:
        return summarize([], 0.0)
    keys = ["mAA5", "mAA10", "NF", "NM", "NI", "match_seconds", "ransac_seconds"]
    out = {k: float(np.mean([s[k] for s in scene_summaries.values()])) for k in keys}
    out["accuracy"] = [float(x) for x in np.mean([s["accuracy"] for s in scene_summaries.values()], axis=0)]
    out["pairs"] = int(sum(s["pairs"] for s in scene_summaries.values()))
    out["failed"] = int(sum(s["failed"] for s in scene_summaries.values()))
    rs = np.array([r["ransac_seconds"] for r in records]) if records else np.zeros(1)
    out["ransac_seconds_median"] = float(np.median(rs))
    out["ransac_seconds_p90"] = float(np.percentile(rs, 90))
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


def evaluate_stereo(scenes: list[Scene], conf: PipelineConfig, cache: H5Cache | None = None,
                    min_covisibility: float | None = 0.1, progress: bool = False,
                    on_scene=None) -> StereoResult:
    """Evaluate one fixed configuration on the stereo task over several scenes.

    on_scene(index, scene_name, summary_so_far) is called after each scene (the tuner reports
    intermediate values to a pruner through it; it may raise to stop early)."""
    from tqdm.auto import tqdm

    from pipeline.geometry import get_estimator
    cache = cache if cache is not None else H5Cache()
    estimator = get_estimator(conf.geometry.ransac)
    summaries, all_records = {}, []
    for idx, scene in enumerate(scenes):
        pairs = scene.select_pairs(min_covisibility)
        why = scene.missing_ground_truth(pairs)
        if why:
            raise ImtuneError(f"scene {scene.name} has no ground truth to evaluate against ({why}); "
                              f"build it first: tune data build-gt --data {scene.root}")
        feats, tables = prepare_scene(scene, conf, cache, pairs, progress=progress)
        recs = []
        for p in tqdm(pairs, desc=f"{scene.name}: stereo", disable=not progress, leave=False):
            tab, knn_s = tables[p.key]
            recs.append(evaluate_pair(scene, p, feats[p.i], feats[p.j], tab, knn_s, conf, estimator))
        nf = float(np.mean([len(f.keypoints) for f in feats.values()])) if feats else 0.0
        summaries[scene.name] = summarize(recs, nf)
        all_records.extend(recs)
        if on_scene is not None:
            on_scene(idx, scene.name, combine(summaries, all_records))
    return StereoResult(summary=combine(summaries, all_records), scenes=summaries, records=all_records)
