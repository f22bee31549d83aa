"""The thin layer between imtune and pycolmap (4.x API): databases, verification, mapping, models.

Coordinates: imtune keypoints follow the pixel-centre convention (OpenCV: the centre of the top-left
pixel is (0, 0)); COLMAP's follow the pixel-corner convention ((0.5, 0.5)). Everything written to COLMAP
is shifted by +0.5 px (keypoints and principal point) and everything read back by -0.5 px.

Cameras (``intrinsics``):
- "colmap": what the official benchmark does (its ``feature_importer``): SIMPLE_RADIAL, focal length
  from EXIF if the file has it, else 1.2 x the long side, refined by COLMAP; known K is not used.
- "prior": known K as a PINHOLE camera flagged as a prior; COLMAP still refines the focal length.
- "fixed": known K held fixed (no intrinsics refinement).

Every function that reads a user-supplied database or model turns pycolmap's failures into an
ImtuneError naming the file.
"""
from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError

PIXEL_OFFSET = 0.5
INTRINSICS_MODES = ("colmap", "prior", "fixed")


def import_pycolmap():
    """``import pycolmap``, keeping this process's SIGTERM handler. pycolmap's glog installs its failure handler
    for SIGTERM when the module loads (it prints a stack trace, then the process dies), which bypassed tune's
    graceful stop (pool killed, trial failed, one line, exit 143) in any process that had used COLMAP, and left
    the pool's workers behind. Python still records its own handler, so setting it again restores it (main thread
    only, as Python requires)."""
    import signal
    import threading

    import pycolmap
    if threading.current_thread() is threading.main_thread():
        h = signal.getsignal(signal.SIGTERM)
        signal.signal(signal.SIGTERM, h if h is not None else signal.SIG_DFL)
    return pycolmap


def quiet(level: int = 2) -> None:
    """Silence COLMAP's glog output below ``level`` (0 info, 1 warning, 2 error, 3 fatal), and keep it on stderr:
    glog otherwise also writes log files (``/tmp/<host>.<user>.log.*``) that nobody asked for. ``IMTUNE_DEBUG=1``
    keeps COLMAP's errors: its own message of why a reconstruction failed."""
    import os
    pycolmap = import_pycolmap()
    if os.environ.get("IMTUNE_DEBUG"):
        level = min(level, 2)
    try:
        pycolmap.logging.logtostderr = True
        pycolmap.logging.minloglevel = level
        pycolmap.logging.stderrthreshold = max(level, 2)
    except Exception:  # older bindings without these attributes
        pass


def make_camera(width: int, height: int, K: np.ndarray | None = None, mode: str = "colmap",
                image_path: Path | None = None, file_size: tuple[int, int] | None = None):
    """A pycolmap.Camera for an image of (width, height) px (the working resolution).

    mode "colmap": SIMPLE_RADIAL with the EXIF focal length of ``image_path`` (read at ``file_size`` and
    rescaled) or 1.2 x max(width, height); "prior" / "fixed": PINHOLE from K (pixel-centre convention)."""
    pycolmap = import_pycolmap()
    if mode not in INTRINSICS_MODES:
        raise ImtuneError(f"unknown intrinsics mode {mode!r} (choose {', '.join(INTRINSICS_MODES)})")
    if mode == "colmap":
        f, prior = 1.2 * max(width, height), False
        if image_path is not None:
            try:
                cam = pycolmap.infer_camera_from_image(str(image_path))
                if cam.has_prior_focal_length and cam.width > 0:
                    f, prior = float(cam.focal_length) * width / float(cam.width), True
            except Exception:
                pass
        return pycolmap.Camera(model="SIMPLE_RADIAL", width=int(width), height=int(height),
                               params=[f, width / 2.0, height / 2.0, 0.0], has_prior_focal_length=prior)
    if K is None:
        raise ImtuneError(f"intrinsics mode {mode!r} needs known intrinsics")
    K = np.asarray(K, float)
    return pycolmap.Camera(model="PINHOLE", width=int(width), height=int(height),
                           params=[K[0, 0], K[1, 1], K[0, 2] + PIXEL_OFFSET, K[1, 2] + PIXEL_OFFSET],
                           has_prior_focal_length=True)


