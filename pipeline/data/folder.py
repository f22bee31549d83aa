"""A plain image folder without ground truth (``<scene>/images/*.jpg``), e.g. ``sacre_coeur``.

The input for building pseudo ground truth with SfM: images with their sizes, no K or pose, all pairs.
Checked after every other format, so a folder that another loader recognises is never taken for this one.
"""
from __future__ import annotations

from pathlib import Path

from pipeline.data._common import pick_scene, scene_dirs
from pipeline.data.imagefile import check_image_file, image_size, list_images
from pipeline.data.scene import ImageInfo, Scene, all_pairs
from pipeline.errors import ImtuneError

NAME = "images"


def _is_scene(p: Path) -> bool:
    from pipeline.data import _other_format  # avoid claiming scenes of richer formats

    return bool(list_images(p / "images")) and _other_format(p, NAME) is None


def detect(root: Path) -> bool:
    return bool(scene_dirs(root, _is_scene))


def list_scenes(root: Path) -> list[str]:
    return list(scene_dirs(root, _is_scene))


def load_folder(root: Path, scene: str | None = None, verify: bool = True) -> Scene:
    """Load the images of ``<scene>/images`` (sizes in px; no intrinsics, no poses; all pairs)."""
    root = Path(root)
    dirs = scene_dirs(root, _is_scene)
    name = pick_scene(root, scene, list(dirs), "image-folder")
    img_dir = dirs[name] / "images"
    images = {}
    for n in list_images(img_dir):
        path = img_dir / n
        size = None
        if verify:
            check_image_file(path)
            size = image_size(path)
        images[n] = ImageInfo(name=n, path=path, size=size)
    if not images:
        raise ImtuneError(f"no images in {img_dir}")
    return Scene(name=name, root=dirs[name], images=images, pairs=all_pairs(list(images)), source=NAME)


load = load_folder
