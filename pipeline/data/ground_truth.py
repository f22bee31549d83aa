"""Ground-truth building: 3D points (hence co-visibility and bags) from known poses, or a whole pseudo
ground truth from an image folder, both with pycolmap; stored in a data cache outside the repository.

- From known poses (Strecha, IMC-PT, any loader with K, R, t): COLMAP SIFT on every image, exhaustive
  matching with COLMAP's geometric verification, then ``pycolmap.triangulate_points`` with the cameras
  and poses held fixed. The points' reprojection error through the known cameras is recorded (median
  and percentiles, px): it checks the poses and the triangulation agree.
- From an image folder (no poses): COLMAP SIFT, exhaustive matching and incremental mapping on the full
  set, as the paper builds its pseudo ground truth; the model with the most registered images becomes
  the scene; unregistered images are dropped (and listed). Cameras default to SIMPLE_PINHOLE so that the
  ground truth is exactly representable by the Scene model (K only, no distortion).

Storage: ``<gt_dir>/<scene name>-<content id>/gt.h5`` where ``gt_dir`` is ``$IMTUNE_GT``, else
``$IMTUNE_CACHE/gt``, else ``~/.cache/imtune/gt``, and the content id hashes the scene's image names and file sizes (a moved copy
of the data finds it; edited images do not). Arrays only, written atomically, checksummed.

    gt = build_ground_truth(scene)            # writes the file, returns GroundTruth
    attach_ground_truth(scene)                # a loaded scene gains points, observations, co-visibility
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError

GT_FILE = "gt.h5"
GT_VERSION = "1"
METHODS = ("auto", "poses", "sfm")


def default_gt_dir() -> Path:
    """``$IMTUNE_GT``, else ``$IMTUNE_CACHE/gt``, else ``~/.cache/imtune/gt``."""
    if os.environ.get("IMTUNE_GT"):
        return Path(os.environ["IMTUNE_GT"]).expanduser()
    from pipeline.cache import default_cache_dir
    return default_cache_dir() / "gt"


def scene_content_id(scene) -> str:
    """Hash of the scene's image names and file sizes (stable across copies of the data folder)."""
    h = hashlib.sha1()
    for n in sorted(scene.images):
        p = scene.images[n].path
        try:
            size = os.stat(p).st_size
        except OSError:
            size = -1
        h.update(f"{n}\0{size}\n".encode())
    return h.hexdigest()[:12]


def gt_path(scene, gt_dir: Path | str | None = None) -> Path:
    """Where the ground truth of ``scene`` lives (whether or not it exists): keyed by its name, images and, when it has
    any, its own ground truth as loaded (``Scene.truth_id``): a scene of the same name and images in another format or
    with other poses (a pairs list of a Strecha scene, a corrected camera file) has its own, never the other's."""
    root = Path(gt_dir).expanduser() if gt_dir is not None else default_gt_dir()
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in scene.name)
    truth = scene.truth_id if scene.truth_id is not None else scene.truth_digest()
    return root / (f"{safe}-{scene_content_id(scene)}" + (f"-{truth}" if truth else "")) / GT_FILE