def K_from_camera(cam) -> np.ndarray:
    """3x3 K (pixel-centre convention) of a pycolmap camera (distortion, if any, is dropped)."""
    K = np.asarray(cam.calibration_matrix(), float).copy()
    K[0, 2] -= PIXEL_OFFSET
    K[1, 2] -= PIXEL_OFFSET
    return K


def check_database(path: Path | str) -> None:
    """Raise ImtuneError naming ``path`` unless it is a readable COLMAP database."""
    path = Path(path)
    if not path.is_file():
        raise ImtuneError(f"COLMAP database not found: {path}")
    try:
        with open(path, "rb") as f:
            head = f.read(16)
        if head != b"SQLite format 3\x00":
            raise ImtuneError(f"{path} is not a COLMAP database (not an SQLite file)")
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            if not {"cameras", "images", "keypoints", "matches"} <= tables:
                raise ImtuneError(f"{path} is not a COLMAP database (tables missing: "
                                  f"{', '.join(sorted({'cameras', 'images', 'keypoints', 'matches'} - tables))})")
            con.execute("PRAGMA quick_check").fetchone()
        finally:
            con.close()
    except sqlite3.DatabaseError as e:
        raise ImtuneError(f"cannot read COLMAP database {path}: {e}") from None


def open_database(path: Path | str, create: bool = False):
    """pycolmap.Database at ``path`` (created if ``create``); ImtuneError naming the file if unreadable."""
    pycolmap = import_pycolmap()
    path = Path(path)
    if not create:
        check_database(path)
    try:
        return pycolmap.Database.open(str(path))
    except Exception as e:
        raise ImtuneError(f"cannot open COLMAP database {path}: {str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__}") from None


def write_database(path: Path | str, images: list[tuple[str, object, np.ndarray]],
                   matches: dict[tuple[str, str], np.ndarray]) -> dict[str, int]:
    """Write a fresh database: one camera per image, its keypoints, and raw (unverified) matches.

    images: [(name, pycolmap.Camera, keypoints (n, 2) px, pixel-centre convention)];
    matches: {(name_i, name_j): (M, 2) indices into the two keypoint arrays}. Returns name -> image_id.
    An existing file at ``path`` is replaced."""
    pycolmap = import_pycolmap()
    path = Path(path)
    if path.exists():
        path.unlink()
    db = pycolmap.Database.open(str(path))
    ids: dict[str, int] = {}
    try:
        for name, cam, kpts in images:
            cid = db.write_camera(cam)
            iid = db.write_image(pycolmap.Image(name=name, camera_id=cid))
            k = np.asarray(kpts, np.float32).reshape(-1, 2) + np.float32(PIXEL_OFFSET)
            db.write_keypoints(iid, np.ascontiguousarray(k))
            ids[name] = iid
        for (a, b), m in matches.items():
            m = np.asarray(m).reshape(-1, 2)
            if len(m) == 0:
                continue
            db.write_matches(ids[a], ids[b], np.ascontiguousarray(m.astype(np.uint32)))
    finally:
        db.close()
    return ids


def verification_options(max_error: float = 4.0, confidence: float = 0.999, max_num_trials: int = 10000,
                         min_inlier_ratio: float = 0.25, min_num_inliers: int = 15, seed: int = 0):
    """COLMAP's two-view geometry options (defaults = COLMAP's, as the official benchmark ran them)."""
    pycolmap = import_pycolmap()
    o = pycolmap.TwoViewGeometryOptions()
    o.min_num_inliers = int(min_num_inliers)
    o.ransac.max_error = float(max_error)
    o.ransac.confidence = float(confidence)
    o.ransac.max_num_trials = int(max_num_trials)
    o.ransac.min_inlier_ratio = float(min_inlier_ratio)
    o.ransac.random_seed = int(seed)
    o.ransac.num_threads = 1
    return o


