"""Image Matching Challenge 2024 / 2025 (Kaggle) training data: datasets that mix scenes and outlier images.

One imtune :class:`~pipeline.data.scene.Scene` per challenge *dataset* (the unit the challenge scores): its images,
each image's ground-truth scene (``Scene.groups``; ``outliers`` for images of no scene, which have no pose), the
camera-centre thresholds of each scene (``Scene.thresholds``, metres) and the images found in the dataset's folder
but in no label row (``Scene.excluded``: left out of the evaluation, counted and said).

Layouts (``root`` is the competition folder, or a folder whose sub-folders are such folders):

- IMC 2025: ``train/<dataset>/<image>``; ``train_labels.csv`` with ``dataset,scene,image,rotation_matrix,
  translation_vector`` (R row-major, 9 values; t, 3 values; ``;``-separated; world-to-camera, metric);
  ``train_thresholds.csv`` with ``dataset,scene,thresholds`` (metres, ``;``-separated). No intrinsics.
- IMC 2024: the same files (in the root or in ``train/``), images under ``train/<dataset>/images/<image>`` or named by
  an ``image_path`` / ``image_name`` column, and a ``calibration_matrix`` column (K, 9 values): intrinsics known.

Bad input is a one-line ImtuneError naming the file and line: a label row whose image file is missing, a malformed
or non-orthonormal rotation, a scene absent from the thresholds, an image listed twice, a pose on an outlier row is
allowed (ignored), no pose on a scene's row is not.
"""
from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np

from pipeline.data._common import check_K, check_rotation
from pipeline.data.imagefile import check_image_file, image_size, is_image_file
from pipeline.data.scene import ImageInfo, Pair, Scene
from pipeline.errors import ImtuneError

NAME = "imc2025"
LABELS = "train_labels.csv"
THRESHOLDS = "train_thresholds.csv"
OUTLIERS = "outliers"
IMAGE_COLUMNS = ("image", "image_name", "image_path")


def _files(root: Path) -> tuple[Path, Path, Path] | None:
    """(labels, thresholds, train folder) of an IMC root, or None."""
    root = Path(root)
    for base in (root, root / "train"):
        lab = base / LABELS
        if lab.is_file():
            train = root / "train" if (root / "train").is_dir() else base
            return lab, base / THRESHOLDS, train
    return None


def _roots(root: Path) -> list[Path]:
    """``root`` when it is an IMC folder, else its sub-folders that are (one level)."""
    root = Path(root)
    if _files(root) is not None:
        return [root]
    if not root.is_dir():
        return []
    return [p for p in sorted(root.iterdir()) if p.is_dir() and not p.name.startswith(".") and _files(p) is not None]


def _read_csv(path: Path, required: tuple[str, ...], what: str) -> tuple[list[str], list[tuple[int, dict]]]:
    from pipeline.fileio import read_text
    text = read_text(path, what)
    try:
        reader = csv.DictReader(io.StringIO(text, newline=""))
        fields = [c.strip() for c in (reader.fieldnames or [])]
        missing = [c for c in required if c not in fields]
        if missing:
            raise ImtuneError(f"{path}: missing column(s) {', '.join(missing)} (found: {', '.join(fields) or 'none'})")
        rows = [(reader.line_num, {(k or "").strip(): (v or "").strip() for k, v in row.items() if k is not None})
                for row in reader]
    except csv.Error as e:
        raise ImtuneError(f"cannot read {path}: {e}") from None
    return fields, [(n, r) for n, r in rows if any(r.values())]


def _numbers(text: str, n: int, where: str, allow_nan: bool = False) -> np.ndarray | None:
    """``;``-separated numbers (the challenge's format) -> array; None for an all-nan / empty field when allowed."""
    parts = [p.strip() for p in text.replace(",", ";").split(";") if p.strip()]
    if not parts and allow_nan:
        return None
    if len(parts) != n:
        raise ImtuneError(f"{where}: expected {n} ';'-separated numbers, found {len(parts)}")
    try:
        a = np.array([float(p) for p in parts], float)
    except ValueError:
        bad = next(p for p in parts if not _isfloat(p))
        raise ImtuneError(f"{where}: not a number: {bad!r}") from None
    if allow_nan and np.all(np.isnan(a)):
        return None
    if not np.all(np.isfinite(a)):
        raise ImtuneError(f"{where}: non-finite value")
    return a


