"""The IMC 2024 / 2025 reconstruction task: a whole dataset (several scenes that look alike, plus outlier images)
reconstructed by COLMAP from our verified matches, every reconstruction a cluster, scored by the challenge's
clustering-aware camera-centre mAA, clusterness and their harmonic mean (:mod:`pipeline.metrics.imc_score`).

Per dataset (an imtune scene loaded by :mod:`pipeline.data.imc2025`):

1. features of every image (cached, as every task);
2. the pairs matched: every pair for a dataset of at most ``exhaustive_up_to`` images, else a *shortlist*: each image
   with its ``shortlist`` most similar images, similarity = mutual nearest neighbours (ratio < 0.8) among the
   ``SHORTLIST_FEATURES`` strongest descriptors of the two images. Why: exhaustive matching is quadratic (2,850 pairs
   for the 76-image dataset, ~1 s of 8k x 8k k-NN and up to the budget B of RANSAC each: about an hour on one core),
   and the challenge's entrants shortlist the same way (with global descriptors; no global-descriptor weights are
   available offline here, so the shortlist is built from the local features already extracted);
3. tentative matches (the one tentative-matches function of every task: ratio r, strategy) and geometric
   verification by the configuration's estimator (eta, Gamma; its CPU seconds per pair are what the budget bounds);
4. a COLMAP database with the verified inliers as two-view geometries (F, uncalibrated), and pycolmap mapping:
   ``mapper`` "incremental" (``pycolmap.incremental_mapping``) or "global" (``pycolmap.global_mapping``, COLMAP 4's
   GLOMAP); the mapper options that decide registration are ``PipelineConfig.mapper`` (searched by a study);
5. every reconstruction of at least ``min_model_size`` images is a cluster (``cluster0`` the largest, ...); the images
   in none are written under ``outliers`` with ``nan`` poses; ``submission.csv`` (the challenge's
   ``dataset,scene,image,rotation_matrix,translation_vector``) is written for every evaluation;
6. the score, mAA and clusterness per dataset and per ground-truth scene.

A dataset's figures are one number each (the score is a set function over the whole dataset): no bootstrap interval
is computed (resampling images would change the alignment triplets and the clusters themselves); repeated runs
(COLMAP's and the estimator's seeds) give the standard deviation.
"""
from __future__ import annotations

import dataclasses
import math
import os
import shutil
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.cache import H5Cache
from pipeline.config import PipelineConfig
from pipeline.data.scene import Scene
from pipeline.errors import EvaluationStopped, ImtuneError
from pipeline.metrics.imc_score import OUTLIERS, centre, score_dataset
from pipeline.tasks.base import TASKS, Task, TaskResult

MAPPERS = ("incremental", "global")
PIPELINES = ("imtune", "colmap", "imc2025-baseline")
VERIFIERS = ("ours", "colmap")
TWO_VIEW = ("F", "colmap")
#: verification runs per dataset (not served from the in-memory cache of a task): tests read it
COUNTERS: Counter = Counter()
#: the pipeline options the reconstruction task runs with where the command line does not set them (`tune evaluate
#: --task reconstruction`, `tune --task reconstruction`; ``Task.pipeline_defaults``): COLMAP's SIFT, whose features
#: close most of the gap to COLMAP out of the box (benchmarks/reconstruction_causes.py), eta 1 px and Gamma 10,000
#: (COLMAP's own verification's cap: a shortlist's pairs of two different scenes run to the cap)
NEW_DEFAULTS = {"feature": "colmap-sift", "threshold": 1.0, "max_iters": 10_000}
VERIFIED_KEPT = 8  # dataset verifications a task keeps in memory (a study: its validation datasets, a few trials)
SHORTLIST_FEATURES = 256
SHORTLIST_RATIO = 0.8
RECON_KEYS = ("score", "mAA", "clusterness", "registered", "clusters", "pairs", "NM", "NI", "ransac_seconds_median",
              "map_seconds", "excluded")
WHY_NO_CI = ("no interval: a dataset's score is one set function of all its images (alignment triplets, clusters); "
             "resampling images would change the clusters themselves. Repeated runs give the standard deviation")


@dataclass(frozen=True)
class ReconstructionConfig:
    """Settings of the reconstruction task (the mapper options it searches are ``PipelineConfig.mapper``).

    mapper: "incremental" or "global" (GLOMAP).
    shortlist: partners per image matched when the dataset has more than ``exhaustive_up_to`` images (0: all pairs;
        20, not 10: at 10 the 76-image IMC 2025 dataset's scenes broke into fragments).
    exhaustive_up_to: datasets of at most this many images match every pair.
    intrinsics: "colmap" (EXIF or 1.2 x the long side, refined: IMC 2025 gives none), "prior" or "fixed" (known K:
        IMC 2024's calibration_matrix).
    seed: COLMAP's random seed (vary it across repeated runs).
    pipeline: "imtune" (our features, matcher and estimator; the mapper options of ``PipelineConfig.mapper``) or
        "colmap": COLMAP's own pipeline at its defaults, the reference an entrant runs (:func:`colmap_reference`):
        its SIFT at the configuration's ``num_features``, exhaustive matching, its two-view verification, the
        incremental mapper at pycolmap's defaults with ``min_model_size`` 3 and ``max_num_models`` 25; or
        "imc2025-baseline": the IMC 2025 challenge's baseline (:func:`baseline_config`): ALIKED matched by LightGlue,
        COLMAP's two-view verification at pycolmap's defaults, the same mapper as "colmap".
    verifier: "ours" (the configuration's estimator: r, eta, Gamma) or "colmap" (COLMAP's two-view verification of
        our tentative matches at pycolmap's defaults; eta and Gamma unused).
    two_view: what the database stores of a pair our estimator verified: "F" (its fundamental matrix and inliers, as
        an uncalibrated geometry) or "colmap" (COLMAP's two-view geometry estimation on those inliers picks the
        configuration: calibrated E, planar / panoramic H or F, as its own verification would).
    """
    mapper: str = "incremental"
    shortlist: int = 20
    exhaustive_up_to: int = 30
    intrinsics: str = "colmap"
    seed: int = 0
    pipeline: str = "imtune"
    verifier: str = "ours"
    two_view: str = "F"

    def __post_init__(self):
        from pipeline.colmap_db import INTRINSICS_MODES
        if self.mapper not in MAPPERS:
            raise ImtuneError(f"unknown mapper {self.mapper!r} (choose {', '.join(MAPPERS)})")
        for what, v, ok in (("pipeline", self.pipeline, PIPELINES), ("verifier", self.verifier, VERIFIERS),
                            ("two_view", self.two_view, TWO_VIEW)):
            if v not in ok:
                raise ImtuneError(f"unknown reconstruction {what} {v!r} (choose {', '.join(ok)})")
        if self.intrinsics not in INTRINSICS_MODES:
            raise ImtuneError(f"unknown intrinsics mode {self.intrinsics!r} (choose {', '.join(INTRINSICS_MODES)})")
        if int(self.shortlist) < 0 or int(self.exhaustive_up_to) < 0:
            raise ImtuneError("shortlist and exhaustive_up_to must be >= 0")
        from pipeline.config import check_seed
        check_seed("reconstruction seed", self.seed)