@dataclass(frozen=True)
class GTConfig:
    """How ground truth is built.

    method: "poses" (triangulate with known poses), "sfm" (reconstruct from images), "auto" (poses when
        every image has K, R, t, else sfm).
    num_features: COLMAP SIFT keypoints per image.
    max_image_size: COLMAP resizes larger images for extraction (keypoints are reported at full size).
    camera_model: COLMAP camera model for "sfm" (SIMPLE_PINHOLE keeps the model exact for the Scene).
    max_ratio: SIFT ratio test of COLMAP's matcher.
    max_reprojection_error: points with a larger reprojection error (px) are dropped by COLMAP.
    num_threads: threads for COLMAP (-1 = all).
    bags: bag spec for the bags stored with the ground truth (for inspection; tasks sample their own).
    min_points: visibility requirement of those bags.
    seed: random seed (COLMAP and bags).
    """
    method: str = "auto"
    num_features: int = 8192
    max_image_size: int = 3200
    camera_model: str = "SIMPLE_PINHOLE"
    max_ratio: float = 0.8
    max_reprojection_error: float = 4.0
    num_threads: int = -1
    bags: tuple = ((5, 100), (10, 50), (25, 25))
    min_points: int = 100
    seed: int = 0

    def __post_init__(self):
        if self.method not in METHODS:
            raise ImtuneError(f"unknown ground-truth method {self.method!r} (choose {', '.join(METHODS)})")
        if self.num_features < 16:
            raise ImtuneError(f"num_features must be >= 16, got {self.num_features}")
        if isinstance(self.max_image_size, bool) or not isinstance(self.max_image_size, int) \
                or self.max_image_size < 1:
            raise ImtuneError(f"max_image_size (COLMAP's extraction size, px) must be a positive integer, "
                              f"got {self.max_image_size!r}")
        models = camera_models()
        if models and self.camera_model not in models:
            from pipeline.registry import did_you_mean
            raise ImtuneError(f"unknown COLMAP camera model {self.camera_model!r}"
                              f"{did_you_mean(str(self.camera_model), models)} (choose from {', '.join(models)})")


def camera_models() -> list[str]:
    """The camera model names of the installed pycolmap (``pycolmap.CameraModelId``, without INVALID), in COLMAP's
    order; [] when pycolmap is missing (building ground truth then says so itself)."""
    from pipeline.colmap_db import import_pycolmap
    try:
        pycolmap = import_pycolmap()  # never a bare import: it would hand SIGTERM to glog (see import_pycolmap)
    except ImportError:
        return []
    ids = getattr(pycolmap, "CameraModelId", None)
    members = getattr(ids, "__members__", {}) if ids is not None else {}
    return [n for n in members if n != "INVALID"]


@dataclass
class GroundTruth:
    """Built ground truth of one scene.

    names: images kept (registered); K (n,3,3), R (n,3,3), t (n,3), sizes (n,2) on disk px (pixel-centre
    convention); points3d (P,3); observations: name -> (point ids, xy px on disk); covisibility (n,n);
    bags: size -> list of name tuples; meta: method, counts, reprojection statistics, dropped images, seconds."""
    scene: str
    method: str
    names: list[str]
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    sizes: np.ndarray
    points3d: np.ndarray
    observations: dict[str, tuple[np.ndarray, np.ndarray]]
    covisibility: np.ndarray
    bags: dict[int, list[tuple[str, ...]]] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------ building

class _colmap_step:
    """``with _colmap_step(scene, "feature extraction", work):`` turns an exception from pycolmap (or the file system
    under it) into the scene's one-line ImtuneError naming the step and the cause: a RuntimeError from COLMAP (its
    database could not be written: a full disk) went up as a traceback that stopped `tune data build-gt` before the
    other scenes. ImtuneError passes through unchanged."""

    def __init__(self, scene, what: str, work: Path):
        self.scene, self.what, self.work = scene, what, work

    def __enter__(self):
        return self

    def __exit__(self, kind, e, tb):
        if e is None or isinstance(e, ImtuneError) or not isinstance(e, Exception):
            return False
        cause = " ".join(str(e).split()) or "no message"
        raise ImtuneError(f"scene {self.scene.name}: COLMAP {self.what} failed ({type(e).__name__}: {cause[:200]}); "
                          f"check that its images are readable and that the work folder {self.work.parent} has free "
                          "space (TMPDIR chooses another)") from None


def _image_root(scene) -> tuple[Path, dict[str, str]]:
    """A folder holding every image of the scene and name -> path relative to it (COLMAP image names); each image
    is checked whole first (ImtuneError naming the scene and the file)."""
    from pipeline.data.imagefile import check_image_bytes, check_jpeg_decode
    paths = {n: Path(info.path).resolve() for n, info in scene.images.items()}
    for p in paths.values():
        if not p.is_file():
            raise ImtuneError(f"scene {scene.name}: image not found: {p}")
        # COLMAP decodes a damaged JPEG without a word (a middle overwritten, a cut with an end marker appended):
        # the same checks as the pair path's (pipeline.data.resize.load_image), before COLMAP reads the file
        try:
            data = p.read_bytes()
            check_image_bytes(p, data)
            check_jpeg_decode(p, data)
        except ImtuneError as e:
            raise ImtuneError(f"scene {scene.name}: {e}") from None
        except OSError as e:
            raise ImtuneError(f"scene {scene.name}: cannot read image {p}: {e.strerror or e}") from None
    root = Path(os.path.commonpath([str(p.parent) for p in paths.values()]))
    return root, {n: str(p.relative_to(root)) for n, p in paths.items()}


