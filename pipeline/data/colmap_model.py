"""A COLMAP sparse model as ground truth, read with pycolmap.

Scene layout: ``<scene>/images/`` plus ``<scene>/sparse/`` or ``<scene>/sparse/<n>/`` holding
cameras/images/points3D as ``.bin`` or ``.txt`` (also ``<scene>/dense/{images,sparse}`` as in the IMC-PT training
archives). With several ``sparse/<n>`` models the one with the most registered images is used. Only registered
images are kept. K is the camera's calibration matrix (px); a camera whose lens distortion moves its image border by
more than ``MAX_DISTORTION_PX`` is refused (imtune models pinhole cameras: undistort first). COLMAP's
pixel coordinates put the top-left pixel's centre at (0.5, 0.5): K's principal point and the observations are moved
by -0.5 px into imtune's pixel-centre convention (:mod:`pipeline.colmap_db`).
Poses world-to-camera in model units; ``points3d`` (P, 3) and per-image observations (point indices, xy px); a model
without 3D points has none (co-visibility unknown, so every pair is evaluated; ``tune data build-gt`` triangulates).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.colmap_db import PIXEL_OFFSET, K_from_camera
from pipeline.data._common import check_K, pick_scene, scene_dirs
from pipeline.data.imagefile import check_image_file, image_size, rotated_by_exif
from pipeline.data.scene import ImageInfo, Scene, all_pairs
from pipeline.errors import ImtuneError

NAME = "colmap"
_PARTS = ("cameras", "images", "points3D")


def is_model_dir(p: Path) -> bool:
    """True if ``p`` holds cameras/images/points3D, all .bin or all .txt."""
    return any(all((p / f"{n}{ext}").is_file() for n in _PARTS) for ext in (".bin", ".txt"))


def _model_candidates(sdir: Path) -> list[Path]:
    out = []
    for base in (sdir / "sparse", sdir / "dense" / "sparse"):
        if is_model_dir(base):
            out.append(base)
        elif base.is_dir():
            out += [p for p in sorted(base.iterdir()) if p.is_dir() and is_model_dir(p)]
        if out:
            break
    return out


def _image_dir(sdir: Path) -> Path:
    for cand in (sdir / "images", sdir / "dense" / "images"):
        if cand.is_dir():
            return cand
    return sdir / "images"


def _is_scene(p: Path) -> bool:
    return bool(_model_candidates(p))


def detect(root: Path) -> bool:
    return bool(scene_dirs(root, _is_scene))


def list_scenes(root: Path) -> list[str]:
    return list(scene_dirs(root, _is_scene))


def check_images_txt(path: Path) -> None:
    """ImtuneError naming the line when ``images.txt`` is not pose line + 2D-points line per image. COLMAP reads
    the line after each image's pose line as its 2D points whatever it holds: a file of pose lines alone (no empty
    points lines) had every second image read as the points of the one before, and half the images were evaluated,
    unsaid."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ImtuneError(f"unreadable COLMAP model file {path}: {e}") from None
    k = 0
    while k < len(lines):
        head = lines[k].strip()
        k += 1
        if not head or head.startswith("#"):
            continue
        if k >= len(lines):
            break
        parts = lines[k].split()
        k += 1
        try:
            [float(v) for v in parts]
            ok = len(parts) % 3 == 0
        except ValueError:
            ok = False
        if not ok:
            name = head.split()[-1] if len(head.split()) >= 10 else "?"
            shown = lines[k - 1].strip()
            shown = shown[:60] + ("..." if len(shown) > 60 else "")
            raise ImtuneError(f"COLMAP model {path.parent}: images.txt line {k}, read as the 2D points of image "
                              f"{name!r}, is not X Y POINT3D_ID triples ({shown}):"
                              " each image takes two lines, its pose and then its 2D points (an empty line when it "
                              "has none)")


def read_model(path: Path):
    """pycolmap.Reconstruction from a model folder; ImtuneError naming it if missing or unreadable."""
    from pipeline.colmap_db import import_pycolmap
    pycolmap = import_pycolmap()

    path = Path(path)
    if not is_model_dir(path):
        raise ImtuneError(f"not a COLMAP model (need cameras, images, points3D as .bin or .txt): {path}")
    for n in _PARTS:
        f = path / f"{n}.bin"
        if f.is_file() and f.stat().st_size == 0:
            raise ImtuneError(f"unreadable COLMAP model {path}: {f.name} is empty")
    if not (path / "images.bin").is_file():
        check_images_txt(path / "images.txt")
    try:
        return pycolmap.Reconstruction(str(path))
    except Exception as e:  # pycolmap raises ValueError / RuntimeError with multi-line C++ messages
        msg = " ".join(str(e).split())
        raise ImtuneError(f"unreadable COLMAP model {path}: {msg}") from None


def _rotation(rot, where: str) -> np.ndarray:
    """The rotation matrix of a pycolmap Rotation3d read from a model. pycolmap keeps the file's quaternion as it is
    and turns it into a matrix as if it were a unit one: a zero quaternion became the identity (a ground-truth pose
    out of nothing, unsaid) and a non-unit one a matrix that is no rotation. A quaternion of another length is
    normalised, as COLMAP does; a zero or non-finite one is one line naming the image."""
    from scipy.spatial.transform import Rotation
    q = np.asarray(rot.quat, float).reshape(4)  # x y z w (Eigen's order)
    n = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else float("nan")
    if not (n > 1e-9):
        raise ImtuneError(f"{where}: its rotation quaternion (qw qx qy qz = {q[3]:g} {q[0]:g} {q[1]:g} {q[2]:g}) is "
                          "no rotation: fix images.txt (or re-export the model)")
    return Rotation.from_quat(q / n).as_matrix()


