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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.cache import H5Cache
from pipeline.config import PipelineConfig
from pipeline.data.scene import Scene
from pipeline.errors import ImtuneError
from pipeline.metrics.imc_score import OUTLIERS, centre, score_dataset
from pipeline.tasks.base import TASKS, Task, TaskResult

MAPPERS = ("incremental", "global")
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
    shortlist: partners per image matched when the dataset has more than ``exhaustive_up_to`` images (0: all pairs).
    exhaustive_up_to: datasets of at most this many images match every pair.
    intrinsics: "colmap" (EXIF or 1.2 x the long side, refined: IMC 2025 gives none), "prior" or "fixed" (known K:
        IMC 2024's calibration_matrix).
    seed: COLMAP's random seed (vary it across repeated runs).
    """
    mapper: str = "incremental"
    shortlist: int = 10
    exhaustive_up_to: int = 30
    intrinsics: str = "colmap"
    seed: int = 0

    def __post_init__(self):
        from pipeline.colmap_db import INTRINSICS_MODES
        if self.mapper not in MAPPERS:
            raise ImtuneError(f"unknown mapper {self.mapper!r} (choose {', '.join(MAPPERS)})")
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
            if len(m) >= 8:
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
                rec["failure"] = f"fewer than 8 matches ({len(m)})"
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

def _mapper_options(kind: str, conf: PipelineConfig, rc: ReconstructionConfig, threads: int):
    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    mc = conf.mapper
    if kind == "incremental":
        o = cdb.mapper_options(min_model_size=mc.min_model_size, num_threads=threads, seed=rc.seed,
                               fixed_intrinsics=(rc.intrinsics == "fixed"))
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
        if rc.intrinsics == "fixed":
            o.mapper.bundle_adjustment.refine_focal_length = False
            o.mapper.bundle_adjustment.refine_extra_params = False
    o.min_num_matches = int(mc.min_inliers)
    return o


def map_dataset(workdir: Path, images: list, verified: list[dict], conf: PipelineConfig, rc: ReconstructionConfig,
                threads: int = 1) -> tuple[list, str | None, float]:
    """Write the database (cameras, keypoints, tentative matches, our verified inliers as two-view geometries) and
    run the mapper. Returns (reconstructions, failure or None, mapping wall seconds)."""
    from pipeline import colmap_db as cdb
    pycolmap = cdb.import_pycolmap()
    cdb.quiet(3)
    workdir.mkdir(parents=True, exist_ok=True)
    db_path = workdir / "database.db"
    matches = {r["pair"]: r["matches"] for r in verified if r["matches"] is not None}
    ids = cdb.write_database(db_path, images, matches)
    db = pycolmap.Database.open(str(db_path))
    try:
        for r in verified:
            if r["matches"] is None or r["NI"] < conf.mapper.min_inliers:
                continue
            a, b = r["pair"]
            tvg = pycolmap.TwoViewGeometry()
            tvg.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            tvg.F = np.asarray(r["F"], float)
            tvg.inlier_matches = np.ascontiguousarray(r["matches"][r["inliers"]].astype(np.uint32))
            db.write_two_view_geometry(ids[a], ids[b], tvg)
    finally:
        db.close()
    out = workdir / "sparse"
    out.mkdir(parents=True, exist_ok=True)
    opts = _mapper_options(rc.mapper, conf, rc, threads)
    t0 = time.perf_counter()
    try:
        if rc.mapper == "incremental":
            recs = pycolmap.incremental_mapping(str(db_path), str(workdir), str(out), opts)
        else:
            recs = pycolmap.global_mapping(str(db_path), str(workdir), str(out), opts)
    except Exception as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        return [], f"mapper failed: {msg}", time.perf_counter() - t0
    dt = time.perf_counter() - t0
    models = [r for r in (recs or {}).values() if r.num_reg_images() >= conf.mapper.min_model_size]
    models.sort(key=lambda r: -r.num_reg_images())
    return models, (None if models else "the mapper registered no model"), dt


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
    uses = ("ratio", "strategy", "threshold", "max_iters", "min_confidence", "min_inliers", "min_model_size")
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
                 workers: int | None = None, submission: str | Path | None = None, progress: bool = False):
        if isinstance(rc, dict):
            rc = ReconstructionConfig(**rc)
        rc = rc or ReconstructionConfig()
        if mapper is not None:
            rc = dataclasses.replace(rc, mapper=mapper)
        self.rc = rc
        self.workers = workers
        self.submission = submission
        self.progress = progress

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

    def for_run(self, conf: PipelineConfig, k: int):
        """COLMAP's seed and the estimator's vary across repeated runs."""
        from pipeline.config import run_seed
        t = ReconstructionTask(dataclasses.replace(self.rc, seed=run_seed(self.rc.seed, k)), workers=self.workers,
                               submission=self.submission, progress=self.progress)
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

    def evaluate(self, scenes: list[Scene], conf: PipelineConfig, cache: H5Cache | None = None,
                 on_step=None) -> TaskResult:
        from tqdm.auto import tqdm

        from pipeline import colmap_db as cdb
        from pipeline.cpus import available_cpus
        from pipeline.geometry import get_estimator
        from pipeline.tasks.prepare import image_features
        cache = cache if cache is not None else H5Cache()
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
            t0 = time.perf_counter()
            names = list(sc.images)
            feats = {n: image_features(cache, sc.images[n], conf.feature)
                     for n in tqdm(names, desc=f"{sc.name}: features", disable=not self.progress, leave=False)}
            secs["features"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            pairs = self.pairs_of(sc, feats)
            verified = verify_all(cache, {n: sc.images[n] for n in names}, conf, pairs, workers,
                                  progress=self.progress, desc=f"{sc.name}: pairs")
            secs["pairs"] += time.perf_counter() - t0
            from pipeline.data.resize import scaled_K
            images = []
            for n in names:
                f, im = feats[n], sc.images[n]
                K = None if im.K is None else scaled_K(im.K, f.sx, f.sy)
                images.append((n, cdb.make_camera(f.width, f.height, K, self.rc.intrinsics, im.path), f.keypoints))
            tmp = Path(tempfile.mkdtemp(prefix="imtune-rec-"))
            t0 = time.perf_counter()
            try:
                models, failure, map_dt = map_dataset(tmp, images, verified, conf, self.rc, threads=max(1, workers))
                clusters = clusters_from_models(models, names, conf.mapper.min_model_size)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            secs["mapping"] += time.perf_counter() - t0
            rows = submission_rows(sc.name, names, clusters)
            path = self._submission_path(sc, conf, cache, len(scenes) > 1)
            write_submission(path, rows)
            result = score_rows(sc, rows)
            rs = [r["ransac_seconds"] for r in verified]
            scene_imgs = [n for n in names if (sc.groups or {}).get(n) != OUTLIERS]
            registered = {n for c in clusters.values() for n in c}
            summary = {"score": result.score, "mAA": result.mAA, "clusterness": result.clusterness,
                       "registered": (sum(n in registered for n in scene_imgs) / len(scene_imgs)) if scene_imgs else 0.0,
                       "clusters": len(clusters), "pairs": len(pairs),
                       "NM": float(np.mean([r["NM"] for r in verified])) if verified else 0.0,
                       "NI": float(np.mean([r["NI"] for r in verified])) if verified else 0.0,
                       "ransac_seconds_median": float(np.median(rs)) if rs else 0.0,
                       "map_seconds": map_dt, "excluded": len(sc.excluded or []),
                       "mapper": self.rc.mapper, "failure": failure, "submission": str(path),
                       "ground_truth_scenes": {k: v.to_dict() for k, v in result.scenes.items()},
                       "outliers_registered": result.outliers_registered,
                       "pair_failures": sum(1 for r in verified if r["failure"])}
            per[sc.name] = summary
            records.append({"dataset": sc.name, "scene": sc.name, "pair": "the whole dataset", **{k: summary[k] for k in ("score", "mAA", "clusterness", "registered",
                                                                           "clusters", "map_seconds", "failure",
                                                                           "submission")},
                            "ransac_seconds": float(np.sum(rs)), "pair_ransac_seconds": rs})
            if on_step is not None:
                on_step(idx, len(scenes), _mean(per))
        summary = _mean(per)
        summary["interval"] = WHY_NO_CI  # said where the other tasks give "ci"
        return TaskResult(summary=summary, scenes=per, records=records, seconds=secs, records_key=self.records_key)


def _mean(per: dict[str, dict]) -> dict:
    """The challenge's final figures: the mean over datasets (the budget statistic: the median over every pair)."""
    out: dict = {}
    for k in RECON_KEYS:
        vals = [s[k] for s in per.values() if isinstance(s.get(k), (int, float))]
        out[k] = float(np.mean(vals)) if vals else 0.0
    out["datasets"] = len(per)
    return out