# ----------------------------------------------------------------------------------------------- pairs

def shortlist_pairs(feats: dict, names: list[str], k: int) -> list[tuple[str, str]]:
    """Each image with its ``k`` most similar images (mutual nearest neighbours with ratio < 0.8 among the
    :data:`SHORTLIST_FEATURES` strongest descriptors of each image; ties: the earlier image); pairs in name order."""
    order = {n: i for i, n in enumerate(names)}
    descs = []
    for name in names:
        f = feats[name]
        d = np.asarray(f.descriptors, np.float32)
        if f.scores is not None and len(f.scores) == len(d):
            d = d[np.argsort(-np.asarray(f.scores))[:SHORTLIST_FEATURES]]
        else:
            d = d[:SHORTLIST_FEATURES]
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        descs.append(d)
    count = len(names)
    sim = np.zeros((count, count))
    for i in range(count):
        for j in range(i + 1, count):
            a, b = descs[i], descs[j]
            if len(a) < 2 or len(b) < 2:
                continue
            dist = np.sqrt(np.maximum(2.0 - 2.0 * a @ b.T, 0.0))
            nn12 = np.argsort(dist, axis=1)[:, :2]
            nn21 = np.argmin(dist, axis=0)
            rows = np.arange(len(a))
            d1, d2 = dist[rows, nn12[:, 0]], dist[rows, nn12[:, 1]]
            ok = (nn21[nn12[:, 0]] == rows) & (d1 < SHORTLIST_RATIO * d2)
            sim[i, j] = sim[j, i] = float(ok.sum())
    pairs = set()
    for i in range(count):
        part = [j for j in np.argsort(-sim[i], kind="stable") if j != i][:k]
        for j in part:
            a, b = (names[i], names[j]) if i < j else (names[j], names[i])
            pairs.add((a, b))
    return sorted(pairs, key=lambda p: (order[p[0]], order[p[1]]))


# ------------------------------------------------------------------------------------------- workers

def _verify_pairs(args) -> list[dict]:
    """Worker: k-NN (cached), tentative matches and our estimator on a chunk of pairs. Returns one dict per pair
    with its tentative matches, inlier mask, F and the estimator's CPU seconds. Never raises for one pair."""
    cache_root, infos, conf, chunk = args
    from pipeline.geometry import get_estimator
    from pipeline.tasks.prepare import image_features, pair_knn, tentative_matches
    cache = H5Cache(cache_root)
    est = get_estimator(conf.geometry.ransac)
    g = conf.geometry
    feats: dict = {}
    out = []
    for a, b in chunk:
        rec: dict = {"pair": (a, b), "NM": 0, "NI": 0, "ransac_seconds": 0.0, "matches": None, "inliers": None,
                     "F": None, "failure": None}
        try:
            for n in (a, b):
                if n not in feats:
                    feats[n] = image_features(cache, infos[n], conf.feature)
            fa, fb = feats[a], feats[b]
            tab, _ = pair_knn(cache, fa, fb, conf.matching)
            m, _ = tentative_matches(tab, conf.matching, fa, fb, task="multiview")
            m = np.asarray(m, np.int64).reshape(-1, 2)
            rec["NM"] = len(m)
            # a pair with fewer tentative matches than the mapper's min_inliers cannot enter the view graph: no RANSAC
            # (COLMAP skips such pairs too); most of a shortlist's cross-scene pairs end here, at no estimator cost
            need = max(8, int(conf.mapper.min_inliers))
            if len(m) >= need:
                p1 = fa.keypoints[m[:, 0]].astype(np.float64)
                p2 = fb.keypoints[m[:, 1]].astype(np.float64)
                res = est.estimate(p1, p2, g.threshold, g.confidence, g.max_iters, seed=g.seed,
                                   sizes=((fa.width, fa.height), (fb.width, fb.height)))
                rec["ransac_seconds"] = float(res.seconds)
                if res.F is not None:
                    inl = np.asarray(res.inliers, bool).reshape(-1)
                    rec.update(NI=int(inl.sum()), matches=m, inliers=inl, F=np.asarray(res.F, float))
                else:
                    rec["failure"] = "estimator found no model"
            else:
                rec["failure"] = f"fewer than {need} matches ({len(m)})"
        except ImtuneError:
            raise
        except Exception as e:  # one pair never stops the dataset
            rec["failure"] = f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}"
        out.append(rec)
    return out


def _init_worker():
    from pipeline.tasks.pool import ignore_sigint_here
    ignore_sigint_here()
    try:
        import cv2
        cv2.setNumThreads(1)
    except Exception:
        pass


def verify_all(cache: H5Cache, infos: dict, conf: PipelineConfig, pairs: list[tuple[str, str]], workers: int,
               progress: bool = False, desc: str = "pairs") -> list[dict]:
    """:func:`_verify_pairs` over every pair, in ``workers`` spawned processes (in this one when <= 1)."""
    from tqdm.auto import tqdm
    chunks = [pairs[k:k + 8] for k in range(0, len(pairs), 8)]
    out: list[dict] = []
    bar = tqdm(total=len(pairs), desc=desc, disable=not progress, leave=False)
    if workers <= 1 or len(chunks) <= 1:
        for c in chunks:
            out.extend(_verify_pairs((str(cache.root), infos, conf, c)))
            bar.update(len(c))
        bar.close()
        return out
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from pipeline.tasks.pool import single_thread_env
    with single_thread_env():
        ex = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_init_worker)
    try:
        for res in ex.map(_verify_pairs, [(str(cache.root), infos, conf, c) for c in chunks]):
            out.extend(res)
            bar.update(len(res))
    finally:
        ex.shutdown(wait=True, cancel_futures=True)
        bar.close()
    return out


# ------------------------------------------------------------------------------------------- mapping

#: mapper options only the incremental mapper reads, and only the global one (:func:`_mapper_options`)
INCREMENTAL_ONLY = ("max_num_models", "init_min_num_inliers", "abs_pose_min_num_inliers", "abs_pose_max_error",
                    "filter_max_reproj_error")