def _extract_and_match(scene, conf: GTConfig, work: Path, known_K: bool, progress) -> tuple[Path, dict[str, int], Path, dict]:
    from pipeline.colmap_db import import_pycolmap
    pycolmap = import_pycolmap()

    from pipeline.colmap_db import PIXEL_OFFSET
    img_root, rel = _image_root(scene)
    db = work / "database.db"
    eo = pycolmap.FeatureExtractionOptions()
    eo.sift.max_num_features = int(conf.num_features)
    eo.max_image_size = int(conf.max_image_size)
    eo.num_threads = int(conf.num_threads)
    ro = pycolmap.ImageReaderOptions()
    ro.camera_model = "PINHOLE" if known_K else conf.camera_model
    t0 = time.perf_counter()
    progress(f"extracting SIFT on {len(rel)} images")
    with _colmap_step(scene, "feature extraction", work):
        pycolmap.extract_features(str(db), str(img_root), sorted(rel.values()), pycolmap.CameraMode.PER_IMAGE, ro,
                                  eo, pycolmap.Device.cpu)
    secs = {"extract": time.perf_counter() - t0}
    back = {v: k for k, v in rel.items()}
    ids: dict[str, int] = {}
    with _colmap_step(scene, "database reading", work):
        d = pycolmap.Database.open(str(db))
    try:
        with _colmap_step(scene, "database reading", work):
            images = d.read_all_images()
        for im in images:
            if im.name not in back:
                continue
            name = back[im.name]
            ids[name] = im.image_id
            if known_K:
                cam = d.read_camera(im.camera_id)
                K = np.asarray(scene.images[name].K, float)
                w, h = scene.images[name].size or (cam.width, cam.height)
                if (cam.width, cam.height) != (w, h):
                    raise ImtuneError(f"scene {scene.name}: image {name} is {cam.width}x{cam.height} px on disk but "
                                      f"its intrinsics are for {w}x{h}")
                cam.params = [K[0, 0], K[1, 1], K[0, 2] + PIXEL_OFFSET, K[1, 2] + PIXEL_OFFSET]
                cam.has_prior_focal_length = True
                with _colmap_step(scene, "database writing", work):
                    d.update_camera(cam)
    finally:
        d.close()
    missing = sorted(set(rel) - set(ids))
    if missing:
        raise ImtuneError(f"scene {scene.name}: COLMAP could not read image {scene.images[missing[0]].path}")
    t0 = time.perf_counter()
    progress(f"matching {len(ids) * (len(ids) - 1) // 2} pairs (exhaustive)")
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = int(conf.num_threads)
    mo.sift.max_ratio = float(conf.max_ratio)
    vo = pycolmap.TwoViewGeometryOptions()
    vo.ransac.random_seed = int(conf.seed)
    with _colmap_step(scene, "exhaustive matching", work):
        pycolmap.match_exhaustive(str(db), mo, pycolmap.ExhaustivePairingOptions(), vo, pycolmap.Device.cpu)
    secs["match"] = time.perf_counter() - t0
    return db, ids, img_root, secs


