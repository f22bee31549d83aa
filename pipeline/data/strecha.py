"""Strecha et al. (CVPR 2008) multi-view benchmark, as in openMVG's SfM_quality_evaluation.

Layout: ``<scene>/images/NNNN.jpg`` and ``<scene>/gt_dense_cameras/NNNN.jpg.camera``. A camera file holds 26
numbers: K (3x3, px), radial distortion (3), R (3x3, camera-to-world), C (3, camera centre in world units),
width height (px). World-to-camera: R_wc = R^T, t = -R^T C. Image names are the file names (``0000.jpg``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.data._common import check_K, check_rotation, parse_floats, pick_scene, scene_dirs
from pipeline.data.imagefile import check_image_file, image_size, list_images, rotated_by_exif
from pipeline.data.scene import ImageInfo, Scene, all_pairs
from pipeline.errors import ImtuneError

NAME = "strecha"
CAMERA_DIR = "gt_dense_cameras"


def _is_scene(p: Path) -> bool:
    return (p / CAMERA_DIR).is_dir()


def detect(root: Path) -> bool:
    """True if ``root`` is a Strecha scene or a folder of Strecha scenes."""
    return bool(scene_dirs(root, _is_scene))


def list_scenes(root: Path) -> list[str]:
    return list(scene_dirs(root, _is_scene))


def read_camera(path: Path) -> dict:
    """Parse a ``.camera`` file: {"K", "dist", "R" (camera-to-world), "C", "size" (w, h)}; ImtuneError naming it."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ImtuneError(f"cannot read camera file {path}: {e}") from None
    v = parse_floats(text, 26, f"camera file {path}")
    w, h = v[24], v[25]
    if np.any(v[9:12] != 0):  # dropped, it had every pose estimated with the pinhole K on distorted images, unsaid
        raise ImtuneError(f"camera file {path}: radial distortion {' '.join(f'{x:g}' for x in v[9:12])} on line 4, "
                          "which imtune does not model (pinhole K; Strecha's published images are undistorted, "
                          "0 0 0): undistort the images and write 0 0 0")
    if w <= 0 or h <= 0 or w != int(w) or h != int(h):
        raise ImtuneError(f"camera file {path}: invalid image size {w:g} x {h:g}")
    return {"K": check_K(v[0:9].reshape(3, 3), f"camera file {path}"), "dist": v[9:12],
            "R": check_rotation(v[12:21].reshape(3, 3), f"camera file {path}"), "C": v[21:24],
            "size": (int(w), int(h))}


def write_camera(path: Path, K, dist, R, C, size) -> None:
    """Write a ``.camera`` file (the inverse of :func:`read_camera`)."""
    K, R = np.asarray(K, float).reshape(3, 3), np.asarray(R, float).reshape(3, 3)
    rows = [*K, np.asarray(dist, float).reshape(3), *R, np.asarray(C, float).reshape(3)]
    lines = [" ".join(f"{x:.10g}" for x in r) for r in rows] + [f"{int(size[0])} {int(size[1])}"]
    Path(path).write_text("\n".join(lines) + "\n")


def _not_a_regular_file(p: Path, what: str) -> None:
    """One line for a folder, FIFO, device or broken link at ``p`` (read as "missing" before, the thing there
    unnamed); nothing when nothing (or a regular file) is there."""
    from pipeline.fileio import kind_at
    kind = kind_at(p)
    if kind not in (None, "a file"):
        raise ImtuneError(f"{what} {p} is {kind}, not a file: put the {what} there")


def load_strecha(root: Path, scene: str | None = None, verify: bool = True) -> Scene:
    """Load one Strecha scene (``root`` is the dataset folder, or the scene folder with ``scene`` None).

    Poses world-to-camera; t in the dataset's world units (metres). Pairs: all pairs, co-visibility unknown.
    ``verify`` checks every image exists, is complete and has the size the camera file states.
    """
    root = Path(root)
    dirs = scene_dirs(root, _is_scene)
    name = pick_scene(root, scene, list(dirs), NAME)
    sdir = dirs[name]
    cam_dir, img_dir = sdir / CAMERA_DIR, sdir / "images"
    names = list_images(img_dir)
    if not names:
        raise ImtuneError(f"no images in {img_dir}")
    cameras = {p.name[: -len(".camera")] for p in cam_dir.glob("*.camera")}
    orphans = sorted(cameras - set(names))
    if orphans:
        _not_a_regular_file(img_dir / orphans[0], "image")
        raise ImtuneError(f"image missing for camera file {cam_dir / (orphans[0] + '.camera')}: "
                          f"expected {img_dir / orphans[0]}")
    images: dict[str, ImageInfo] = {}
    for n in names:
        cam_path = cam_dir / f"{n}.camera"
        if not cam_path.is_file():
            _not_a_regular_file(cam_path, "camera file")
            raise ImtuneError(f"missing camera file for image {img_dir / n}: expected {cam_path}")
        cam = read_camera(cam_path)
        path = img_dir / n
        if verify:
            check_image_file(path)
            if image_size(path) != cam["size"]:
                w, h = image_size(path)
                raise ImtuneError(f"camera file {cam_path} states size {cam['size'][0]}x{cam['size'][1]} "
                                  f"but {path} is {w}x{h}{rotated_by_exif(path, cam['size'])}")
        R_wc = cam["R"].T
        images[n] = ImageInfo(name=n, path=path, K=cam["K"], R=R_wc, t=-R_wc @ cam["C"], size=cam["size"])
    return Scene(name=name, root=sdir, images=images, pairs=all_pairs(names), source=NAME)


load = load_strecha
