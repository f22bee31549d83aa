"""Small helpers shared by the loaders (not public API)."""
from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError


def parse_floats(text: str, n: int | None, where: str) -> np.ndarray:
    """Whitespace-separated numbers -> float64 array; ImtuneError naming ``where`` if the count or a value is bad."""
    tokens = text.split()
    if n is not None and len(tokens) != n:
        raise ImtuneError(f"{where}: expected {n} numbers, found {len(tokens)}")
    try:
        values = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise ImtuneError(f"{where}: not a number: {bad!r}") from None
    if not np.all(np.isfinite(values)):
        raise ImtuneError(f"{where}: non-finite value")
    return values


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def check_rotation(R: np.ndarray, where: str, tol: float = 1e-2) -> np.ndarray:
    """R as a 3x3 float array; ImtuneError if it is not a rotation (orthonormal, det +1) within ``tol``."""
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(R)) or np.abs(R.T @ R - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1) > tol:
        raise ImtuneError(f"{where}: not a rotation matrix")
    return R


def check_K(K: np.ndarray, where: str) -> np.ndarray:
    """K as a 3x3 float array; ImtuneError unless it is an upper-triangular intrinsics matrix with f > 0."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    if (not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1) > 1e-6
            or abs(K[1, 0]) + abs(K[2, 0]) + abs(K[2, 1]) > 1e-9):
        raise ImtuneError(f"{where}: not an intrinsics matrix (expected [[fx s cx] [0 fy cy] [0 0 1]], f > 0)")
    return K


def check_principal_point(K: np.ndarray, size: tuple[int, int], image: Path | str) -> None:
    """ImtuneError naming ``image`` when K's principal point (px) lies outside the image of ``size`` (w, h) px: K is
    then for another image size (a resized copy of the images, the intrinsics left as they were), which formats that
    state no image size (pairs lists, IMC-PT, IMC 2022) cannot tell otherwise."""
    w, h = size
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
        raise ImtuneError(f"image {image} is {w}x{h} px but the principal point of its intrinsics ({cx:g}, {cy:g}) "
                          "lies outside it: the intrinsics are for another size (resized images?); use the images "
                          "they were given for, or scale K to these")


def split_pair_key(key: str, known: set[str], where: str) -> tuple[str, str]:
    """Split "idA-idB" into two known ids (ids may themselves contain '-')."""
    parts = key.split("-")
    for k in range(1, len(parts)):
        a, b = "-".join(parts[:k]), "-".join(parts[k:])
        if a in known and b in known:
            return a, b
    raise ImtuneError(f"{where}: pair {key!r} does not name two known images")


def pick_scene(root: Path, scene: str | None, available: list[str], what: str) -> str:
    """Validate a scene name against the available ones (None: the only one)."""
    if scene is None:
        if len(available) == 1:
            return available[0]
        if not available:
            raise ImtuneError(f"no {what} scene found under {root}")
        raise ImtuneError(f"{root} holds several {what} scenes; choose one of: {', '.join(available)}")
    if scene not in available:
        listing = ", ".join(available) if available else "none"
        raise ImtuneError(f"unknown scene {scene!r} in {root} (available: {listing})")
    return scene


def scene_dirs(root: Path, is_scene: Callable[[Path], bool]) -> dict[str, Path]:
    """Scenes of a dataset folder: ``root`` itself if it is a scene, else its child folders that are scenes."""
    root = Path(root)
    if is_scene(root):
        return {root.name: root}
    if not root.is_dir():
        return {}
    return {p.name: p for p in sorted(root.iterdir()) if p.is_dir() and not p.name.startswith(".") and is_scene(p)}


def unique(seq: Iterable[str]) -> list[str]:
    """Items in first-seen order without duplicates."""
    return list(dict.fromkeys(seq))