def _points_from_model(rec, id_to_name: dict[int, str]):
    """points3d (P, 3), observations name -> (ids, xy px pixel-centre), from a pycolmap Reconstruction."""
    from pipeline.colmap_db import PIXEL_OFFSET
    pids = sorted(rec.point3D_ids())
    index = {p: k for k, p in enumerate(pids)}
    pts = np.array([rec.point3D(p).xyz for p in pids], float).reshape(-1, 3)
    obs: dict[str, tuple[list, list]] = {n: ([], []) for n in id_to_name.values()}
    for p in pids:
        for el in rec.point3D(p).track.elements:
            name = id_to_name.get(el.image_id)
            if name is None:
                continue
            xy = np.asarray(rec.image(el.image_id).points2D[el.point2D_idx].xy, float) - PIXEL_OFFSET
            obs[name][0].append(index[p])
            obs[name][1].append(xy)
    return pts, {n: (np.asarray(a, np.int64), np.asarray(b, float).reshape(-1, 2)) for n, (a, b) in obs.items()}


def reprojection_errors(points3d: np.ndarray, observations: dict, K: dict, R: dict, t: dict) -> np.ndarray:
    """Distances (px) between every observation and its point projected through the given camera."""
    out = []
    for n, (ids, xy) in observations.items():
        if len(ids) == 0:
            continue
        Xc = (np.asarray(R[n], float) @ points3d[ids].T).T + np.asarray(t[n], float).reshape(1, 3)
        x = (np.asarray(K[n], float) @ Xc.T).T
        with np.errstate(divide="ignore", invalid="ignore"):
            p = x[:, :2] / x[:, 2:3]
        d = np.linalg.norm(p - xy, axis=1)
        d[~np.isfinite(d)] = np.inf
        out.append(d)
    return np.concatenate(out) if out else np.zeros(0)


def _reproj_stats(e: np.ndarray) -> dict:
    if e.size == 0:
        return {"observations": 0}
    return {"observations": int(e.size), "median_px": float(np.median(e)), "mean_px": float(np.mean(e[np.isfinite(e)])),
            "p90_px": float(np.percentile(e, 90)), "p99_px": float(np.percentile(e, 99))}


def check_poses_scene(scene) -> None:
    """ImtuneError when triangulating with known poses cannot give ``scene`` a ground truth: fewer than 3 images
    (COLMAP's triangulator keeps no point seen in only two images; the empty ground truth it gave had co-visibility
    0 for the one pair, which hid it from every stereo evaluation)."""
    if len(scene.images) < 3:
        raise ImtuneError(f"scene {scene.name}: ground truth from known poses needs at least 3 images, it has "
                          f"{len(scene.images)} (COLMAP triangulates no point seen in only two images); without it "
                          "its pairs are evaluated as listed (co-visibility unknown): leave it out with --scenes")


def build_from_poses(scene, conf: GTConfig = GTConfig(), work: Path | None = None, progress=None) -> GroundTruth:
    """Triangulate 3D points of a scene with known K, R, t (held fixed); see the module docstring."""
    from pipeline.colmap_db import import_pycolmap
    pycolmap = import_pycolmap()

    from pipeline.colmap_db import quiet
    progress = progress or (lambda msg: None)
    bad = [n for n, i in scene.images.items() if i.K is None or i.R is None or i.t is None]
    if bad:
        raise ImtuneError(f"scene {scene.name}: image {bad[0]} has no known pose/intrinsics "
                          f"(use method 'sfm' to reconstruct from the images)")
    check_poses_scene(scene)
    quiet(3)  # our own one-line errors say why a build failed
    own = work is None
    work = Path(tempfile.mkdtemp(prefix="imtune-gt-")) if work is None else Path(work)
    try:
        db, ids, img_root, secs = _extract_and_match(scene, conf, work, known_K=True, progress=progress)
        rec = pycolmap.Reconstruction()
        with _colmap_step(scene, "database reading", work):
            d = pycolmap.Database.open(str(db))
        try:
            for name, iid in ids.items():
                with _colmap_step(scene, "database reading", work):
                    im = d.read_image(iid)
                    cam = d.read_camera(im.camera_id)
                rec.add_camera_with_trivial_rig(cam)
                info = scene.images[name]
                pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(info.R, float)), np.asarray(info.t, float).reshape(3))
                rec.add_image_with_trivial_frame(pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=iid), pose)
        finally:
            d.close()
        progress("triangulating with the known poses")
        t0 = time.perf_counter()
        o = pycolmap.IncrementalPipelineOptions()
        o.extract_colors = False
        o.num_threads = int(conf.num_threads)
        o.mapper.filter_max_reproj_error = float(conf.max_reprojection_error)
        (work / "model").mkdir(exist_ok=True)
        try:
            tri = pycolmap.triangulate_points(rec, str(db), str(img_root), str(work / "model"), True, o, False)
        except Exception as e:
            raise ImtuneError(f"scene {scene.name}: triangulation failed: {' '.join(str(e).split())}") from None
        secs["triangulate"] = time.perf_counter() - t0
        id_to_name = {iid: n for n, iid in ids.items()}
        pts, obs = _points_from_model(tri, id_to_name)
        names = list(scene.images)
        K = {n: np.asarray(scene.images[n].K, float) for n in names}
        R = {n: np.asarray(scene.images[n].R, float) for n in names}
        t = {n: np.asarray(scene.images[n].t, float).reshape(3) for n in names}
        if not len(pts):  # written, it hid every pair of the scene (co-visibility 0) from the stereo task
            raise ImtuneError(f"scene {scene.name}: triangulating with the known poses gave no 3D point (too few "
                              "matches seen in 3 or more of its images): no ground truth written")
        err = reprojection_errors(pts, obs, K, R, t)
        meta = {"reprojection": _reproj_stats(err), "seconds": secs, "registered": len(names), "dropped": [],
                "points": int(len(pts))}
        return _finish(scene, "poses", names, K, R, t, pts, obs, conf, meta)
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)