def _isfloat(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _image_column(fields: list[str], path: Path) -> str:
    for c in IMAGE_COLUMNS:
        if c in fields:
            return c
    raise ImtuneError(f"{path}: missing column image (or image_name / image_path; found: {', '.join(fields)})")


def _labels(root: Path) -> tuple[Path, Path, Path, list[str], list[tuple[int, dict]]]:
    found = _files(root)
    if found is None:
        raise ImtuneError(f"no {LABELS} in {root} or {Path(root) / 'train'}")
    lab, th, train = found
    fields, rows = _read_csv(lab, ("dataset", "scene", "rotation_matrix", "translation_vector"), "IMC labels file")
    _image_column(fields, lab)
    return lab, th, train, fields, rows


def detect(root: Path) -> bool:
    return bool(list_scenes(root))


def list_scenes(root: Path) -> list[str]:
    """The datasets named in the labels (each one imtune scene), in order of first appearance."""
    out: list[str] = []
    for r in _roots(root):
        try:
            _, _, _, _, rows = _labels(r)
        except ImtuneError:
            continue
        for _, row in rows:
            if row.get("dataset") and row["dataset"] not in out:
                out.append(row["dataset"])
    return out


def _root_of(root: Path, dataset: str) -> Path:
    for r in _roots(root):
        try:
            if any(row.get("dataset") == dataset for _, row in _labels(r)[4]):
                return r
        except ImtuneError:
            continue
    raise ImtuneError(f"unknown dataset {dataset!r} in {root} (available: {', '.join(list_scenes(root)) or 'none'})")


def _image_path(train: Path, dataset: str, scene: str, image: str) -> Path:
    """Where a label row's image is: train/<dataset>/<image> (2025), train/<image_path> (2024's paths),
    train/<dataset>/images/<image>, train/<dataset>/<scene>/images/<image>; the first candidate when none exists."""
    cands = [train / dataset / image, train / image, train.parent / image, train / dataset / "images" / image,
             train / dataset / scene / "images" / image]
    for c in cands:
        if c.is_file():
            return c
    return cands[0]


def read_thresholds(path: Path) -> dict[tuple[str, str], tuple[float, ...]]:
    """(dataset, scene) -> thresholds (metres) from a train_thresholds.csv; one-line errors naming the line."""
    if not os.path.lexists(path):
        return {}
    _, rows = _read_csv(path, ("dataset", "scene", "thresholds"), "IMC thresholds file")
    out: dict[tuple[str, str], tuple[float, ...]] = {}
    for line, row in rows:
        where = f"{path}, line {line}"
        parts = [p for p in row["thresholds"].split(";") if p.strip()]
        try:
            th = tuple(float(p) for p in parts)
        except ValueError:
            raise ImtuneError(f"{where}: thresholds must be ';'-separated numbers, got {row['thresholds']!r}") from None
        if len(th) < 3 or not all(np.isfinite(th)) or min(th) <= 0 or list(th) != sorted(th):
            raise ImtuneError(f"{where}: thresholds must be at least 3 increasing positive distances (metres), "
                              f"got {row['thresholds']!r}")
        key = (row["dataset"], row["scene"])
        if key in out:
            raise ImtuneError(f"{where}: scene {row['scene']!r} of dataset {row['dataset']!r} is listed twice")
        out[key] = th
    return out


def load_imc2025(root: Path, scene: str | None = None, verify: bool = True) -> Scene:
    """Load one dataset (an imtune scene; ``scene`` names the dataset, None: the only one)."""
    root = Path(root)
    names = list_scenes(root)
    if scene is None:
        if len(names) != 1:
            raise ImtuneError(f"{root} holds several IMC datasets; choose one of: {', '.join(names) or 'none'}")
        scene = names[0]
    r = _root_of(root, scene)
    lab, th_path, train, fields, rows = _labels(r)
    col = _image_column(fields, lab)
    has_K = "calibration_matrix" in fields
    thresholds = read_thresholds(th_path)
    images: dict[str, ImageInfo] = {}
    groups: dict[str, str] = {}
    first: dict[str, int] = {}
    for line, row in rows:
        if row["dataset"] != scene:
            continue
        where = f"{lab}, line {line}"
        image, gscene = row.get(col, ""), row["scene"]
        if not image:
            raise ImtuneError(f"{where}: empty {col}")
        if not gscene:
            raise ImtuneError(f"{where}: empty scene (use '{OUTLIERS}' for images of no scene)")
        name = Path(image).name if col == "image_path" else image
        if name in first:
            raise ImtuneError(f"{lab}, lines {first[name]} and {line}: image {name!r} of dataset {scene!r} is listed "
                              "twice: keep one of the lines")
        first[name] = line
        outlier = gscene == OUTLIERS
        Rv = _numbers(row["rotation_matrix"], 9, f"{where} (rotation_matrix)", allow_nan=True)
        tv = _numbers(row["translation_vector"], 3, f"{where} (translation_vector)", allow_nan=True)
        R = t = None
        if not outlier:
            if Rv is None or tv is None:
                raise ImtuneError(f"{where}: image {name} of scene {gscene!r} has no pose (only '{OUTLIERS}' rows may "
                                  "leave rotation_matrix / translation_vector empty or nan)")
            R = check_rotation(Rv, f"{where} (rotation_matrix: not orthonormal with determinant +1)", tol=1e-3)
            t = tv
            if (scene, gscene) not in thresholds:
                raise ImtuneError(f"{where}: scene {gscene!r} of dataset {scene!r} has no thresholds in {th_path} "
                                  "(the challenge's mAA needs them): add its row")
        K = None
        if has_K and row.get("calibration_matrix") and not outlier:
            Kv = _numbers(row["calibration_matrix"], 9, f"{where} (calibration_matrix)", allow_nan=True)
            K = None if Kv is None else check_K(Kv, where)
        path = _image_path(train, scene, gscene, image)
        size = None
        if verify:
            if not path.is_file():
                raise ImtuneError(f"{where}: image file not found: {path}")
            check_image_file(path)
            size = image_size(path)
        images[name] = ImageInfo(name=name, path=path, K=K, R=R, t=t, size=size)
        groups[name] = gscene
    if not images:
        raise ImtuneError(f"no images of dataset {scene!r} in {lab}")
    by_scene: dict[str, list[str]] = {}
    for n in images:
        if groups[n] != OUTLIERS:
            by_scene.setdefault(groups[n], []).append(n)
    counts = {len(thresholds[(scene, g)]) for g in by_scene}
    if len(counts) > 1:
        raise ImtuneError(f"{th_path}: the scenes of dataset {scene!r} have different numbers of thresholds "
                          f"({', '.join(map(str, sorted(counts)))}); the challenge's mAA needs one number")
    folder = train / scene
    excluded = []
    if folder.is_dir():
        known = {p.resolve() for p in (im.path for im in images.values())}
        for p in sorted(folder.rglob("*")):
            if p.is_file() and is_image_file(p) and p.resolve() not in known:
                excluded.append(str(p.relative_to(folder)))
    pairs = [Pair(a, b) for names_ in by_scene.values() for k, a in enumerate(names_) for b in names_[k + 1:]]
    th = {g: tuple(thresholds[(scene, g)]) for g in by_scene}
    return Scene(name=scene, root=folder if folder.is_dir() else train, images=images, pairs=pairs, source=NAME,
                 groups=groups, thresholds=th, excluded=excluded)


def describe(root: Path) -> list[dict]:
    """One dict per dataset: its ground-truth scenes and their image counts, outliers, images in no label row,
    whether intrinsics are known (IMC 2024's calibration_matrix). Reads the labels only (no image is opened)."""
    out = []
    for name in list_scenes(root):
        sc = load_imc2025(root, name, verify=False)
        groups = sc.groups or {}
        scenes: dict[str, int] = {}
        for g in groups.values():
            if g != OUTLIERS:
                scenes[g] = scenes.get(g, 0) + 1
        out.append({"dataset": name, "images": len(sc.images), "scenes": scenes,
                    "outliers": sum(1 for g in groups.values() if g == OUTLIERS),
                    "unlabelled": len(sc.excluded or []),
                    "intrinsics": all(im.K is not None for n, im in sc.images.items() if groups.get(n) != OUTLIERS)})
    return out


load = load_imc2025