def verify(path: Path | str, options=None, num_threads: int = 1) -> None:
    """COLMAP geometric verification of every matched pair in the database (its own RANSAC)."""
    pycolmap = import_pycolmap()
    vo = pycolmap.GeometricVerifierOptions()
    vo.num_threads = int(num_threads)
    pycolmap.geometric_verification(str(path), vo, pycolmap.ExistingMatchedPairingOptions(),
                                    options if options is not None else verification_options())


def mapper_options(min_model_size: int = 3, num_threads: int = 1, seed: int = 0, fixed_intrinsics: bool = False,
                   max_runtime_seconds: float | None = None):
    """IncrementalPipelineOptions for a bag: single-threaded, seeded, no colours (no image reads)."""
    pycolmap = import_pycolmap()
    o = pycolmap.IncrementalPipelineOptions()
    o.min_model_size = int(min_model_size)
    o.num_threads = int(num_threads)
    o.random_seed = int(seed)
    o.extract_colors = False
    o.multiple_models = True
    if fixed_intrinsics:
        o.ba_refine_focal_length = False
        o.ba_refine_principal_point = False
        o.ba_refine_extra_params = False
    if max_runtime_seconds:
        o.max_runtime_seconds = float(max_runtime_seconds)
    for sub in (o.mapper, o.triangulation):
        try:
            sub.random_seed = int(seed)
        except AttributeError:
            pass
    try:
        o.mapper.num_threads = int(num_threads)
    except AttributeError:
        pass
    return o


def incremental_mapping(db_path: Path | str, out_dir: Path | str, options) -> tuple[dict, str | None]:
    """Run pycolmap incremental mapping; (models by index, failure reason or None).

    Never raises for a reconstruction that fails: no initial pair, nothing registered or an exception
    inside COLMAP are returned as a reason (the official benchmark's issue 49 is a recorded failure here)."""
    pycolmap = import_pycolmap()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        recs = pycolmap.incremental_mapping(str(db_path), str(out_dir), str(out_dir), options)
    except Exception as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        return {}, f"mapper failed: {msg}"
    recs = {k: r for k, r in (recs or {}).items() if r.num_reg_images() > 0}
    if not recs:
        return {}, "mapper found no initial pair / registered no images"
    return recs, None


def largest_model(recs: dict):
    """The model with the most registered images (ties: more 3D points), or None."""
    if not recs:
        return None
    return max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))


def model_poses(rec) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (R, t) world-to-camera of every registered image with a finite pose."""
    out = {}
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        if not im.has_pose:
            continue
        T = np.asarray(im.cam_from_world().matrix(), float)
        R, t = T[:, :3], T[:, 3]
        if np.all(np.isfinite(R)) and np.all(np.isfinite(t)):
            out[im.name] = (R, t)
    return out


def model_stats(rec) -> dict:
    """NL (3D points), registered images, mean track length, mean reprojection error (px)."""
    n = rec.num_points3D()
    return {"NL": int(n), "registered": int(rec.num_reg_images()),
            "TL": float(rec.compute_mean_track_length()) if n else 0.0,
            "reprojection_error": float(rec.compute_mean_reprojection_error()) if n else 0.0}


def read_model(path: Path | str):
    """A COLMAP sparse model (cameras/images/points3D .bin or .txt); ImtuneError naming the folder."""
    pycolmap = import_pycolmap()
    path = Path(path)
    if not path.is_dir():
        raise ImtuneError(f"COLMAP model folder not found: {path}")
    have = {p.name for p in path.iterdir()}
    if not ({"cameras.bin", "images.bin", "points3D.bin"} <= have or {"cameras.txt", "images.txt", "points3D.txt"} <= have):
        raise ImtuneError(f"{path} is not a COLMAP model (expected cameras, images, points3D .bin or .txt)")
    try:
        return pycolmap.Reconstruction(str(path))
    except Exception as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ImtuneError(f"cannot read COLMAP model {path}: {msg}") from None


def limit_threads(n: int = 1) -> None:
    """Cap BLAS / OpenMP threads in this process (call before heavy imports in worker processes)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(n)