def build_from_images(scene, conf: GTConfig = GTConfig(), work: Path | None = None, progress=None) -> GroundTruth:
    """Pseudo ground truth by SfM on the scene's images (exhaustive matching); see the module docstring."""
    from pipeline.colmap_db import import_pycolmap
    pycolmap = import_pycolmap()

    from pipeline.colmap_db import K_from_camera, largest_model, quiet
    progress = progress or (lambda msg: None)
    if len(scene.images) < 2:
        raise ImtuneError(f"scene {scene.name}: needs at least 2 usable images for SfM, has {len(scene.images)}")
    quiet(3)  # our own one-line errors say why a build failed
    own = work is None
    work = Path(tempfile.mkdtemp(prefix="imtune-gt-")) if work is None else Path(work)
    try:
        db, ids, img_root, secs = _extract_and_match(scene, conf, work, known_K=False, progress=progress)
        progress("incremental mapping")
        t0 = time.perf_counter()
        o = pycolmap.IncrementalPipelineOptions()
        o.extract_colors = False
        o.num_threads = int(conf.num_threads)
        o.random_seed = int(conf.seed)
        o.min_model_size = 2
        o.mapper.filter_max_reproj_error = float(conf.max_reprojection_error)
        try:
            recs = pycolmap.incremental_mapping(str(db), str(img_root), str(work / "sparse"), o)
        except Exception as e:
            raise ImtuneError(f"scene {scene.name}: SfM failed: {' '.join(str(e).split())}") from None
        secs["map"] = time.perf_counter() - t0
        model = largest_model(recs or {})
        if model is None or model.num_reg_images() < 2:
            raise ImtuneError(f"scene {scene.name}: SfM registered fewer than 2 images "
                              f"({len(scene.images)} images; too few matches between them): no ground truth written; "
                              "add overlapping views of the scene, or leave it out with --scenes")
        id_to_name = {}
        rel_to_name = {}
        for name, iid in ids.items():
            rel_to_name[iid] = name
        K, R, t = {}, {}, {}
        for iid in model.reg_image_ids():
            im = model.image(iid)
            name = rel_to_name[iid]
            T = np.asarray(im.cam_from_world().matrix(), float)
            K[name] = K_from_camera(model.camera(im.camera_id))
            R[name], t[name] = T[:, :3], T[:, 3]
            id_to_name[iid] = name
        names = [n for n in scene.images if n in id_to_name.values()]
        dropped = [n for n in scene.images if n not in names]
        pts, obs = _points_from_model(model, id_to_name)
        err = reprojection_errors(pts, obs, K, R, t)
        meta = {"reprojection": _reproj_stats(err), "seconds": secs, "registered": len(names), "dropped": dropped,
                "points": int(len(pts)), "models": len(recs or {}),
                "camera_model": conf.camera_model}
        return _finish(scene, "sfm", names, K, R, t, pts, obs, conf, meta)
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)


