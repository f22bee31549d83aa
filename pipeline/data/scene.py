"""The one Scene model every loader produces.

Conventions: poses are world-to-camera (x_cam = R X + t); intrinsics K are for the image *as stored on
disk* (``ImageInfo.size``); the pipeline rescales them with the image (IMC convention, long side <= 1024
px) through :func:`pipeline.data.resize.scaled_K`. A pair's ground-truth relative pose maps camera-i
coordinates to camera-j coordinates: x_j = R_ij x_i + t_ij.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: loader name -> where a scene of that format has its own ground-truth poses from (what reports name)
OWN_POSES = {
    # what the layout tells (a camera file per image), not where the cameras came from: the layout also holds a
    # KITTI sequence, the Middlebury temple or an IMC scene, whose cameras no laser scan measured
    "strecha": "the camera files of its Strecha-layout folder",
    "imc_pt2020": "IMC-PT calibration files",
    "imc2022": "IMC 2022 calibration.csv",
    "colmap": "its COLMAP model",
    "pairs_with_gt": "its pairs list",
    "imc2025": "the IMC 2024/2025 train_labels.csv",
}


@dataclass
class ImageInfo:
    """One image. ``size`` is (width, height) in px of the file on disk; K is 3x3 for that size."""
    name: str
    path: Path
    K: np.ndarray | None = None
    R: np.ndarray | None = None  # 3x3 world-to-camera rotation
    t: np.ndarray | None = None  # (3,) world-to-camera translation
    size: tuple[int, int] | None = None
    depth_path: Path | None = None  # optional depth map (IMC-PT h5 'depth'), same size as the image


@dataclass
class Pair:
    """An evaluation pair (names of two images of the scene).

    R, t: ground-truth relative pose (camera i -> camera j). When None, derived from absolute poses.
    K_i, K_j: per-pair intrinsics overriding the images' (pairs-with-GT lists carry K per pair).
    covisibility: the paper's co-visibility in [0, 1]; None where unknown.
    """
    i: str
    j: str
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    K_i: np.ndarray | None = None
    K_j: np.ndarray | None = None
    covisibility: float | None = None

    @property
    def key(self) -> str:
        return f"{self.i}|{self.j}"


@dataclass
class Scene:
    """A scene: images, evaluation pairs, optional 3D points and multiview bags.

    points3d: (P, 3) world points; observations: image name -> (point indices (n,), keypoints (n, 2) px).
    bags: bag size -> list of tuples of image names.
    """
    name: str
    root: Path
    images: dict[str, ImageInfo]
    pairs: list[Pair] = field(default_factory=list)
    points3d: np.ndarray | None = None
    observations: dict[str, tuple[np.ndarray, np.ndarray]] | None = None
    bags: dict[int, list[tuple[str, ...]]] | None = None
    source: str = ""  # loader name
    truth_id: str | None = None  # the ground truth as loaded (truth_digest), set by load_scene: keys built ground truth
    # the ground truth `tune data build-gt` built, once attached (pipeline.data.ground_truth.attach_ground_truth):
    # method ("poses" / "sfm"), images, registered, unregistered (names), pairs_listed, pairs_dropped,
    # pairs_unregistered (pairs kept on their own poses that hold an unregistered image: co-visibility unknown)
    built: dict | None = None
    # IMC 2024/2025 datasets (pipeline.data.imc2025): image -> its ground-truth scene ("outliers": of none), the
    # camera-centre thresholds (metres) of each scene, and the image files in no label row (left out, counted)
    groups: dict[str, str] | None = None
    thresholds: dict[str, tuple[float, ...]] | None = None
    excluded: list[str] | None = None

    def truth_origin(self) -> str:
        """Where the poses this scene is evaluated against come from, one phrase for reports: the scene's own
        (the camera files of the Strecha layout, IMC-PT's calibration, a pairs list's relative poses) or imtune's SfM
        reconstruction (`tune data build-gt`: an image folder, or ``--method sfm``); and what a built ground truth
        adds (co-visibility from its 3D points)."""
        own = OWN_POSES.get(self.source)
        b = self.built or {}
        if b.get("method") == "sfm":
            reg = f"{b.get('registered')} of {b.get('images')} images registered"
            if self.pairs and all(p.R is not None and p.t is not None for p in self.pairs):
                # each pair's listed relative pose is what is evaluated; SfM gave co-visibility and the pairs kept
                return f"the scene's own poses ({own}); co-visibility from imtune's SfM (tune data build-gt, {reg})"
            return (f"imtune's SfM reconstruction (tune data build-gt, pycolmap; {reg})"
                    + (f", in place of the scene's own poses ({own})" if own else ""))
        if own is None:
            return "none (no poses: build them with `tune data build-gt`)"
        return f"the scene's own poses ({own})" + ("; co-visibility from 3D points triangulated with them (tune data "
                                                   "build-gt)" if b.get("method") == "poses" else "")

    def truth_digest(self) -> str:
        """12 hex of the scene's ground truth as it stands: its format and every image's K, R, t and every pair's
        R, t, K (float64 bytes); "" when it has none (a plain image folder). Built ground truth is keyed by it
        (``truth_id``, fixed at load), so that a scene of the same name and images with other poses never takes
        another's (an SfM ground truth replaces K, R, t)."""
        import hashlib
        h, known = hashlib.sha1(self.source.encode()), False

        def add(tag: str, a) -> None:
            nonlocal known
            if a is not None:
                known = True
                h.update(tag.encode() + b"\0" + np.ascontiguousarray(a, dtype=np.float64).tobytes())
        for n in sorted(self.images):
            im = self.images[n]
            h.update(b"\1" + n.encode())
            for tag, a in (("K", im.K), ("R", im.R), ("t", im.t)):
                add(tag, a)
        for p in self.pairs:
            h.update(b"\2" + p.key.encode())
            for tag, a in (("R", p.R), ("t", p.t), ("Ki", p.K_i), ("Kj", p.K_j)):
                add(tag, a)
        return h.hexdigest()[:12] if known else ""

    def relative_pose(self, pair: Pair) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth (R_ij, t_ij) of a pair; t is not normalised."""
        if pair.R is not None and pair.t is not None:
            return np.asarray(pair.R, float), np.asarray(pair.t, float).reshape(3)
        a, b = self.images[pair.i], self.images[pair.j]
        if a.R is None or b.R is None or a.t is None or b.t is None:
            raise ValueError(f"scene {self.name}: no ground-truth pose for pair {pair.key}")
        R = b.R @ a.R.T
        t = b.t.reshape(3) - R @ a.t.reshape(3)
        return R, t

    def intrinsics(self, pair: Pair) -> tuple[np.ndarray, np.ndarray]:
        """(K_i, K_j) for the images as stored on disk."""
        Ki = pair.K_i if pair.K_i is not None else self.images[pair.i].K
        Kj = pair.K_j if pair.K_j is not None else self.images[pair.j].K
        return np.asarray(Ki, float), np.asarray(Kj, float)

    def missing_ground_truth(self, pairs: list[Pair] | None = None) -> str | None:
        """Why these pairs cannot be evaluated against ground truth (None when they can)."""
        for p in (self.pairs if pairs is None else pairs):
            Ki, Kj = (p.K_i if p.K_i is not None else self.images[p.i].K,
                      p.K_j if p.K_j is not None else self.images[p.j].K)
            if Ki is None or Kj is None:
                return f"no intrinsics for {p.i if Ki is None else p.j}"
            if p.R is None and (self.images[p.i].R is None or self.images[p.j].R is None):
                return f"no ground-truth pose for {p.i if self.images[p.i].R is None else p.j}"
        return None

    def zero_baseline(self, pairs: list[Pair] | None = None) -> str | None:
        """Why a pair cannot be scored (None when every pair can): the first pair whose ground-truth cameras share
        one centre, so that its translation direction is undefined and every estimate's error there is inf or the
        angle of rounding noise (a camera file or a pairs-list line duplicated). Zero: the centres (the listed
        translation) closer than 1e-6 x the scene's scale (the centres' norms, at least 1)."""
        centres: dict[str, np.ndarray | None] = {}

        def centre(n: str):
            if n not in centres:
                im = self.images[n]
                ok = im.R is not None and im.t is not None
                centres[n] = -np.asarray(im.R, float).T @ np.asarray(im.t, float).reshape(3) if ok else None
            return centres[n]
        for p in (self.pairs if pairs is None else pairs):
            if p.t is not None:
                gap, scale = float(np.linalg.norm(p.t)), 1.0
            else:
                ca, cb = centre(p.i), centre(p.j)
                if ca is None or cb is None:
                    continue
                gap = float(np.linalg.norm(ca - cb))
                scale = max(1.0, float(np.linalg.norm(ca)), float(np.linalg.norm(cb)))
            if gap <= 1e-6 * scale:
                return (f"pair {p.key} has no baseline in the ground truth (the two cameras' centres coincide): its "
                        "translation direction is undefined and every method's pose error there would be inf or "
                        "rounding noise; correct the pose of one image, or remove one of them (or the pair's line)")
        return None

    def select_pairs(self, min_covisibility: float | None = 0.1) -> list[Pair]:
        """The protocol's pairs: co-visibility >= threshold where known, all listed pairs otherwise."""
        from pipeline.config import check_covisibility
        min_covisibility = check_covisibility(min_covisibility)  # nan / inf / outside [0, 1] -> ImtuneError
        if min_covisibility is None:
            return list(self.pairs)
        return [p for p in self.pairs if p.covisibility is None or p.covisibility >= min_covisibility]


def all_pairs(names: list[str]) -> list[Pair]:
    """Every unordered pair (i < j in the given order)."""
    return [Pair(a, b) for k, a in enumerate(names) for b in names[k + 1:]]