GLOBAL_ONLY = ("global_max_rotation_error", "global_max_angular_error")


def _mapper_options(kind: str, conf: PipelineConfig, rc: ReconstructionConfig, threads: int):
    """pycolmap's options of ``kind`` ("incremental" / "global") with ``conf.mapper``'s values set on them."""
    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    mc = conf.mapper
    if kind == "incremental":
        o = cdb.mapper_options(min_model_size=mc.min_model_size, num_threads=threads, seed=rc.seed,
                               fixed_intrinsics=(rc.intrinsics == "fixed"))
        o.max_num_models = int(mc.max_num_models)
        o.mapper.init_min_num_inliers = int(mc.init_min_num_inliers)
        o.mapper.abs_pose_min_num_inliers = int(mc.abs_pose_min_num_inliers)
        o.mapper.abs_pose_max_error = float(mc.abs_pose_max_error)
        o.mapper.filter_max_reproj_error = float(mc.filter_max_reproj_error)
    else:
        o = pycolmap.GlobalPipelineOptions()
        o.min_model_size = int(mc.min_model_size)
        o.num_threads = int(threads)
        o.random_seed = int(rc.seed)
        o.multiple_models = True
        o.mapper.num_threads = int(threads)
        o.mapper.random_seed = int(rc.seed)
        o.mapper.global_positioning.use_gpu = False
        o.mapper.bundle_adjustment.ceres.use_gpu = False
        o.mapper.rotation_averaging.max_rotation_error_deg = float(mc.global_max_rotation_error)
        o.mapper.max_angular_reproj_error_deg = float(mc.global_max_angular_error)
        if rc.intrinsics == "fixed":
            o.mapper.bundle_adjustment.refine_focal_length = False
            o.mapper.bundle_adjustment.refine_extra_params = False
    o.min_num_matches = int(mc.min_inliers)
    return o


def _write_two_view(db, ids: dict, verified: list[dict], conf: PipelineConfig, rc: ReconstructionConfig,
                    cameras: dict, keypoints: dict) -> None:
    """Our verified pairs as two-view geometries: F as an uncalibrated geometry (``two_view`` "F"), or the geometry
    COLMAP's two-view estimation finds on our inliers (``two_view`` "colmap", pycolmap's default options)."""
    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    for r in verified:
        if r["matches"] is None or r["NI"] < conf.mapper.min_inliers:
            continue
        a, b = r["pair"]
        inl = np.ascontiguousarray(r["matches"][r["inliers"]].astype(np.uint32))
        if rc.two_view == "colmap":
            o = pycolmap.TwoViewGeometryOptions()
            o.ransac.random_seed = int(rc.seed)
            tvg = pycolmap.estimate_two_view_geometry(
                cameras[a], (keypoints[a] + cdb.PIXEL_OFFSET).astype(np.float64), cameras[b],
                (keypoints[b] + cdb.PIXEL_OFFSET).astype(np.float64), inl, o)
            if len(tvg.inlier_matches) < conf.mapper.min_inliers:
                continue
        else:
            tvg = pycolmap.TwoViewGeometry()
            tvg.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            tvg.F = np.asarray(r["F"], float)
            tvg.inlier_matches = inl
        db.write_two_view_geometry(ids[a], ids[b], tvg)


def map_dataset(workdir: Path, images: list, verified: list[dict], conf: PipelineConfig, rc: ReconstructionConfig,
                threads: int = 1, tentative: dict | None = None,
                timeout: float | None = None) -> tuple[list, str | None, float]:
    """Write the database (cameras, keypoints, tentative matches, the verified pairs as two-view geometries) and
    run the mapper. ``rc.verifier`` "colmap": ``tentative`` ({pair: matches}) are written and COLMAP verifies them
    (pycolmap's default two-view options) instead of ``verified``; ``rc.pipeline`` "imc2025-baseline": the same with
    :func:`baseline_verification_options` and the reference's mapper (:func:`reference_mapper_options`). Returns (reconstructions, failure or None,
    mapping wall seconds); ``timeout``: the mapping's bound in seconds (:func:`run_mapper`)."""
    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    cdb.quiet(3)
    workdir.mkdir(parents=True, exist_ok=True)
    db_path = workdir / "database.db"
    baseline = rc.pipeline == "imc2025-baseline"
    if baseline:  # the IMC 2025 baseline: LightGlue's matches, COLMAP's verification and mapper at its settings
        cdb.write_database(db_path, images, tentative or {})
        cdb.verify(db_path, baseline_verification_options(), num_threads=threads)
        return run_mapper(workdir, db_path, reference_mapper_options(threads, rc.seed), "incremental",
                          REFERENCE_MIN_MODEL_SIZE, timeout=timeout)
    if rc.verifier == "colmap":
        ids = cdb.write_database(db_path, images, tentative or {})
        o = pycolmap.TwoViewGeometryOptions()
        o.min_num_inliers = int(conf.mapper.min_inliers)  # COLMAP's 15 at the defaults
        o.ransac.random_seed = int(rc.seed)
        cdb.verify(db_path, o, num_threads=threads)
    else:
        matches = {r["pair"]: r["matches"] for r in verified if r["matches"] is not None}
        ids = cdb.write_database(db_path, images, matches)
        db = pycolmap.Database.open(str(db_path))
        try:
            _write_two_view(db, ids, verified, conf, rc, {n: cam for n, cam, _ in images},
                            {n: np.asarray(k, np.float64).reshape(-1, 2) for n, _, k in images})
        finally:
            db.close()
    return run_mapper(workdir, db_path, _mapper_options(rc.mapper, conf, rc, threads), rc.mapper,
                      conf.mapper.min_model_size, timeout=timeout)


def run_mapper(workdir: Path, db_path: Path, opts, mapper: str, min_model_size: int,
               timeout: float | None = None) -> tuple[list, str | None, float]:
    """pycolmap's ``mapper`` on ``db_path`` with ``opts``; the models of at least ``min_model_size`` images, largest
    first, a failure reason or None, and the mapping wall seconds. ``timeout`` (seconds): the mapper runs in a child
    process (:func:`_map_in_child`), killed when it runs longer, and :class:`MappingTimeout` is raised (pycolmap's
    global mapper takes no cancellation token, and its incremental one stops only between images)."""
    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    out = workdir / "sparse"
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if timeout is not None:
        recs, failure = _map_in_child(db_path, workdir, out, opts, mapper, timeout)
        if failure is not None:
            return [], failure, time.perf_counter() - t0
    else:
        try:
            if mapper == "incremental":
                recs = pycolmap.incremental_mapping(str(db_path), str(workdir), str(out), opts)
            else:
                recs = pycolmap.global_mapping(str(db_path), str(workdir), str(out), opts)
        except Exception as e:
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            return [], f"mapper failed: {msg}", time.perf_counter() - t0
    dt = time.perf_counter() - t0
    models = [r for r in (recs or {}).values() if r.num_reg_images() >= min_model_size]
    models.sort(key=lambda r: -r.num_reg_images())
    return models, (None if models else "the mapper registered no model"), dt