def _finish(scene, method, names, K, R, t, pts, obs, conf: GTConfig, meta) -> GroundTruth:
    from pipeline.data.bags import sample_bags
    from pipeline.metrics.covisibility import covisibility
    sizes = np.array([scene.images[n].size or (0, 0) for n in names], np.int64).reshape(-1, 2)
    n = len(names)
    C = np.eye(n)
    for a in range(n):
        for b in range(a + 1, n):
            oa, ob = obs[names[a]], obs[names[b]]
            C[a, b] = C[b, a] = covisibility(oa[0], oa[1], tuple(sizes[a]), ob[0], ob[1], tuple(sizes[b]))
    bags = sample_bags(names, {x: obs[x][0] for x in names}, dict(conf.bags), conf.min_points, conf.seed)
    iu = np.triu_indices(n, 1)
    cv = C[iu]
    meta.update({"version": GT_VERSION, "config": asdict(conf),
                 "pairs": int(len(cv)), "pairs_covisible_0.1": int((cv >= 0.1).sum()),
                 "bags": {str(k): len(v) for k, v in bags.items()}})
    return GroundTruth(scene=scene.name, method=method, names=list(names),
                       K=np.stack([K[x] for x in names]) if n else np.zeros((0, 3, 3)),
                       R=np.stack([R[x] for x in names]) if n else np.zeros((0, 3, 3)),
                       t=np.stack([np.asarray(t[x], float).reshape(3) for x in names]) if n else np.zeros((0, 3)),
                       sizes=sizes, points3d=pts, observations={x: obs[x] for x in names},
                       covisibility=C, bags=bags, meta=meta)


def choose_method(scene, method: str = "auto") -> str:
    if method != "auto":
        return method
    known = all(i.K is not None and i.R is not None and i.t is not None for i in scene.images.values())
    return "poses" if known else "sfm"


def build_ground_truth(scene, gt_dir: Path | str | None = None, conf: GTConfig = GTConfig(), force: bool = False,
                       progress=None) -> tuple[GroundTruth, Path]:
    """Build (or, unless ``force``, reuse) the ground truth of ``scene`` and store it; (gt, path)."""
    path = gt_path(scene, gt_dir)
    err = _not_a_file(path)  # before the build (SfM may take hours), not when it is written
    if err is not None:
        raise err
    method = choose_method(scene, conf.method)
    if path.is_file() and not force:
        try:
            gt = load_ground_truth(path)
            want = json.loads(json.dumps(dict(asdict(conf), method="-")))
            same = dict(gt.meta.get("config", {}), method="-") == want
            if same and gt.method == method:
                return gt, path
        except ImtuneError:
            pass  # corrupt: rebuild
    builder = build_from_poses if method == "poses" else build_from_images
    gt = builder(scene, conf, progress=progress)
    save_ground_truth(gt, path)
    return gt, path


# ------------------------------------------------------------------------------------------ storage

def save_ground_truth(gt: GroundTruth, path: Path | str) -> Path:
    """Write ``gt`` to an h5 file atomically (temp name, fsync, rename) with a checksum."""
    from pipeline.fileio import arrays_checksum, atomic_write_h5
    path = Path(path)
    arrays = {"K": gt.K, "R": gt.R, "t": gt.t, "sizes": gt.sizes, "points3d": gt.points3d,
              "covisibility": gt.covisibility}
    for k, n in enumerate(gt.names):
        ids, xy = gt.observations[n]
        arrays[f"obs/{k}/ids"] = np.asarray(ids, np.int64)
        arrays[f"obs/{k}/xy"] = np.asarray(xy, float).reshape(-1, 2)
    for size, bags in gt.bags.items():
        idx = {n: k for k, n in enumerate(gt.names)}
        arrays[f"bags/{size}"] = np.array([[idx[n] for n in b] for b in bags], np.int64).reshape(-1, size)
    attrs = {"names": json.dumps(gt.names), "scene": gt.scene, "method": gt.method, "meta": json.dumps(gt.meta),
             "sha1": arrays_checksum(arrays)}
    return atomic_write_h5(path, arrays, attrs)


