"""IMC 2022 (Kaggle "image-matching-challenge-2022") training data.

``train/<scene>/images/<image_id>.jpg``; ``train/<scene>/calibration.csv`` with columns image_id,
camera_intrinsics (9 numbers, row-major K in px), rotation_matrix (9, world-to-camera), translation_vector
(3, SfM units); ``train/<scene>/pair_covisibility.csv`` with columns pair ("idA-idB"), covisibility,
fundamental_matrix; ``train/scaling_factors.csv`` with columns scene, scaling_factor (SfM units -> metres).
``root`` may be the competition folder, its ``train`` folder or a scene folder. Image names are file names.
"""
from __future__ import annotations

import csv
import os
from pathlib import Path

from pipeline.data._common import (
    check_K,
    check_principal_point,
    check_rotation,
    parse_floats,
    pick_scene,
    scene_dirs,
    split_pair_key,
)
from pipeline.data.imagefile import check_image_file, image_size
from pipeline.data.scene import ImageInfo, Pair, Scene, all_pairs
from pipeline.errors import ImtuneError

NAME = "imc2022"
CALIB = "calibration.csv"
COVIS = "pair_covisibility.csv"
SCALES = "scaling_factors.csv"


def _is_scene(p: Path) -> bool:
    return (p / CALIB).is_file() and (p / "images").is_dir()


def _train_dir(root: Path) -> Path:
    root = Path(root)
    return root / "train" if (root / "train").is_dir() and not _is_scene(root) else root


def detect(root: Path) -> bool:
    return bool(scene_dirs(_train_dir(root), _is_scene))


def list_scenes(root: Path) -> list[str]:
    return list(scene_dirs(_train_dir(root), _is_scene))


def _read_csv(path: Path, required: tuple[str, ...]) -> list[tuple[int, dict]]:
    """[(line number, row dict)]; ImtuneError naming the file if unreadable or a column is missing."""
    import io

    from pipeline.fileio import read_text
    text = read_text(path, "IMC 2022 file")  # a folder, a FIFO or a device there: one line, never read
    try:
        reader = csv.DictReader(io.StringIO(text, newline=""))
        fields = [c.strip() for c in (reader.fieldnames or [])]
        missing = [c for c in required if c not in fields]
        if missing:
            raise ImtuneError(f"{path}: missing column(s) {', '.join(missing)} (found: {', '.join(fields)})")
        return [(reader.line_num, {k.strip(): (v or "").strip() for k, v in row.items() if k is not None})
                for row in reader]
    except csv.Error as e:
        raise ImtuneError(f"cannot read {path}: {e}") from None


def read_scaling_factors(root: Path) -> dict[str, float]:
    """scene -> scaling factor (multiply translations by it to get metres); {} if the file is absent."""
    path = _train_dir(root) / SCALES
    if not path.is_file():
        return {}
    out = {}
    for line, row in _read_csv(path, ("scene", "scaling_factor")):
        out[row["scene"]] = float(parse_floats(row["scaling_factor"], 1, f"{path}, line {line}")[0])
    return out


def _find_image(img_dir: Path, image_id: str) -> Path:
    p = img_dir / f"{image_id}.jpg"
    if p.is_file():
        return p
    others = sorted(q for q in img_dir.glob(f"{image_id}.*") if q.is_file())
    return others[0] if others else p


def load_imc2022(root: Path, scene: str | None = None, verify: bool = True) -> Scene:
    """Load one IMC 2022 training scene: K, R, t per image and the listed pairs with their co-visibility
    (all pairs, co-visibility unknown, without pair_covisibility.csv). Translations stay in SfM units; see
    :func:`read_scaling_factors` for the metric scale."""
    root = Path(root)
    dirs = scene_dirs(_train_dir(root), _is_scene)
    name = pick_scene(root, scene, list(dirs), NAME)
    sdir = dirs[name]
    img_dir = sdir / "images"
    calib_path = sdir / CALIB
    images: dict[str, ImageInfo] = {}
    id_to_name: dict[str, str] = {}
    id_line: dict[str, int] = {}
    for line, row in _read_csv(calib_path, ("image_id", "camera_intrinsics", "rotation_matrix",
                                            "translation_vector")):
        where = f"{calib_path}, line {line}"
        image_id = row["image_id"]
        if not image_id:
            raise ImtuneError(f"{where}: empty image_id")
        if image_id in id_line:  # the last row's K, R, t were used, unsaid
            raise ImtuneError(f"{calib_path}, lines {id_line[image_id]} and {line}: image_id {image_id!r} is listed "
                              "twice: keep one of the lines")
        id_line[image_id] = line
        K = check_K(parse_floats(row["camera_intrinsics"], 9, f"{where} (camera_intrinsics)"), where)
        R = check_rotation(parse_floats(row["rotation_matrix"], 9, f"{where} (rotation_matrix)"), where)
        t = parse_floats(row["translation_vector"], 3, f"{where} (translation_vector)")
        path = _find_image(img_dir, image_id)
        size = None
        if verify:
            check_image_file(path)
            size = image_size(path)
            check_principal_point(K, size, path)
        images[path.name] = ImageInfo(name=path.name, path=path, K=K, R=R, t=t, size=size)
        id_to_name[image_id] = path.name
    if not images:
        raise ImtuneError(f"no images listed in {calib_path}")
    covis_path = sdir / COVIS
    if os.path.lexists(covis_path):  # a folder or FIFO there is named, not read as "no co-visibility: every pair"
        pairs = []
        first_line: dict[frozenset, int] = {}  # {idA, idB} -> the line that listed the pair first
        for line, row in _read_csv(covis_path, ("pair", "covisibility")):
            where = f"{covis_path}, line {line}"
            a, b = split_pair_key(row["pair"], set(id_to_name), where)
            if a == b:  # no relative pose to estimate
                raise ImtuneError(f"{where}: pair {row['pair']!r} pairs image {a} with itself: remove the line")
            if frozenset((a, b)) in first_line:  # it would count twice in every mAA (as in a pairs file)
                raise ImtuneError(f"{covis_path}, lines {first_line[frozenset((a, b))]} and {line}: the pair {a}-{b} is "
                                  "listed twice (in either order): keep one of the lines")
            first_line[frozenset((a, b))] = line
            c = float(parse_floats(row["covisibility"], 1, where)[0])
            if not 0.0 <= c <= 1.0:  # a fraction: 5 passed every --covisibility, -1 none, unsaid
                raise ImtuneError(f"{where}: covisibility must be in [0, 1], got {row['covisibility']}")
            pairs.append(Pair(id_to_name[a], id_to_name[b], covisibility=c))
    else:
        pairs = all_pairs(list(images))
    return Scene(name=name, root=sdir, images=images, pairs=pairs, source=NAME)


load = load_imc2022
