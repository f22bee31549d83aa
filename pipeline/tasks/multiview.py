"""The multiview task (IMC protocol): bags of images reconstructed with COLMAP from our tentative matches.

For every bag (``pipeline.data.bags``): the bag's keypoints (working resolution) and the project's
tentative matches (ratio test / strategy of ``MatchConfig`` on the cached k-NN tables) are written into
a fresh COLMAP database; COLMAP runs its own geometric verification (its RANSAC, default settings, as
the official benchmark's ``matches_importer --match_type raw``) and incremental mapping; the model with
the most registered images is evaluated. Per bag:

- NL: 3D points; TL: mean track length; RC: registered images / bag size (%);
- success: COLMAP returned a model (its ``min_model_size``, 3, discards small models when there are
  several); a bag where COLMAP finds no initial pair, raises, or whose worker process dies is a recorded
  failure (never a crash, never dropped);
- pose error of every pair of the bag = max(rotation error, translation-direction error) of the
  relative pose from the model vs ground truth (degrees); +inf when either image is unregistered;
- ATE: RMSE of camera centres after a Umeyama similarity alignment (>= 3 registered cameras).

Aggregation (the official benchmark's): per bag size, SR = % successful bags; RC and mAA over all bags
(failures contribute 0); NL and TL over successful bags; ATE over bags that have one. Then the mean
over bag sizes (per scene), then the mean over scenes.

Bags run in parallel worker processes (``workers``; spawn context; COLMAP and BLAS limited to one
thread each), so wall time scales with cores.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.cache import H5Cache, make_key
from pipeline.config import PipelineConfig
from pipeline.cpus import available_cpus
from pipeline.data.bags import DEFAULT_BAGS, MIN_BAG, MIN_POINTS, scene_bags
from pipeline.data.scene import Pair, Scene
from pipeline.errors import ImtuneError
from pipeline.metrics.pose import accuracy_curve, mean_average_accuracy, pose_error_deg
from pipeline.tasks.base import TASKS, Task, TaskResult
from pipeline.tasks.pool import (
    exit_with_parent,
    ignore_sigint_here,
    kill_executor,
    kill_processes,
    quiet_resource_tracker,
    sigint_held,
    single_thread_env,
)
from pipeline.tasks.stereo import CI_KEYS, CI_RESAMPLES, CI_SEED, add_intervals

BAG_STAGE_VERSION = "1"
MULTIVIEW_KEYS = ("SR", "RC", "NL", "TL", "mAA5", "mAA10", "ATE", "NM", "bags", "failed", "seconds")


@dataclass(frozen=True)
class MultiviewConfig:
    """Settings of the multiview task (the matching itself comes from ``PipelineConfig.matching``).

    bags: ((size, count), ...) — the protocol's ((5, 100), (10, 50), (25, 25)); sizes clipped to the scene.
    min_points: each image of a bag must see at least this many of the bag's 3D points.
    bag_seed: seed of the bag sampling (each bag size draws from its own generator, seeded by (bag_seed, size):
        ``pipeline.data.bags.sample_bags``).
    intrinsics: "colmap" (official: COLMAP estimates them, EXIF or 1.2 x long side), "prior" (known K as a
        refined prior) or "fixed" (known K, not refined). See ``pipeline.colmap_db``.
    pair_min_points: write matches only for bag pairs sharing at least this many ground-truth 3D points
        (the official benchmark's vis_th = 100); 0 = every pair of the bag. Ignored without 3D points.
    min_model_size: COLMAP's minimum model size (official: 3; a lone smaller model is still kept by COLMAP).
    verify_max_error: COLMAP geometric verification threshold (px; COLMAP default 4).
    verify_min_inliers: minimum inliers of a verified pair (COLMAP default 15).
    seed: COLMAP's random seed (RANSAC and mapper) — a run is reproducible; vary it across repeated runs.
    max_seconds_per_bag: COLMAP stops mapping a bag after this long (None = no limit).
    """
    bags: tuple = tuple(DEFAULT_BAGS.items())
    min_points: int = MIN_POINTS
    bag_seed: int = 0
    intrinsics: str = "colmap"
    pair_min_points: int = 100
    min_model_size: int = 3
    verify_max_error: float = 4.0
    verify_min_inliers: int = 15
    seed: int = 0
    max_seconds_per_bag: float | None = None

    def __post_init__(self):
        from pipeline.colmap_db import INTRINSICS_MODES
        if self.intrinsics not in INTRINSICS_MODES:
            raise ImtuneError(f"unknown intrinsics mode {self.intrinsics!r} (choose {', '.join(INTRINSICS_MODES)})")
        if self.min_model_size < 2:
            raise ImtuneError(f"min_model_size must be >= 2, got {self.min_model_size}")
        from pipeline.config import check_seed
        check_seed("multiview seed", self.seed)
        if self.verify_max_error <= 0:
            raise ImtuneError(f"verify_max_error must be > 0 px, got {self.verify_max_error}")
        try:
            object.__setattr__(self, "bags", tuple((int(s), int(c)) for s, c in dict(self.bags).items()))
        except (TypeError, ValueError):
            raise ImtuneError(f"bags must be (size, count) pairs, got {self.bags!r}") from None

    @property
    def bag_spec(self) -> dict[int, int]:
        return dict(self.bags)


# --------------------------------------------------------------------------------------------- jobs

@dataclass
class BagJob:
    """Everything one worker needs for one bag (plain arrays; pickled to the worker)."""
    scene: str
    size: int
    index: int
    names: tuple
    keypoints: dict          # name -> (n, 2) float32, working px
    image_sizes: dict        # name -> (w, h) working px
    K: dict                  # name -> 3x3 at working resolution (None when unknown)
    paths: dict              # name -> image path (EXIF focal for intrinsics="colmap")
    poses: dict              # name -> (R, t) ground truth, world-to-camera
    matches: dict            # (name_i, name_j) -> (M, 2) int
    conf: MultiviewConfig
    workdir: str
    keep: bool = False


def run_bag(job: BagJob) -> dict:
    """Reconstruct one bag and score it. Never raises: any failure is a record with ``failure`` set."""
    from pipeline import colmap_db as cdb
    t0, c0 = time.perf_counter(), time.process_time()
    names = list(job.names)
    rec = _empty_record(job)
    rec["started"] = time.time()
    bag_dir = Path(job.workdir) / f"{_safe(job.scene)}-{job.size}-{job.index:03d}"
    try:
        cdb.quiet(3)
        shutil.rmtree(bag_dir, ignore_errors=True)
        bag_dir.mkdir(parents=True)
        c = job.conf
        images = [(n, cdb.make_camera(job.image_sizes[n][0], job.image_sizes[n][1], job.K.get(n), c.intrinsics,
                                      job.paths.get(n)), job.keypoints[n]) for n in names]
        db = bag_dir / "database.db"
        cdb.write_database(db, images, job.matches)
        cdb.verify(db, cdb.verification_options(max_error=c.verify_max_error, min_num_inliers=c.verify_min_inliers,
                                                seed=c.seed))
        opts = cdb.mapper_options(min_model_size=c.min_model_size, num_threads=1, seed=c.seed,
                                  fixed_intrinsics=(c.intrinsics == "fixed"), max_runtime_seconds=c.max_seconds_per_bag)
        recs, failure = cdb.incremental_mapping(db, bag_dir / "sparse", opts)
        # COLMAP discards models below min_model_size only when it has several; a lone smaller model is kept
        # (and was evaluated by the official benchmark): the bag succeeded with that model
        model = cdb.largest_model(recs)
        if model is None:
            rec["failure"] = failure or "no model"
        else:
            _score(rec, model, job)
    except Exception as e:  # never let one bag stop the run
        msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
        rec["failure"] = f"{type(e).__name__}: {msg}"
    finally:
        if not job.keep:
            shutil.rmtree(bag_dir, ignore_errors=True)
    rec["seconds"] = time.perf_counter() - t0
    rec["cpu_seconds"] = time.process_time() - c0
    rec["pid"] = os.getpid()
    return rec


def _safe(s: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in s)


def _empty_record(job: BagJob) -> dict:
    names = list(job.names)
    pairs = [f"{a}|{b}" for k, a in enumerate(names) for b in names[k + 1:]]
    nm = [len(m) for m in job.matches.values()]
    return {"scene": job.scene, "bag_size": job.size, "bag": job.index, "images": names, "registered": [],
            "success": False, "failure": None, "NL": 0, "TL": 0.0, "RC": 0.0,
            "NM": float(np.mean(nm)) if nm else 0.0, "pairs": pairs, "errors": [math.inf] * len(pairs),
            "ATE": None, "reprojection_error": None, "seconds": 0.0}


def _score(rec: dict, model, job: BagJob) -> None:
    from pipeline import colmap_db as cdb
    from pipeline.metrics.ate import absolute_trajectory_error, camera_center
    names = list(job.names)
    poses = cdb.model_poses(model)
    st = cdb.model_stats(model)
    rec.update(success=True, NL=st["NL"], TL=st["TL"], reprojection_error=st["reprojection_error"],
               registered=[n for n in names if n in poses], RC=100.0 * sum(n in poses for n in names) / len(names))
    errs = []
    for k, a in enumerate(names):
        for b in names[k + 1:]:
            if a not in poses or b not in poses or a not in job.poses or b not in job.poses:
                errs.append(math.inf)
                continue
            Ra, ta = poses[a]
            Rb, tb = poses[b]
            R = Rb @ Ra.T
            t = tb - R @ ta
            Ga, ga = job.poses[a]
            Gb, gb = job.poses[b]
            R_gt = Gb @ Ga.T
            t_gt = gb - R_gt @ ga
            errs.append(pose_error_deg(R_gt, t_gt, R, t)[0])
    rec["errors"] = errs
    common = [n for n in names if n in poses and n in job.poses]
    res = absolute_trajectory_error([camera_center(*poses[n]) for n in common],
                                    [camera_center(*job.poses[n]) for n in common])
    rec["ATE"] = None if res is None else res.ate


# ------------------------------------------------------------------------------------------ running

def _init_worker(parent: int):
    ignore_sigint_here()  # the parent stops its workers on Ctrl-C: no traceback per worker
    exit_with_parent(parent)  # ... and a parent killed with kill -9 leaves no COLMAP worker behind
    from pipeline import colmap_db as cdb
    cdb.limit_threads(1)
    try:
        import cv2
        cv2.setNumThreads(1)
    except Exception:
        pass
    cdb.quiet(3)


def run_bags(jobs: list[BagJob], workers: int = 2, progress: bool = False, desc: str = "bags",
             fn=None) -> list[dict]:
    """Run bag jobs, in ``workers`` processes (spawn) or in this process when ``workers`` <= 1.

    Results come back in the order of ``jobs``. A worker that dies (COLMAP abort) breaks the pool: the
    bags in flight are retried one at a time in a fresh process, and a bag that kills its process again is
    recorded as failed. ``fn`` replaces :func:`run_bag` (a module-level function; tests)."""
    from tqdm.auto import tqdm
    fn = fn or run_bag
    results: list[dict | None] = [None] * len(jobs)
    bar = tqdm(total=len(jobs), desc=desc, disable=not progress, leave=False)
    if workers <= 1 or len(jobs) <= 1:
        _init_worker_inline()
        for k, j in enumerate(jobs):
            results[k] = fn(j)
            bar.update(1)
        bar.close()
        return results  # type: ignore[return-value]
    # longest bags first (largest size) so the two workers finish together
    order = sorted(range(len(jobs)), key=lambda k: -len(jobs[k].names))
    pending = list(order)
    suspects: list[int] = []
    while pending:
        pending, broken = _pool_pass(jobs, pending, results, workers, bar, fn)
        suspects.extend(broken)
    for k in suspects:  # isolate: one bag per fresh process
        if results[k] is None:
            _, again = _pool_pass(jobs, [k], results, 1, bar, fn)
            if again:
                rec = _empty_record(jobs[k])
                rec["failure"] = "COLMAP worker process died"
                results[k] = rec
                bar.update(1)
    bar.close()
    return results  # type: ignore[return-value]


def _init_worker_inline():
    from pipeline import colmap_db as cdb
    cdb.quiet(3)


def _pool_pass(jobs, indices, results, workers, bar, fn):
    """Submit ``indices`` to a fresh pool; returns (not yet submitted, in-flight when the pool broke)."""
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool
    ctx = mp.get_context("spawn")
    todo = list(indices)
    submitted: list[int] = []
    with quiet_resource_tracker():  # the executor's queue locks start the tracker (quiet after a Ctrl-C)
        ex = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                                 initargs=(os.getpid(),))
    procs = {}
    inflight = {}
    try:
        while todo or inflight:
            while todo and len(inflight) < 2 * workers:
                k = todo.pop(0)
                with single_thread_env(), sigint_held():  # a worker spawned here inherits both
                    inflight[ex.submit(fn, jobs[k])] = k
                procs.update(getattr(ex, "_processes", None) or {})
                submitted.append(k)
            done, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
            for f in done:
                k = inflight.pop(f)
                results[k] = f.result()
                bar.update(1)
    except BrokenProcessPool:
        # Python 3.11's executor then joins the surviving workers, which may sit idle on the call
        # queue forever (it is only fixed in 3.12, where broken pools kill their workers): kill them.
        kill_processes(list({**procs, **(getattr(ex, "_processes", None) or {})}.values()))
    except KeyboardInterrupt:  # Ctrl-C / SIGTERM: the workers stop now, not after the bags in flight and queued
        kill_executor(ex, list(procs.values()))
        raise
    ex.shutdown(wait=True)
    return todo, [k for k in submitted if results[k] is None]


# ------------------------------------------------------------------------------------------ summary

def summarize_bags(records: list[dict]) -> dict:
    """Figures of one group of bags (one bag size of one scene): SR, RC (%), NL, TL, mAA(5), mAA(10),
    accuracy at 1..10 deg, ATE, NM (tentative matches per pair written), bags, failed, seconds per bag (wall time)
    and cpu_seconds per bag (CPU time of the bag's process, COLMAP's threads included: what neighbours on the machine
    do not change)."""
    if not records:
        return {"SR": 0.0, "RC": 0.0, "NL": 0.0, "TL": 0.0, "mAA5": 0.0, "mAA10": 0.0, "accuracy": [0.0] * 10,
                "ATE": None, "NM": 0.0, "bags": 0, "failed": 0, "seconds": 0.0, "cpu_seconds": 0.0}
    ok = [r for r in records if r["success"]]
    curves = [accuracy_curve(r["errors"], 10) for r in records]
    ates = [r["ATE"] for r in records if r.get("ATE") is not None]
    return {"SR": 100.0 * len(ok) / len(records),
            "RC": float(np.mean([r["RC"] for r in records])),
            "NL": float(np.mean([r["NL"] for r in ok])) if ok else 0.0,
            "TL": float(np.mean([r["TL"] for r in ok])) if ok else 0.0,
            "mAA5": float(np.mean([mean_average_accuracy(r["errors"], 5) for r in records])),
            "mAA10": float(np.mean([mean_average_accuracy(r["errors"], 10) for r in records])),
            "accuracy": [float(x) for x in np.mean(curves, axis=0)],
            "ATE": float(np.mean(ates)) if ates else None,
            "NM": float(np.mean([r["NM"] for r in records])),
            "bags": len(records), "failed": len(records) - len(ok),
            "seconds": float(np.mean([r["seconds"] for r in records])),
            "cpu_seconds": float(np.mean([r.get("cpu_seconds", 0.0) for r in records]))}


def _mean_of(summaries: list[dict]) -> dict:
    """Mean of summaries (over bag sizes or scenes); ATE over those that have one; counts summed."""
    if not summaries:
        return summarize_bags([])
    out: dict[str, Any] = {}
    for k in ("SR", "RC", "NL", "TL", "mAA5", "mAA10", "NM", "seconds", "cpu_seconds"):
        out[k] = float(np.mean([s.get(k, 0.0) for s in summaries]))
    out["accuracy"] = [float(x) for x in np.mean([s["accuracy"] for s in summaries], axis=0)]
    ates = [s["ATE"] for s in summaries if s.get("ATE") is not None]
    out["ATE"] = float(np.mean(ates)) if ates else None
    out["bags"] = int(sum(s["bags"] for s in summaries))
    out["failed"] = int(sum(s["failed"] for s in summaries))
    return out


def summarize_scene(records: list[dict]) -> dict:
    """A scene's figures: per bag size ("by_size") and their mean over bag sizes (the top-level keys)."""
    sizes = sorted({r["bag_size"] for r in records})
    by_size = {str(s): summarize_bags([r for r in records if r["bag_size"] == s]) for s in sizes}
    out = _mean_of(list(by_size.values()))
    out["by_size"] = by_size
    return out


def combine(scene_summaries: dict[str, dict]) -> dict:
    """Overall figures: mean over scenes of the per-scene figures."""
    out = _mean_of(list(scene_summaries.values()))
    sizes = sorted({k for s in scene_summaries.values() for k in s.get("by_size", {})}, key=int)
    out["by_size"] = {k: _mean_of([s["by_size"][k] for s in scene_summaries.values() if k in s.get("by_size", {})])
                      for k in sizes}
    return out


# ------------------------------------------------------------------------------------------ main

def scene_jobs(scene: Scene, conf: PipelineConfig, mv: MultiviewConfig, cache: H5Cache, workdir: str,
               progress: bool = False, keep: bool = False) -> list[BagJob]:
    """Bags of a scene and their jobs: features, k-NN tables (cached) and tentative matches of the pairs used."""
    from tqdm.auto import tqdm

    from pipeline.data.resize import scaled_K
    from pipeline.metrics.covisibility import common_points
    from pipeline.tasks.prepare import image_features, pair_knn, tentative_matches
    bags = scene_bags(scene, mv.bag_spec, min_points=mv.min_points, seed=mv.bag_seed)
    if not bags and len(scene.images) < MIN_BAG:
        raise ImtuneError(f"scene {scene.name}: {len(scene.images)} images, and a multiview bag needs at least "
                          f"{MIN_BAG} (COLMAP's mapper keeps no model of two images); leave it out with --scenes")
    if not bags:
        raise ImtuneError(f"scene {scene.name}: no valid bag (each image must see >= {mv.min_points} of the bag's "
                          f"3D points; {len(scene.images)} images)")
    order = {n: k for k, n in enumerate(scene.images)}
    missing = [n for b in bags.values() for bag in b for n in bag if scene.images[n].R is None]
    if missing:
        raise ImtuneError(f"scene {scene.name}: no ground-truth pose for image {missing[0]} (multiview needs poses)")
    names = sorted({n for b in bags.values() for bag in b for n in bag}, key=order.__getitem__)
    bag_pairs = {(x, y) for lst in bags.values() for bag in lst for k, x in enumerate(bag) for y in bag[k + 1:]}
    why = scene.zero_baseline([Pair(x, y) for x, y in sorted(bag_pairs)])
    if why:  # a bag's pair errors there were inf or rounding noise
        raise ImtuneError(f"scene {scene.name}: {why}")
    feats = {n: image_features(cache, scene.images[n], conf.feature)
             for n in tqdm(names, desc=f"{scene.name}: features", disable=not progress, leave=False)}
    obs = scene.observations if mv.pair_min_points > 0 else None  # pairs need common 3D points when set
    pairs = set()
    for b in bags.values():
        for bag in b:
            for k, a in enumerate(bag):
                for c in bag[k + 1:]:
                    pairs.add((a, c) if order[a] < order[c] else (c, a))
    matches = {}
    for a, c in tqdm(sorted(pairs, key=lambda p: (order[p[0]], order[p[1]])), desc=f"{scene.name}: matching",
                     disable=not progress, leave=False):
        if obs is not None and common_points(obs.get(a, ([], None)), obs.get(c, ([], None))) < mv.pair_min_points:
            continue
        tab, _ = pair_knn(cache, feats[a], feats[c], conf.matching)
        # the one tentative-matches function of every task: matcher (or the imported multiview matches), pre-filter
        m, _ = tentative_matches(tab, conf.matching, feats[a], feats[c], task="multiview")
        matches[(a, c)] = np.asarray(m, np.int64).reshape(-1, 2)
    jobs = []
    for size in sorted(bags):
        for idx, bag in enumerate(bags[size]):
            bag = tuple(sorted(bag, key=order.__getitem__))
            info = {n: scene.images[n] for n in bag}
            jobs.append(BagJob(
                scene=scene.name, size=size, index=idx, names=bag,
                keypoints={n: np.asarray(feats[n].keypoints, np.float32) for n in bag},
                image_sizes={n: (feats[n].width, feats[n].height) for n in bag},
                K={n: (None if (Kn := info[n].K) is None else scaled_K(Kn, feats[n].sx, feats[n].sy)) for n in bag},
                paths={n: str(info[n].path) for n in bag},
                poses={n: (np.asarray(info[n].R, float), np.asarray(info[n].t, float).reshape(3)) for n in bag},
                matches={p: matches[p] for p in ((a, c) for k, a in enumerate(bag) for c in bag[k + 1:]) if p in matches},
                conf=mv, workdir=workdir, keep=keep))
    return jobs


def _bag_key(job: BagJob) -> str:
    import hashlib
    h = hashlib.sha1()
    for n in job.names:
        h.update(n.encode())
        h.update(np.ascontiguousarray(job.keypoints[n]).tobytes())
        K = job.K.get(n)
        h.update(b"" if K is None else np.asarray(K, float).tobytes())
        R, t = job.poses[n]
        h.update(np.asarray(R, float).tobytes() + np.asarray(t, float).tobytes())
    for p in sorted(job.matches):
        h.update(("|".join(p)).encode())
        h.update(np.ascontiguousarray(job.matches[p]).tobytes())
    return make_key("bag", h.hexdigest(), dataclasses.asdict(job.conf), BAG_STAGE_VERSION)


@TASKS.register("multiview", "COLMAP reconstructions of bags of images from our tentative matches; pose mAA, SR, RC, ATE")
class MultiviewTask(Task):
    """The paper's multiview task: bags of each scene reconstructed by COLMAP (its own RANSAC and mapper) from
    the configuration's tentative matches; figures per bag size, then the mean over sizes, then over scenes.

    ``mv``: a :class:`MultiviewConfig` (default: the protocol's bags); ``workers``: parallel bag processes (None:
    the CPUs this process may use; <= 1 runs bags in this process); ``use_cache``: reuse bag records whose inputs
    are unchanged; ``keep_models``: keep every bag's COLMAP database and model under this folder (its bags are
    then reconstructed, never read from the cache);
    ``progress``: tqdm bars. ``on_step`` is called after each scene."""

    name = "multiview"
    uses = ("ratio", "strategy", "min_confidence")  # COLMAP verifies the matches with its own RANSAC: eta and Gamma play no part
    summary_keys = MULTIVIEW_KEYS[:-1] + ("accuracy",)
    std_keys = ("mAA5", "mAA10", "SR")
    columns = ("bags", "SR", "RC", "NL", "TL", "mAA5", "mAA10", "ATE", "failed", "NM", "seconds")
    space_file = "multiview.yaml"
    records_key = "bag_records"
    note = "COLMAP from our tentative matches; SR, RC in %; ATE in ground-truth units"
    unit, unit_one = "bags", "bag"
    units_label = "multiview bags (COLMAP; paired over the same bags)"
    verifier = "COLMAP"  # its own RANSAC and mapper verify the matches: eta and Gamma play no part
    why_untimed = "COLMAP reconstructs each bag whole, with its own RANSAC, untimed"
    test_figures = "multiview mAA(10°) of the COLMAP reconstructions of the test bags [95% interval over bags and runs]"
    # a comparison runs the bags the studies were tested on (all but COLMAP's seed, which the comparison sets)
    reapplied = tuple(f.name for f in dataclasses.fields(MultiviewConfig) if f.name != "seed")
    needs_points = True  # bags are sampled from the 3D points each image sees
    sweep = True  # ~110 COLMAP reconstructions a trial: `tune findings` sweeps r's grid, as the paper did

    @classmethod
    def intervals(cls, records: list[dict], **kw) -> dict:
        """Bags resampled within each scene (:func:`pipeline.metrics.uncertainty.bag_intervals`)."""
        from pipeline.metrics.uncertainty import bag_intervals
        return bag_intervals(records, **kw)

    @classmethod
    def paired(cls, records_a: list[dict], records_b: list[dict], **kw) -> dict:
        """Paired over the bags both evaluated (:func:`pipeline.metrics.uncertainty.paired_bags`)."""
        from pipeline.metrics.uncertainty import paired_bags
        return paired_bags(records_a, records_b, **kw)

    def __init__(self, mv: MultiviewConfig | dict | None = None, workers: int | None = None, use_cache: bool = True,
                 keep_models: str | Path | None = None, progress: bool = False, ci_resamples: int = CI_RESAMPLES):
        self.ci_resamples = int(ci_resamples or 0)  # bootstrap over bags of the final summary (0 = none)
        if isinstance(mv, dict):
            values: dict[str, Any] = {k: (tuple(tuple(x) for x in v) if k == "bags" else v) for k, v in mv.items()}
            mv = MultiviewConfig(**values)
        self.mv = mv or MultiviewConfig()
        self.workers = workers
        self.use_cache = use_cache
        if keep_models is not None:  # a file there failed every bag (mAA 0, "NotADirectoryError" per record), unsaid
            from pipeline.fileio import check_writable_folder
            check_writable_folder(keep_models, "--keep-models folder", "give a writable folder with --keep-models DIR")
        self.keep_models = keep_models
        self.progress = progress

    def options(self) -> dict:
        return dataclasses.asdict(self.mv)

    @classmethod
    def from_options(cls, options: dict | None, **extra) -> MultiviewTask:
        """The options are the MultiviewConfig's fields."""
        return super().from_options({"mv": dict(options)} if options else None, **extra)

    def evaluation_units(self, scene: Scene) -> list:
        return scene.select_pairs(None)

    def check_scene(self, scene: Scene) -> str | None:
        """Bags need ground-truth poses and either the scene's own bags or 3D points to sample them from."""
        if len(scene.images) < MIN_BAG:
            return f"nothing for the multiview task to evaluate (fewer than {MIN_BAG} images, the smallest bag)"
        if not scene.bags and scene.observations is None:
            return "no ground truth to evaluate against (no multiview bags and no 3D points to sample them from)"
        missing = [n for n, im in scene.images.items() if im.R is None]
        if missing:
            return f"no ground truth to evaluate against (no pose for image {missing[0]})"
        return None

    def scene_notes(self, scene: Scene) -> list[str]:
        """Bag sizes above the scene's image count are evaluated as bags of all its images (one bag: the protocol's
        25-image bags on an 11-image Strecha scene), which the per-size results list under that size."""
        n = len(scene.images)
        over = sorted(size for size in self.mv.bag_spec if size > n)
        notes = []
        if over and n >= 2:
            sizes = ", ".join(map(str, over))
            notes.append(f"scene {scene.name} has {n} images: bag size{'s' if len(over) > 1 else ''} {sizes} evaluated "
                         f"as bags of all {n} (listed under size {n}, at most one bag); its multiview numbers at those "
                         "sizes are not the protocol's")
        try:  # a size no bag of which passes the visibility rule drops out of the means over sizes
            bags = scene_bags(scene, self.mv.bag_spec, min_points=self.mv.min_points, seed=self.mv.bag_seed)
        except ImtuneError:  # no bags at all: the evaluation says why
            return notes
        wanted = sorted({min(s, n) for s in self.mv.bag_spec if min(s, n) >= MIN_BAG} - set(bags))
        for size in wanted:
            notes.append(f"scene {scene.name}: no bag of {size} images in which each image sees >= "
                         f"{self.mv.min_points} of the bag's 3D points: size {size} is left out, and its multiview "
                         f"means are over the sizes {', '.join(map(str, sorted(bags)))} only")
        for size, count in sorted(self.mv.bag_spec.items()):  # fewer bags than asked (the protocol allows it): said
            got = len(bags.get(size, ())) if size <= n else count
            if 0 < got < count:
                notes.append(f"scene {scene.name}: {got} bag{'s' if got != 1 else ''} of {size} images, not {count}: its "
                             f"{n} images give only {got} distinct bag{'s' if got != 1 else ''} passing the visibility "
                             "rule (the protocol takes fewer where a scene has fewer)")
        return notes

    def for_run(self, conf: PipelineConfig, k: int):
        """COLMAP's seed varies across repeated runs (the bags stay the same)."""
        from pipeline.config import run_seed
        t = MultiviewTask(dataclasses.replace(self.mv, seed=run_seed(self.mv.seed, k)), workers=self.workers,
                          use_cache=self.use_cache, keep_models=self.keep_models, progress=self.progress,
                          ci_resamples=self.ci_resamples)
        return t, conf

    def figures(self, result: TaskResult) -> dict:
        """The overall figures, accuracy at 1..10 deg, per bag size, and per scene the same."""
        keys = MULTIVIEW_KEYS[:-1]

        def part(s):
            d = {k: s.get(k) for k in keys}
            d["accuracy"] = s.get("accuracy")
            d["by_size"] = {size: {k: v.get(k) for k in keys} for size, v in (s.get("by_size") or {}).items()}
            d.update({k: v for k, v in s.items() if k in CI_KEYS})  # intervals, where computed
            return d
        out = part(result.summary)
        out["scenes"] = {name: part(s) for name, s in result.scenes.items()}
        return out

    def evaluate(self, scenes: list[Scene], conf: PipelineConfig, cache: H5Cache | None = None,
                 on_step=None) -> TaskResult:
        mv, keep_models, use_cache = self.mv, self.keep_models, self.use_cache
        progress = self.progress
        cache = cache if cache is not None else H5Cache()
        workers = self.workers if self.workers is not None else available_cpus()
        tmp = tempfile.mkdtemp(prefix="imtune-mv-") if keep_models is None else str(keep_models)
        summaries: dict[str, dict] = {}
        all_records: list[dict] = []
        secs = {"prepare": 0.0, "bags": 0.0}
        try:
            for idx, scene in enumerate(scenes):
                t0 = time.perf_counter()
                jobs = scene_jobs(scene, conf, mv, cache, tmp, progress=progress, keep=keep_models is not None)
                secs["prepare"] += time.perf_counter() - t0
                t0 = time.perf_counter()
                keys = [_bag_key(j) for j in jobs] if use_cache else []  # read only when use_cache
                recs: list[dict | None] = [None] * len(jobs)
                if use_cache and keep_models is None:  # a cached bag has no model to keep: it is reconstructed
                    for k, key in enumerate(keys):
                        got = cache.get("bags", key)
                        if got is not None:
                            recs[k] = _decode(got)
                todo = [k for k in range(len(jobs)) if recs[k] is None]
                fresh = run_bags([jobs[k] for k in todo], workers=workers, progress=progress,
                                 desc=f"{scene.name}: bags")
                for k, r in zip(todo, fresh):
                    recs[k] = r
                    if use_cache and not _transient(r):
                        cache.put("bags", keys[k], _encode(r))
                secs["bags"] += time.perf_counter() - t0
                summaries[scene.name] = summarize_scene(recs)  # type: ignore[arg-type]
                all_records.extend(recs)  # type: ignore[arg-type]
                if on_step is not None:
                    on_step(idx, len(scenes), combine(summaries))
        finally:
            if keep_models is None:
                shutil.rmtree(tmp, ignore_errors=True)
        summary = combine(summaries)
        if self.ci_resamples:  # the final summary only: a bootstrap over bags (never on a step)
            from pipeline.metrics.uncertainty import bag_intervals
            add_intervals(summary, summaries, bag_intervals(all_records, n_resamples=self.ci_resamples, seed=CI_SEED,
                                                            scenes=[sc.name for sc in scenes]), self.ci_resamples)
            summary["ci"]["method"] = "percentile bootstrap, resampling bags within each scene and bag size"
        return TaskResult(summary=summary, scenes=summaries, records=all_records, seconds=secs,
                          records_key=self.records_key)


def evaluate_multiview(scenes: list[Scene], conf: PipelineConfig, mv: MultiviewConfig | None = None,
                       cache: H5Cache | None = None, workers: int | None = None, progress: bool = False,
                       use_cache: bool = True, keep_models: str | Path | None = None) -> TaskResult:
    """``MultiviewTask(mv, workers, ...).evaluate(scenes, conf, cache)``: one configuration, every scene."""
    return MultiviewTask(mv, workers=workers, use_cache=use_cache, keep_models=keep_models,
                         progress=progress).evaluate(scenes, conf, cache)


def _transient(rec: dict) -> bool:
    """Failures that say nothing about the matches (worker died, Python error): never cached."""
    f = rec.get("failure") or ""
    return f.startswith("COLMAP worker process died") or (":" in f and f.split(":")[0].endswith("Error"))


def _encode(rec: dict) -> dict[str, np.ndarray]:
    blob = json.dumps(rec, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o),
                      allow_nan=True).encode()
    return {"json": np.frombuffer(blob, dtype=np.uint8)}


def _decode(arrays: dict[str, np.ndarray]) -> dict:
    rec = json.loads(bytes(np.asarray(arrays["json"], np.uint8)).decode())
    rec["errors"] = [float(e) for e in rec["errors"]]
    return rec