def load_ground_truth(path: Path | str) -> GroundTruth:
    """Read a ground-truth file; ImtuneError naming it when missing, unreadable or corrupt."""
    import h5py

    from pipeline.cache import _checksum
    path = Path(path)
    if not path.is_file():
        raise ImtuneError(f"ground truth not found: {path}")
    try:
        with h5py.File(path, "r") as f:
            arrays: dict[str, np.ndarray] = {}
            f.visititems(lambda k, v: arrays.__setitem__(k, v[()]) if isinstance(v, h5py.Dataset) else None)
            names = json.loads(f.attrs["names"])
            scene = str(f.attrs["scene"])
            method = str(f.attrs["method"])
            meta = json.loads(f.attrs["meta"])
            sha = f.attrs["sha1"]
        sha = sha.decode() if isinstance(sha, bytes) else sha
        if _checksum(arrays) != sha:
            raise ValueError("checksum mismatch")
        obs = {n: (arrays[f"obs/{k}/ids"].astype(np.int64), arrays[f"obs/{k}/xy"].astype(float)) for k, n in enumerate(names)}
        bags = {int(k.split("/")[1]): [tuple(names[i] for i in row) for row in v]
                for k, v in arrays.items() if k.startswith("bags/")}
        return GroundTruth(scene=scene, method=method, names=names, K=arrays["K"], R=arrays["R"], t=arrays["t"],
                           sizes=arrays["sizes"], points3d=arrays["points3d"], observations=obs,
                           covisibility=arrays["covisibility"], bags=bags, meta=meta)
    except ImtuneError:
        raise
    except Exception as e:
        raise ImtuneError(f"corrupt ground-truth file {path} ({type(e).__name__}: {' '.join(str(e).split())[:120]}); "
                          f"rebuild it with `tune data build-gt --force`") from None


def _not_a_file(p: Path) -> ImtuneError | None:
    """The error for something other than a file in the place of the ground-truth file ``p`` or a file in the place
    of one of its folders (both read as "not built"), else None."""
    if p.exists() and not p.is_file():
        return ImtuneError(f"ground truth {p} is {'a folder' if p.is_dir() else 'not a regular file'}, not the file "
                           "it should be: move it away, then build the ground truth again with `tune data build-gt`")
    blocker = None if p.exists() else next((q for q in p.parents if q.exists() and not q.is_dir()), None)
    if blocker is None:
        return None
    from pipeline.cache import default_cache_dir
    cache = default_cache_dir()
    if not os.environ.get("IMTUNE_GT") and cache / "gt" in p.parents and (blocker == cache or blocker in cache.parents):
        # the ground truth's default place is inside the cache: the cache setting is the culprit (/dev/null is
        # nothing to "move away")
        return ImtuneError(f"cache folder {cache} is not a folder{'' if blocker == cache else f' ({blocker} is a file)'}"
                           f", and the ground truth goes "
                           f"in {cache / 'gt'}: give a folder with --cache DIR or $IMTUNE_CACHE (or --gt-dir for the "
                           "ground truth)")
    return ImtuneError(f"ground truth {p}: {blocker} is a file where a folder should be: move it away, or give "
                       "another folder with --gt-dir (or $IMTUNE_GT)")


def find_ground_truth(scene, gt_dir: Path | str | None = None) -> Path | None:
    """The ground-truth file of ``scene`` if one has been built, else None; ImtuneError when something else (a
    folder) stands in its place (it read as "not built": stereo lost its co-visibility filter without a word)."""
    p = gt_path(scene, gt_dir)
    err = _not_a_file(p)
    if err is not None:
        raise err
    return p if p.is_file() else None