class MappingTimeout(EvaluationStopped):
    """The mapper ran longer than its bound and was stopped (``seconds``: how long it ran)."""

    def __init__(self, msg: str, seconds: float):
        super().__init__(msg)
        self.seconds = seconds


def _mapper_child(db_path: str, workdir: str, out: str, opts, mapper: str, models: str, conn) -> None:
    """The child process of :func:`_map_in_child`: map, write every model to ``models/<k>``, send None or the
    failure's first line."""
    from pipeline import colmap_db as cdb
    from pipeline.tasks.pool import ignore_sigint_here
    ignore_sigint_here()  # Ctrl-C is the parent's: it kills this process
    pycolmap = cdb.import_pycolmap()
    cdb.quiet(3)
    try:
        if mapper == "incremental":
            recs = pycolmap.incremental_mapping(db_path, workdir, out, opts)
        else:
            recs = pycolmap.global_mapping(db_path, workdir, out, opts)
        for k, rec in enumerate((recs or {}).values()):
            d = Path(models) / str(k)
            d.mkdir(parents=True, exist_ok=True)
            rec.write(str(d))
        conn.send(None)
    except Exception as e:
        conn.send(f"mapper failed: {str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__}")
    finally:
        conn.close()


def _map_in_child(db_path: Path, workdir: Path, out: Path, opts, mapper: str, timeout: float) -> tuple[dict, str | None]:
    """The mapper in a spawned child process given ``timeout`` wall seconds: its reconstructions read back from disk
    ({k: Reconstruction}) and None, or ({}, failure) when it failed or died; :class:`MappingTimeout` when it ran out
    of time (the child is killed first)."""
    import multiprocessing as mp

    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    models = workdir / "child-models"
    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_mapper_child, args=(str(db_path), str(workdir), str(out), opts, mapper, str(models), send),
                    daemon=True)
    from pipeline.tasks.pool import sigint_held
    t0 = time.perf_counter()
    with sigint_held():
        p.start()
    send.close()
    try:
        ready = recv.poll(max(0.0, float(timeout)))
        dt = time.perf_counter() - t0
        if not ready:
            raise MappingTimeout(f"the {mapper} mapper ran beyond the bound of {float(timeout):g} s and was stopped "
                                 f"after {dt:.1f} s", dt)
        try:
            failure = recv.recv()
        except EOFError:  # the child died without a word (a crash inside COLMAP)
            p.join(5)
            return {}, f"mapper failed: its process ended with exit code {p.exitcode}"
        p.join()
    finally:
        if p.is_alive():
            p.kill()
            p.join()
        recv.close()
    if failure is not None:
        return {}, failure
    recs = {}
    for d in sorted(models.iterdir(), key=lambda d: int(d.name)) if models.is_dir() else []:
        recs[int(d.name)] = pycolmap.Reconstruction(str(d))
    return recs, None


# ------------------------------------------------------------------------------------ the COLMAP reference

REFERENCE_MIN_MODEL_SIZE = 3  # the IMC 2025 baseline's settings of COLMAP's incremental mapper
REFERENCE_MAX_NUM_MODELS = 25
REFERENCE_STAGE_VERSION = "1"


def reference_mapper_options(threads: int, seed: int):
    """The reference's mapper: ``pycolmap.IncrementalPipelineOptions()`` as constructed (pycolmap's defaults), with
    only ``min_model_size`` 3 and ``max_num_models`` 25 (the IMC 2025 baseline's), the thread count and the seeds
    set (:data:`REFERENCE_SET`)."""
    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    o = pycolmap.IncrementalPipelineOptions()
    o.min_model_size = REFERENCE_MIN_MODEL_SIZE
    o.max_num_models = REFERENCE_MAX_NUM_MODELS
    o.num_threads = int(threads)
    o.random_seed = int(seed)
    o.mapper.num_threads = int(threads)
    o.mapper.random_seed = int(seed)
    o.triangulation.random_seed = int(seed)
    return o


#: the options :func:`reference_mapper_options` sets (every other one is pycolmap's default)
REFERENCE_SET = ("min_model_size", "max_num_models", "num_threads", "random_seed", "mapper.num_threads",
                 "mapper.random_seed", "triangulation.random_seed")


def reference_stage_options(num_features: int, threads: int) -> tuple:
    """The reference's (extraction, matching, two-view verification) options: pycolmap's own option objects as
    constructed, with only ``sift.max_num_features``, the thread counts and the CPU device set
    (:data:`REFERENCE_STAGE_SET`)."""
    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    eo = pycolmap.FeatureExtractionOptions()
    eo.sift.max_num_features = int(num_features)
    eo.num_threads = int(threads)
    eo.use_gpu = False
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = int(threads)
    mo.use_gpu = False
    return eo, mo, pycolmap.TwoViewGeometryOptions()


#: what :func:`reference_stage_options` sets, per option object (every other option is pycolmap's default)
REFERENCE_STAGE_SET = (("sift.max_num_features", "num_threads", "use_gpu"), ("num_threads", "use_gpu"), ())


