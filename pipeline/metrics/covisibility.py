"""Co-visibility of image pairs, exactly as the IMC protocol defines it.

For images i and j, take the 3D points observed in both; in each image, the area of the axis-aligned
bounding box of those points' observations (their projections) divided by the image area; the pair's
co-visibility is the smaller of the two ratios, in [0, 1]. Fewer than two common points give 0 (a box
of one point has no area). Pairs are selected for the stereo task at co-visibility >= 0.1.

Inputs are a scene's ``observations`` (image name -> (point indices, keypoints (n, 2) px in the image
as stored on disk)) and image sizes (width, height) in px of the same images.
"""
from __future__ import annotations

import numpy as np

from pipeline.errors import ImtuneError

#: The paper's co-visibility bins for the stereo breakdown: 0+, 0.1+, ..., 0.6+ (each bin is ">= edge").
COVISIBILITY_BINS: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)


def bbox_area(xy: np.ndarray) -> float:
    """Area (px^2) of the axis-aligned bounding box of points (n, 2); 0 for fewer than two points."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    if len(xy) < 2:
        return 0.0
    span = xy.max(0) - xy.min(0)
    return float(span[0] * span[1])


def covisibility(ids_i: np.ndarray, kpts_i: np.ndarray, size_i: tuple[int, int],
                 ids_j: np.ndarray, kpts_j: np.ndarray, size_j: tuple[int, int]) -> float:
    """Co-visibility of one pair from the two images' observations.

    ids_*: 3D point index of each observation (n,); kpts_*: the observations (n, 2) px; size_*: (w, h) px.
    Returns min over the two images of (bounding-box area of the common points / image area), in [0, 1].
    """
    ids_i = np.asarray(ids_i).reshape(-1)
    ids_j = np.asarray(ids_j).reshape(-1)
    _, a, b = np.intersect1d(ids_i, ids_j, assume_unique=False, return_indices=True)
    if len(a) < 2:
        return 0.0
    ai = bbox_area(np.asarray(kpts_i)[a]) / float(size_i[0] * size_i[1])
    aj = bbox_area(np.asarray(kpts_j)[b]) / float(size_j[0] * size_j[1])
    return float(min(1.0, max(0.0, min(ai, aj))))


def common_points(obs_i, obs_j) -> int:
    """Number of 3D points observed in both images."""
    return int(len(np.intersect1d(np.asarray(obs_i[0]), np.asarray(obs_j[0]))))


def _require(scene) -> None:
    if scene.observations is None:
        raise ImtuneError(f"scene {scene.name}: no 3D points, so co-visibility is unknown; "
                          f"build them with `tune data build-gt` (or use a loader that provides points)")
    for name in scene.observations:
        if name in scene.images and scene.images[name].size is None:
            raise ImtuneError(f"scene {scene.name}: image size of {name} unknown (needed for co-visibility)")


def covisibility_matrix(scene, names: list[str] | None = None) -> np.ndarray:
    """(n, n) symmetric co-visibility of the given images (default: all, in the scene's order); diagonal 1."""
    _require(scene)
    names = list(scene.images) if names is None else list(names)
    n = len(names)
    M = np.eye(n)
    empty = (np.zeros(0, np.int64), np.zeros((0, 2)))
    obs = [scene.observations.get(x, empty) for x in names]
    sizes = [scene.images[x].size for x in names]
    for a in range(n):
        for b in range(a + 1, n):
            M[a, b] = M[b, a] = covisibility(obs[a][0], obs[a][1], sizes[a], obs[b][0], obs[b][1], sizes[b])
    return M


def scene_covisibility(scene, pairs=None) -> dict[str, float]:
    """Co-visibility of each pair (default: the scene's pairs), keyed by ``Pair.key``."""
    _require(scene)
    pairs = scene.pairs if pairs is None else pairs
    empty = (np.zeros(0, np.int64), np.zeros((0, 2)))
    out = {}
    for p in pairs:
        oi = scene.observations.get(p.i, empty)
        oj = scene.observations.get(p.j, empty)
        out[p.key] = covisibility(oi[0], oi[1], scene.images[p.i].size, oj[0], oj[1], scene.images[p.j].size)
    return out


def set_pair_covisibility(scene, overwrite: bool = True) -> int:
    """Fill ``Pair.covisibility`` of the scene's pairs from its points; returns how many pairs were set."""
    values = scene_covisibility(scene)
    n = 0
    for p in scene.pairs:
        if overwrite or p.covisibility is None:
            p.covisibility = values[p.key]
            n += 1
    return n


def bin_label(edge: float) -> str:
    """'0.1+' style label of a co-visibility bin."""
    return f"{edge:g}+"