def attach_ground_truth(scene, gt_dir: Path | str | None = None, required: bool = False,
                        overwrite_covisibility: bool = False) -> bool:
    """Give ``scene`` its built ground truth, if any: 3D points and observations (unless the loader
    provided them), and the co-visibility of its pairs (where unknown, or always with
    ``overwrite_covisibility``). For SfM ground truth also K, R, t of every image; images the SfM did
    not register are dropped from the scene (and from its pairs: the stereo task's notes say how many, of how many
    listed, and which images). ``scene.built`` records the method and those counts. Returns True if a ground truth was
    attached; with ``required`` a missing one raises ImtuneError with the command that builds it."""
    p = find_ground_truth(scene, gt_dir)
    if p is None:
        if required:
            raise ImtuneError(f"scene {scene.name}: no ground truth built (expected {gt_path(scene, gt_dir)}); "
                              f"run `tune data build-gt --scenes {scene.name}` first")
        return False
    gt = load_ground_truth(p)
    idx = {n: k for k, n in enumerate(gt.names)}
    listed = len(scene.pairs)
    scene.built = {"method": gt.method, "images": len(scene.images), "registered": len(scene.images),
                   "unregistered": [], "pairs_listed": listed, "pairs_dropped": 0}
    if gt.method == "sfm":
        unregistered = [n for n in scene.images if n not in idx]
        # a pair with its own relative pose (a pairs list: R, t and K per pair) needs no pose from the SfM: it stays,
        # with its images, registered or not, and the co-visibility filter decides (its co-visibility is 0: the
        # unregistered image sees none of the SfM's points); it was dropped whatever --covisibility said
        own = {n for q in scene.pairs if q.R is not None and q.t is not None for n in (q.i, q.j)}
        for n in unregistered:
            if n not in own:
                del scene.images[n]
        for n, k in idx.items():
            if n in scene.images:
                info = scene.images[n]
                info.K, info.R, info.t = gt.K[k].copy(), gt.R[k].copy(), gt.t[k].copy()
                if info.size is None:
                    info.size = (int(gt.sizes[k][0]), int(gt.sizes[k][1]))
        scene.pairs = [q for q in scene.pairs if q.i in scene.images and q.j in scene.images
                       and ((q.i in idx and q.j in idx) or (q.R is not None and q.t is not None))]
        scene.built.update(registered=len(idx.keys() & scene.images.keys()), unregistered=unregistered,
                           pairs_dropped=listed - len(scene.pairs),
                           pairs_unregistered=sum(1 for q in scene.pairs if q.i not in idx or q.j not in idx))
    if scene.observations is None:
        scene.points3d = gt.points3d
        scene.observations = {n: gt.observations[n] for n in gt.names if n in scene.images}
    for q in scene.pairs:
        if (q.covisibility is None or overwrite_covisibility) and q.i in idx and q.j in idx:
            q.covisibility = float(gt.covisibility[idx[q.i], idx[q.j]])
        elif (q.covisibility is None or overwrite_covisibility) and gt.method == "sfm":
            q.covisibility = 0.0  # an image the SfM did not register sees none of its 3D points
    fill_covisibility(scene)
    return True


def fill_covisibility(scene) -> int:
    """Co-visibility of the scene's pairs that lack it, from the scene's own 3D points (loaders such as
    the COLMAP one provide points but not co-visibility). Returns how many pairs were filled."""
    if scene.observations is None or all(q.covisibility is not None for q in scene.pairs):
        return 0
    if any(scene.images[n].size is None for n in scene.observations if n in scene.images):
        return 0
    from pipeline.metrics.covisibility import set_pair_covisibility
    return set_pair_covisibility(scene, overwrite=False)


def prepare_scene_ground_truth(scene, gt_dir: Path | str | None = None) -> Path | None:
    """What the evaluate path calls for every scene: attach a built ground truth when one exists, then
    fill unknown co-visibility from whatever 3D points the scene has. Returns the file used, if any."""
    p = find_ground_truth(scene, gt_dir)
    if p is not None:
        attach_ground_truth(scene, gt_dir)
    else:
        fill_covisibility(scene)
    return p