#: largest displacement (px) lens distortion may cause at an image's border and still be read as a pinhole camera
MAX_DISTORTION_PX = 0.5


def distortion_px(cam) -> float:
    """How far (px) a pycolmap camera's lens distortion moves the points of its image border (corners and edge
    midpoints) from where its pinhole part alone puts them; 0 for PINHOLE models, inf where it cannot be undone."""
    w, h = float(cam.width), float(cam.height)
    xy = np.array([[x, y] for x in (0.0, w / 2, w) for y in (0.0, h / 2, h) if (x, y) != (w / 2, h / 2)])
    K = np.asarray(cam.calibration_matrix(), float)
    with np.errstate(all="ignore"):
        nrm = np.asarray(cam.cam_from_img(xy), float).reshape(-1, 2)  # undistorted, normalised
        pin = nrm @ K[:2, :2].T + K[:2, 2]
        d = np.linalg.norm(pin - xy, axis=1)
    return float(d.max()) if np.all(np.isfinite(d)) else float("inf")


def load_colmap(root: Path, scene: str | None = None, model: Path | None = None, image_dir: Path | None = None,
                verify: bool = True) -> Scene:
    """Load a COLMAP model as a Scene: registered images (K, R, t, size), 3D points and observations, all pairs
    of registered images (co-visibility unknown: compute it from the points). ``model`` / ``image_dir``
    override the folders found in the scene. ``verify`` checks every image file exists, is complete and has its
    camera's size."""
    root = Path(root)
    if model is not None:
        sdir, name = root, scene or root.name
        models = [Path(model)]
    else:
        dirs = scene_dirs(root, _is_scene)
        name = pick_scene(root, scene, list(dirs), NAME)
        sdir = dirs[name]
        models = _model_candidates(sdir)
    recs = [(read_model(m), m) for m in models]
    rec, mdir = max(recs, key=lambda r: r[0].num_reg_images())
    img_dir = Path(image_dir) if image_dir is not None else _image_dir(sdir)

    images: dict[str, ImageInfo] = {}
    id_to_name: dict[int, str] = {}
    for image_id in sorted(rec.reg_image_ids()):
        im = rec.images[image_id]
        cam = rec.cameras[im.camera_id]
        pose = im.cam_from_world  # a method in pycolmap 4.x, a property in older versions
        pose = pose() if callable(pose) else pose
        if im.name in images:  # the later image's pose and points replaced the earlier's, unsaid
            first = next(i for i, n in id_to_name.items() if n == im.name)
            raise ImtuneError(f"COLMAP model {mdir}: images {first} and {image_id} are both named {im.name!r}: "
                              "one image file cannot have two poses")
        path = img_dir / im.name
        if verify:
            check_image_file(path)
            w, h = image_size(path)
            if (w, h) != (int(cam.width), int(cam.height)):  # K is for the camera's size: a resized copy made it wrong
                turned = rotated_by_exif(path, (int(cam.width), int(cam.height)))
                raise ImtuneError(f"COLMAP model {mdir}: camera {im.camera_id} of {im.name} is {cam.width}x{cam.height}"
                                  f" px but {path} is {w}x{h}" + (turned or ": use the images the model was made "
                                                                 "from (or rescale the model's cameras to them)"))
        # a focal length of 0 (cameras.txt) was taken as ground truth; pycolmap refuses NaN, not 0 or < 0
        K = check_K(K_from_camera(cam), f"COLMAP model {mdir}: camera {im.camera_id} of {im.name}")
        moved = distortion_px(cam)
        if moved > MAX_DISTORTION_PX:  # poses were estimated with the pinhole K alone on distorted images, unsaid
            raise ImtuneError(f"COLMAP model {mdir}: camera {im.camera_id} ({cam.model.name}) of {im.name} has lens "
                              f"distortion moving its image border by up to {moved:.3g} px, which imtune does not "
                              "model (pinhole K): undistort the images and the model first "
                              "(`colmap image_undistorter`; its output folder reads as is)")
        images[im.name] = ImageInfo(name=im.name, path=path, K=K,
                                    R=_rotation(pose.rotation, f"COLMAP model {mdir}: image {image_id} ({im.name})"),
                                    t=np.asarray(pose.translation, float).reshape(3),
                                    size=(int(cam.width), int(cam.height)))
        id_to_name[image_id] = im.name
    if not images:
        raise ImtuneError(f"COLMAP model {mdir} has no registered images")

    point_ids = sorted(rec.point3D_ids())
    if not point_ids:  # poses only: co-visibility unknown (every pair evaluated), not 0 for every pair (none evaluated)
        return Scene(name=name, root=sdir, images=images, pairs=all_pairs(list(images)), source=NAME)
    index = {pid: k for k, pid in enumerate(point_ids)}
    points3d = np.array([rec.points3D[p].xyz for p in point_ids], dtype=np.float64).reshape(-1, 3)
    observations = {}
    for image_id, image_name in id_to_name.items():
        idx, xy = [], []
        for p2 in rec.images[image_id].points2D:
            if p2.has_point3D() and p2.point3D_id in index:
                idx.append(index[p2.point3D_id])
                xy.append(np.asarray(p2.xy, float) - PIXEL_OFFSET)
        observations[image_name] = (np.asarray(idx, dtype=np.int64), np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    return Scene(name=name, root=sdir, images=images,
                 pairs=all_pairs(list(images)), points3d=points3d, observations=observations, source=NAME)


load = load_colmap