def reference_database(cache: H5Cache, scene: Scene, num_features: int, threads: int) -> Path:
    """COLMAP's own database of ``scene`` (cached under the cache folder, keyed by the image files, ``num_features``
    and pycolmap's version): ``pycolmap.extract_features`` (its SIFT at ``max_num_features`` = ``num_features``,
    every other extraction option pycolmap's default; one camera per image, COLMAP's default camera model and
    focal-length guess), then ``pycolmap.match_exhaustive`` at pycolmap's default matching and two-view
    verification options (every pair; its verification's RANSAC seed is pycolmap's default). Built once per key:
    repeated runs vary the mapper's seed only."""
    from pipeline import colmap_db as cdb
    from pipeline.cache import file_digest, make_key
    from pipeline.features.colmap_sift import _pycolmap_version
    pycolmap = cdb.import_pycolmap()
    names = list(scene.images)
    key = make_key("colmap-reference", [(n, file_digest(scene.images[n].path)) for n in names], int(num_features),
                   _pycolmap_version(), REFERENCE_STAGE_VERSION)
    folder = Path(cache.root) / "colmap-reference" / key
    db_path = folder / "database.db"
    if db_path.is_file():
        return db_path
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f"database.tmp{os.getpid()}.db"
    if tmp.exists():
        tmp.unlink()
    cdb.quiet(2)
    img_dir = Path(scene.images[names[0]].path).parent
    if any(Path(scene.images[n].path).parent != img_dir for n in names):
        raise ImtuneError(f"dataset {scene.name}: the COLMAP reference needs every image in one folder")
    eo, mo, vo = reference_stage_options(num_features, threads)
    pycolmap.extract_features(str(tmp), str(img_dir), image_names=names, extraction_options=eo,
                              device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(str(tmp), matching_options=mo, verification_options=vo, device=pycolmap.Device.cpu)
    COUNTERS["reference_database"] += 1
    os.replace(tmp, db_path)
    return db_path


# ------------------------------------------------------------------------------ the IMC 2025 baseline

#: what the IMC 2025 challenge's baseline notebook runs (ALIKED + LightGlue, COLMAP's verification, the incremental
#: mapper at min_model_size 3 and max_num_models 25), at the configuration's ``num_features`` (the notebook's 4096 is
#: ``--num-features 4096``): ALIKED's detection threshold 0.01 and LightGlue with its adaptive depth and width off,
#: as the notebook sets them; LightGlue's own filter_threshold (kornia's default, 0.1); a pair with fewer than 15
#: LightGlue matches is not written to the database (the notebook's ``min_matches``)
BASELINE_FEATURE_OPTIONS = (("detection_threshold", 0.01),)
BASELINE_MATCHER_OPTIONS = (("depth_confidence", -1.0), ("width_confidence", -1.0))
BASELINE_MIN_CONFIDENCE = 0.1
BASELINE_MIN_MATCHES = 15


def baseline_config(conf: PipelineConfig) -> PipelineConfig:
    """The IMC 2025 baseline's features and matcher (:data:`BASELINE_FEATURE_OPTIONS`, ...) with ``conf``'s
    ``num_features`` and ``max_side``; every other section of ``conf`` as it is (the baseline does not use the
    estimator: COLMAP verifies). Idempotent."""
    from pipeline.config import FeatureConfig, MatchConfig
    f = FeatureConfig(name="aliked", num_features=conf.feature.num_features, max_side=conf.feature.max_side,
                      options=tuple(sorted(BASELINE_FEATURE_OPTIONS)))
    m = MatchConfig(method="lightglue", min_confidence=BASELINE_MIN_CONFIDENCE,
                    matcher_options=tuple(sorted(BASELINE_MATCHER_OPTIONS)))
    return dataclasses.replace(conf, feature=f, matching=m)


def baseline_verification_options():
    """The baseline's two-view verification: ``pycolmap.TwoViewGeometryOptions()`` as constructed (the notebook
    calls ``pycolmap.match_exhaustive`` at its defaults on the imported matches); nothing is set."""
    from pipeline import colmap_db as cdb
    return cdb.import_pycolmap().TwoViewGeometryOptions()


def clusters_from_models(models: list, names: list[str], min_size: int) -> dict[str, dict[str, tuple]]:
    """Clusters from the mapper's models, largest first, each image in one cluster only: COLMAP's incremental mapper
    with several models may register an image in more than one of them (the challenge refuses a submission naming an
    image twice), so an image stays in the first (largest) model that has it and a later model keeps the rest; a model
    left with fewer than ``min_size`` images is no cluster. Poses (world-to-camera, the model's frame) by image name."""
    from pipeline import colmap_db as cdb
    taken: set[str] = set()
    out: dict[str, dict[str, tuple]] = {}
    for m in models:
        poses = cdb.model_poses(m)
        mine = {n: poses[n] for n in names if n in poses and n not in taken}
        if len(mine) >= min_size:
            out[f"cluster{len(out)}"] = mine
            taken.update(mine)
    return out


# ------------------------------------------------------------------------------------------ submission

def _fmt(a) -> str:
    return ";".join("nan" if not np.isfinite(x) else repr(float(x)) for x in np.asarray(a, float).reshape(-1))


def submission_rows(dataset: str, names: list[str], clusters: dict[str, dict[str, tuple]]) -> list[tuple]:
    """(dataset, cluster, image, R ';'-joined, t ';'-joined): the registered images cluster by cluster (cluster0
    first), then every other image under ``outliers`` with nan. One row per image."""
    rows, seen = [], set()
    for c, poses in clusters.items():
        for n in names:
            if n in poses:
                R, t = poses[n]
                rows.append((dataset, c, n, _fmt(R), _fmt(t)))
                seen.add(n)
    nan9, nan3 = ";".join(["nan"] * 9), ";".join(["nan"] * 3)
    rows.extend((dataset, OUTLIERS, n, nan9, nan3) for n in names if n not in seen)
    return rows


SUBMISSION_HEADER = ("dataset", "scene", "image", "rotation_matrix", "translation_vector")


def write_submission(path: Path, rows: list[tuple]) -> None:
    """The challenge's submission.csv (atomic write)."""
    import csv
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(SUBMISSION_HEADER)
        w.writerows(rows)
    os.replace(tmp, path)


def score_rows(scene: Scene, rows: list[tuple]):
    """The challenge's score of submission rows of ``scene`` (clusters in the order the rows give them)."""
    groups = scene.groups or {}
    truth: dict[str, dict] = {}
    for n, g in groups.items():
        im = scene.images[n]
        truth.setdefault(g, {})[n] = None if g == OUTLIERS else centre(im.R, im.t)
    clusters: dict[str, dict] = {}
    seen: set[str] = set()
    for _, c, n, R, t in rows:
        if n in seen:  # the challenge's own check refuses such a submission
            raise ImtuneError(f"dataset {scene.name}: image {n} is written twice in the submission")
        seen.add(n)
        Rv = np.array([float(x) for x in R.split(";")], float)
        tv = np.array([float(x) for x in t.split(";")], float)
        clusters.setdefault(c, {})[n] = centre(Rv, tv) if np.all(np.isfinite(Rv)) and np.all(np.isfinite(tv)) \
            else np.full(3, math.nan)
    return score_dataset(truth, clusters, {k: list(v) for k, v in (scene.thresholds or {}).items()},
                         dataset=scene.name)


# ------------------------------------------------------------------------------------------------ task

@TASKS.register("reconstruction", "IMC 2024/2025 datasets reconstructed whole (pycolmap incremental or global), "
                "clustered into scenes; the challenge's score, mAA and clusterness")
class ReconstructionTask(Task):
    """The IMC 2024/2025 task (module docstring). ``rc``: a :class:`ReconstructionConfig` (or its dict); ``mapper``:
    shortcut for ``rc.mapper``; ``workers``: processes verifying pairs (None: the CPUs this process may use);
    ``submission``: where ``submission.csv`` goes (a file, or a folder: ``<folder>/submission.csv``; None: a folder
    per configuration under the cache); ``progress``: tqdm bars."""

    name = "reconstruction"
    uses: tuple[str, ...] = ("ratio", "strategy", "threshold", "max_iters", "min_confidence", "min_inliers", "min_model_size",
            "max_num_models", "init_min_num_inliers", "abs_pose_min_num_inliers", "abs_pose_max_error",
            "filter_max_reproj_error", "global_max_rotation_error", "global_max_angular_error")
    summary_keys = RECON_KEYS
    std_keys = ("score", "mAA", "clusterness")
    columns = ("score", "mAA", "clusterness", "registered", "clusters", "pairs", "NI", "map_seconds")
    objective = "score"
    space_file = "reconstruction.yaml"
    records_key = "dataset_records"
    note = ("IMC 2025 score = harmonic mean of camera-centre mAA and clusterness, per dataset; registered: fraction "
            "of the dataset's scene images registered")
    timed = True
    unit, unit_one = "datasets", "dataset"
    units_label = "IMC reconstruction datasets"
    pipeline_defaults = NEW_DEFAULTS
    default_reference = "colmap"
    #: the defaults are measured (docs/reconstruction.md): 8 random draws of nine parameters rarely reach them
    start_at_defaults = True
    #: a 30-trial study's best led the defaults at its own seed only (benchmarks/reconstruction_noise.py): confirm
    #: the three best and the defaults at more seeds before freezing (docs/reconstruction.md)
    confirm_default = 3
    in_both = False  # IMC datasets only: `--task both` (the paper's scenes) leaves it out
    test_figures = "IMC 2025 score (harmonic mean of mAA and clusterness) of the test datasets, mean over runs"

    @classmethod
    def intervals(cls, records: list[dict], **kw) -> dict:
        return {"method": WHY_NO_CI}

    @classmethod
    def paired(cls, records_a: list[dict], records_b: list[dict], **kw) -> dict:
        by = {r["dataset"]: r for r in records_b}
        diffs = {r["dataset"]: by[r["dataset"]]["score"] - r["score"] for r in records_a if r["dataset"] in by}
        return {"difference": float(np.mean(list(diffs.values()))) if diffs else None, "datasets": diffs,
                "method": WHY_NO_CI}

    def __init__(self, rc: ReconstructionConfig | dict | None = None, mapper: str | None = None,
                 workers: int | None = None, submission: str | Path | None = None, progress: bool = False,
                 pipeline: str | None = None, verifier: str | None = None, two_view: str | None = None,
                 shortlist: int | None = None, trial_timeout: float | None = None):
        if isinstance(rc, dict):
            unknown = sorted(set(rc) - {f.name for f in dataclasses.fields(ReconstructionConfig)})
            if unknown:
                raise ImtuneError(f"unknown reconstruction option(s) {', '.join(unknown)}")
            rc = ReconstructionConfig(**rc)
        rc = rc or ReconstructionConfig()
        given: dict = {"mapper": mapper, "pipeline": pipeline, "verifier": verifier, "two_view": two_view,
                       "shortlist": shortlist}
        rc = dataclasses.replace(rc, **{k: v for k, v in given.items() if v is not None})
        self.rc = rc
        self._kept: dict = {}  # verified pairs by key (:meth:`_verified`)
        self.workers = workers
        self.submission = submission
        self.progress = progress
        if trial_timeout is not None and not (isinstance(trial_timeout, (int, float)) and math.isfinite(trial_timeout)
                                              and trial_timeout > 0):
            raise ImtuneError(f"trial timeout {trial_timeout!r}: expected a number of seconds > 0")
        #: a bound on the wall seconds of one evaluation's mapping, all its datasets together (a study's trials:
        #: ``--trial-timeout``); beyond it the mapper is stopped and :class:`EvaluationStopped` raised. Not passed on
        #: by :meth:`for_run` / :meth:`reference_task`: a test run measures the frozen settings whatever they take
        self.trial_timeout = None if trial_timeout is None else float(trial_timeout)
        # each mapper reads its own options (_mapper_options): a study searches and records only those of its mapper,
        # from its mapper's search space (the incremental thresholds were inert, searched, in a global study)
        skip = INCREMENTAL_ONLY if rc.mapper == "global" else GLOBAL_ONLY
        self.uses = tuple(p for p in type(self).uses if p not in skip)
        self.space_file = "reconstruction-global.yaml" if rc.mapper == "global" else type(self).space_file

    def options(self) -> dict:
        return dataclasses.asdict(self.rc)

    @classmethod
    def from_options(cls, options: dict | None, **extra) -> ReconstructionTask:
        return super().from_options({"rc": dict(options)} if options else None, **extra)

    def evaluation_units(self, scene: Scene) -> list:
        return list(scene.pairs)

    def check_scene(self, scene: Scene) -> str | None:
        if not scene.groups:
            return ("not an IMC 2024/2025 dataset (no scene labels): the reconstruction task needs train_labels.csv "
                    "and train_thresholds.csv (see `tune data to-imc` to write posed scenes in that layout)")
        sizes: dict[str, int] = {}
        for g in scene.groups.values():
            if g != OUTLIERS:
                sizes[g] = sizes.get(g, 0) + 1
        if len(scene.images) < 2 or not sizes:
            return f"nothing for the reconstruction task to evaluate ({len(scene.images)} image(s), scenes: {sizes})"
        if self.rc.intrinsics != "colmap":
            missing = [n for n, im in scene.images.items() if im.K is None and scene.groups.get(n) != OUTLIERS]
            if missing:
                return f"intrinsics {self.rc.intrinsics!r} need known K (none for {missing[0]}; IMC 2025 gives none)"
        return None

    def scene_notes(self, scene: Scene) -> list[str]:
        notes = []
        if scene.excluded:
            notes.append(f"dataset {scene.name}: {len(scene.excluded)} image file(s) in no label row left out "
                         f"(e.g. {scene.excluded[0]})")
        groups = scene.groups or {}
        small = sorted({g for g in groups.values() if g != OUTLIERS and list(groups.values()).count(g) <= 3})
        for g in small:
            notes.append(f"dataset {scene.name}: scene {g} has 3 images or fewer: the challenge deducts 3 cameras, so "
                         "it adds nothing to the mAA's numerator")
        return notes

    def budget_seconds(self, summary: dict) -> float | None:
        return summary.get("ransac_seconds_median")

    references = ("colmap", "imc2025-baseline")

    def reference_task(self, kind: str = "colmap") -> ReconstructionTask:
        """The same task on a named reference pipeline: ``kind`` "colmap", COLMAP's own pipeline
        (:func:`reference_database`, :func:`reference_mapper_options`), or "imc2025-baseline", the IMC 2025
        baseline (:func:`baseline_config`, :func:`baseline_verification_options`, the same mapper)."""
        if kind not in self.references:
            raise ImtuneError(f"unknown reference pipeline {kind!r} (choose {', '.join(self.references)})")
        return ReconstructionTask(dataclasses.replace(self.rc, pipeline=kind, mapper="incremental"),
                                  workers=self.workers, submission=self.submission, progress=self.progress)

    @classmethod
    def compare_runs(cls, ref_runs: list[dict], runs: list[dict]) -> dict | None:
        """Frozen - reference, score per dataset: the differences d(dataset, k) of run k of each side (the k-th
        seeds), their mean over datasets and runs, a 95% Student t interval over those differences and the two-sided
        one-sample t test's p (scipy). It treats datasets and runs as independent draws; with one dataset the
        interval holds the run-to-run (seed) variation only, and with one run of one dataset there is none."""
        from pipeline.metrics.replicates import one_sample_t
        diffs: dict[str, list[float]] = {}
        for r, f in zip(ref_runs, runs):
            for ds, s in (f.get("scenes") or {}).items():
                rs = (r.get("scenes") or {}).get(ds)
                if rs and s.get("score") is not None and rs.get("score") is not None:
                    diffs.setdefault(ds, []).append(float(s["score"]) - float(rs["score"]))
        d = np.array([x for v in diffs.values() for x in v], float)
        if not len(d):
            return None
        mean, ci, _, p = one_sample_t(d)
        return {"difference": mean, "ci": ci, "p_value": p, "pairs": int(len(d)), "units": "dataset runs",
                "datasets": {k: float(np.mean(v)) for k, v in diffs.items()},
                "method": "score(frozen) - score(reference) per dataset and run (the k-th seeds of both); 95% "
                          "Student t interval and one-sample t test over those differences"}

    def for_run(self, conf: PipelineConfig, k: int):
        """COLMAP's seed and the estimator's vary across repeated runs."""
        from pipeline.config import run_seed
        t = ReconstructionTask(dataclasses.replace(self.rc, seed=run_seed(self.rc.seed, k)), workers=self.workers,
                               submission=self.submission, progress=self.progress)
        t._kept = self._kept  # the estimator's seed is in the key: a run reuses only what it would recompute
        return t, Task.for_run(self, conf, k)[1]  # the estimator's seed too

    def pairs_of(self, scene: Scene, feats: dict) -> list[tuple[str, str]]:
        names = list(scene.images)
        if self.rc.shortlist == 0 or len(names) <= self.rc.exhaustive_up_to:
            return [(a, b) for k, a in enumerate(names) for b in names[k + 1:]]
        return shortlist_pairs(feats, names, self.rc.shortlist)

    def _submission_path(self, scene: Scene, conf: PipelineConfig, cache: H5Cache, several: bool) -> Path:
        if self.submission is None:
            from pipeline.config import config_hash
            key = config_hash({"conf": conf.to_dict(), "rc": self.options(), "data": scene.name})
            return Path(cache.root) / "submissions" / key / "submission.csv"
        p = Path(self.submission)
        if p.is_dir() or p.suffix.lower() != ".csv":
            return p / (f"{scene.name}/submission.csv" if several else "submission.csv")
        return p.with_name(f"{p.stem}-{scene.name}{p.suffix}") if several else p

    def _verified(self, cache: H5Cache, sc: Scene, feats: dict, conf: PipelineConfig, workers: int) -> tuple:
        """(pairs, verified records, tentative matches or None) of a dataset. Verification by our estimator is kept
        in memory for the last :data:`VERIFIED_KEPT` (dataset, features, matching, estimator, pairs) keys: a trial
        that changes only mapper options (``PipelineConfig.mapper``, the mapper kind, COLMAP's seed) reuses it;
        ``COUNTERS["verify"]`` counts the verifications run."""
        from pipeline.config import config_hash
        key = config_hash({"data": sc.name, "images": list(sc.images), "feature": conf.feature.__dict__,
                           "matching": conf.matching.__dict__, "geometry": conf.geometry.__dict__,
                           "min_inliers": conf.mapper.min_inliers,  # pairs below it are not verified
                           "shortlist": [self.rc.shortlist, self.rc.exhaustive_up_to], "verifier": self.rc.verifier,
                           "pipeline": self.rc.pipeline})
        hit = self._kept.get(key)
        if hit is not None:
            self._kept[key] = self._kept.pop(key)  # most recently used last
            return hit
        names = list(sc.images)
        pairs = self.pairs_of(sc, feats)
        tentative = None
        baseline = self.rc.pipeline == "imc2025-baseline"
        if self.rc.verifier == "colmap" or baseline:  # COLMAP verifies while the database is written (map_dataset)
            from tqdm.auto import tqdm

            from pipeline.tasks.prepare import pair_knn, tentative_matches
            tentative = {}
            for a, b in tqdm(pairs, desc=f"{sc.name}: matching", disable=not self.progress, leave=False):
                tab, _ = pair_knn(cache, feats[a], feats[b], conf.matching)
                m, _ = tentative_matches(tab, conf.matching, feats[a], feats[b], task="multiview")
                tentative[(a, b)] = np.asarray(m, np.int64).reshape(-1, 2)
            # the baseline: a pair with fewer LightGlue matches than the notebook's min_matches is not imported
            few = BASELINE_MIN_MATCHES if baseline else 0
            verified = [{"pair": p, "NM": len(m), "NI": 0, "ransac_seconds": 0.0, "matches": None, "inliers": None,
                         "F": None,
                         "failure": f"fewer than {few} LightGlue matches ({len(m)})" if len(m) < few else None}
                        for p, m in tentative.items()]
            tentative = {p: m for p, m in tentative.items() if len(m) >= few}
        else:
            verified = verify_all(cache, {n: sc.images[n] for n in names}, conf, pairs, workers,
                                  progress=self.progress, desc=f"{sc.name}: pairs")
        COUNTERS["verify"] += 1
        self._kept[key] = (pairs, verified, tentative)
        while len(self._kept) > VERIFIED_KEPT:
            self._kept.pop(next(iter(self._kept)))
        return pairs, verified, tentative

    def _reference_models(self, cache: H5Cache, sc: Scene, conf: PipelineConfig, workers: int, tmp: Path):
        """The COLMAP reference's models of ``sc`` (``rc.pipeline`` "colmap"): its cached database
        (:func:`reference_database`) mapped at :func:`reference_mapper_options`."""
        db_path = reference_database(cache, sc, conf.feature.num_features, max(1, workers))
        local = tmp / "database.db"
        shutil.copyfile(db_path, local)
        from pipeline import colmap_db as cdb
        cdb.quiet(3)
        opts = reference_mapper_options(max(1, workers), self.rc.seed)
        return run_mapper(tmp, local, opts, "incremental", REFERENCE_MIN_MODEL_SIZE)

    def evaluate(self, scenes: list[Scene], conf: PipelineConfig, cache: H5Cache | None = None,
                 on_step=None) -> TaskResult:
        from tqdm.auto import tqdm

        from pipeline import colmap_db as cdb
        from pipeline.cpus import available_cpus
        from pipeline.geometry import get_estimator
        from pipeline.tasks.prepare import image_features
        cache = cache if cache is not None else H5Cache()
        reference = self.rc.pipeline == "colmap"
        if self.rc.pipeline == "imc2025-baseline":  # its own features and matcher, whatever conf says
            conf = baseline_config(conf)
            from pipeline.matching.learned import get_learned_matcher
            get_learned_matcher(conf.matching.method, conf.matching.matcher_options)  # no weights: one line, now
        elif not reference and self.rc.verifier == "ours":
            get_estimator(conf.geometry.ransac)  # unknown / unavailable: one line, before any work
        for sc in scenes:
            why = self.check_scene(sc)
            if why:
                raise ImtuneError(f"dataset {sc.name}: {why}")
        workers = self.workers if self.workers is not None else available_cpus()
        per: dict[str, dict] = {}
        records: list[dict] = []
        secs = {"features": 0.0, "pairs": 0.0, "mapping": 0.0}
        for idx, sc in enumerate(scenes):
            names = list(sc.images)
            min_size = (REFERENCE_MIN_MODEL_SIZE if reference or self.rc.pipeline == "imc2025-baseline"
                        else conf.mapper.min_model_size)
            tmp = Path(tempfile.mkdtemp(prefix="imtune-rec-"))
            try:
                if reference:
                    t0 = time.perf_counter()
                    pairs, verified = [], []
                    models, failure, map_dt = self._reference_models(cache, sc, conf, workers, tmp)
                    secs["pairs"] += time.perf_counter() - t0 - map_dt
                    secs["mapping"] += map_dt
                else:
                    t0 = time.perf_counter()
                    feats = {n: image_features(cache, sc.images[n], conf.feature)
                             for n in tqdm(names, desc=f"{sc.name}: features", disable=not self.progress,
                                           leave=False)}
                    secs["features"] += time.perf_counter() - t0
                    t0 = time.perf_counter()
                    pairs, verified, tentative = self._verified(cache, sc, feats, conf, workers)
                    secs["pairs"] += time.perf_counter() - t0
                    from pipeline.data.resize import scaled_K
                    images = []
                    for n in names:
                        f, im = feats[n], sc.images[n]
                        K = None if im.K is None else scaled_K(im.K, f.sx, f.sy)
                        images.append((n, cdb.make_camera(f.width, f.height, K, self.rc.intrinsics, im.path),
                                       f.keypoints))
                    left = None if self.trial_timeout is None else self.trial_timeout - secs["mapping"]
                    t0 = time.perf_counter()
                    try:
                        if left is not None and left <= 0:
                            raise MappingTimeout("no time was left for it", 0.0)
                        models, failure, map_dt = map_dataset(tmp, images, verified, conf, self.rc,
                                                              threads=max(1, workers), tentative=tentative,
                                                              timeout=left)
                    except MappingTimeout as e:
                        spent = secs["mapping"] + e.seconds
                        raise EvaluationStopped(
                            f"trial timeout: mapping stopped over the bound of {self.trial_timeout:g} s "
                            f"(--trial-timeout) at dataset {sc.name} ({idx + 1} of {len(scenes)}), after "
                            f"{spent:.1f} s of mapping in all: {e}") from None
                    secs["mapping"] += time.perf_counter() - t0
                clusters = clusters_from_models(models, names, min_size)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            rows = submission_rows(sc.name, names, clusters)
            path = self._submission_path(sc, conf, cache, len(scenes) > 1)
            write_submission(path, rows)
            result = score_rows(sc, rows)
            rs = [r["ransac_seconds"] for r in verified]
            scene_imgs = [n for n in names if (sc.groups or {}).get(n) != OUTLIERS]
            registered = {n for c in clusters.values() for n in c}
            summary = {"score": result.score, "mAA": result.mAA, "clusterness": result.clusterness,
                       "registered": (sum(n in registered for n in scene_imgs) / len(scene_imgs)) if scene_imgs else 0.0,
                       "clusters": len(clusters), "pairs": len(pairs) if not reference else len(names) * (len(names) - 1) // 2,
                       "NM": float(np.mean([r["NM"] for r in verified])) if verified else 0.0,
                       "NI": float(np.mean([r["NI"] for r in verified])) if verified else 0.0,
                       "ransac_seconds_median": float(np.median(rs)) if rs else 0.0,
                       "map_seconds": map_dt, "excluded": len(sc.excluded or []),
                       "mapper": "incremental" if reference or self.rc.pipeline != "imtune" else self.rc.mapper, "failure": failure,
                       "submission": str(path),
                       "ground_truth_scenes": {k: v.to_dict() for k, v in result.scenes.items()},
                       "outliers_registered": result.outliers_registered,
                       "pair_failures": sum(1 for r in verified if r["failure"])}
            per[sc.name] = summary
            records.append({"dataset": sc.name, "scene": sc.name, "pair": "the whole dataset",
                            **{k: summary[k] for k in ("score", "mAA", "clusterness", "registered", "clusters",
                                                       "map_seconds", "failure", "submission")},
                            "ransac_seconds": float(np.sum(rs)) if rs else 0.0, "pair_ransac_seconds": rs})
            if on_step is not None:
                on_step(idx, len(scenes), _mean(per))
        summary = _mean(per)
        summary["interval"] = WHY_NO_CI
        if self.rc.pipeline == "imc2025-baseline":  # what ran (its own features and matcher)
            summary["baseline_config"] = conf.to_dict()  # said where the other tasks give "ci"
        return TaskResult(summary=summary, scenes=per, records=records, seconds=secs, records_key=self.records_key)


def _mean(per: dict[str, dict]) -> dict:
    """The challenge's final figures: the mean over datasets (the budget statistic: the median over every pair)."""
    out: dict = {}
    for k in RECON_KEYS:
        vals = [s[k] for s in per.values() if isinstance(s.get(k), (int, float))]
        out[k] = float(np.mean(vals)) if vals else 0.0
    out["datasets"] = len(per)
    return out
