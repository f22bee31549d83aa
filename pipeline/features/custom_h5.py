"""Bring your own features: the official IMC benchmark's feature-import h5 layout, as ``custom:DIR``.

    tune evaluate --feature custom:/path/to/my_features            # evaluated like a built-in
    tune --feature custom:/path/to/my_features --ransac degensac   # and tuned like one

Layout (ubc-vision/image-matching-benchmark, ``import_features.py`` / ``submission_validator.py``): one
folder per scene holding

- ``keypoints.h5``: one dataset per image, keyed by the image file name without its extension
  (``0000.jpg`` -> ``0000``), shape (N, 2), (x, y) in pixels of the image *as stored on disk* (the
  pixel-centre convention: the centre of the top-left pixel is (0, 0)); extra columns are ignored;
- ``descriptors.h5``: same keys, (N, D): float (L2 distance) or uint8 (packed bits, Hamming distance —
  option ``distance=l2`` treats uint8 as numbers); optional when custom matches are used;
- ``scores.h5`` (optional): (N,) detection scores, higher is better — needed only when an image has more
  keypoints than ``num_features`` (the strongest are kept, as the official import does);
- ``scales.h5``, ``orientations.h5`` (optional): (N,) in the same pixel units / degrees; used by
  pre-filters (AdaLAM, GMS with scale or rotation).

``DIR`` may be that scene folder itself (one scene), or any folder above scene folders named like the
scenes (``DIR/<scene>/keypoints.h5`` or the benchmark's ``DIR/<dataset>/<scene>/keypoints.h5``): the
scene folder of an image is the one whose name is a component of the image's path. Image names in
subfolders (``a/b/c.jpg``) are looked up as ``a/b/c`` (h5 groups), then ``c``.

Keypoints are resized with the image to the working resolution (IMC convention, long side <= 1024 px).
Checked, each a one-line ImtuneError naming the file and the key: a missing image key, non-finite
keypoints or descriptors, keypoints outside the image (tolerance 0.5 px beyond the pixel-centre extent),
descriptor rows != keypoints, a descriptor dimension differing between images of one file.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, ClassVar, Literal, overload

import numpy as np

from pipeline.errors import ImtuneError
from pipeline.features.base import Extractor, Features

PREFIX = "custom:"
FILES = ("keypoints.h5", "descriptors.h5", "scores.h5", "scales.h5", "orientations.h5")
MATCH_FILES = ("matches.h5", "matches_stereo_0.h5", "matches_stereo.h5", "matches_multiview.h5")
#: keypoints may lie this far (px) beyond the pixel-centre extent [0, W - 1] x [0, H - 1]
BOUNDS_TOLERANCE = 0.5
MAX_DEPTH = 3


def parse_custom(name: str) -> Path:
    """``custom:DIR`` -> the absolute folder; ImtuneError if it does not exist."""
    if not name.startswith(PREFIX) or not name[len(PREFIX):].strip():
        raise ImtuneError(f"bad custom source {name!r}: expected custom:DIR")
    d = Path(name[len(PREFIX):].strip()).expanduser().resolve()
    if not d.is_dir():
        raise ImtuneError(f"{name}: folder {d} does not exist")
    return d


def scene_folders(root: Path, marker: tuple[str, ...] = ("keypoints.h5",)) -> list[Path]:
    """Folders under ``root`` (depth <= 3, root included) holding any of the ``marker`` files."""
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        depth = len(Path(dirpath).relative_to(root).parts)
        if any(m in filenames for m in marker):
            out.append(Path(dirpath))
        if depth >= MAX_DEPTH:
            dirnames[:] = []
        dirnames.sort()
    return out


def folder_for(root: Path, image_path: Path | str, scene: str | None = None,
               marker: tuple[str, ...] = ("keypoints.h5",), what: str = "keypoints.h5") -> Path:
    """The scene folder (under ``root``) holding the h5 files of the image at ``image_path``."""
    folders = scene_folders(root, marker)
    if not folders:
        raise ImtuneError(f"{root}: no {what} in this folder or its subfolders (IMC import layout: "
                          f"<DIR>[/<dataset>]/<scene>/{what})")
    if len(folders) == 1 and folders[0] == root:  # DIR is the scene folder itself: one scene, whatever its name
        return folders[0]
    # a lone scene folder under DIR serves the scene it is named after only (it served every scene: the images
    # of another scene were given its keypoints, by the same image names)
    parts = set(Path(image_path).resolve().parts) | ({scene} if scene else set())
    hits = [f for f in folders if f.name in parts]
    if len(hits) == 1:
        return hits[0]
    if not hits:
        raise ImtuneError(f"{root}: none of the scene folders holding {what} ({', '.join(f.name for f in folders[:5])}"
                          f"{', ...' if len(folders) > 5 else ''}) is named after a folder of {image_path}: add "
                          f"<DIR>/<scene>/ for that image's scene, or use only the scenes DIR holds (--scenes, --test-scenes)")
    raise ImtuneError(f"{root}: several scene folders match {image_path}: {', '.join(map(str, hits))}")


def image_keys(name: str) -> list[str]:
    """Candidate h5 keys of an image name: without extension (with its subfolders), then the bare stem."""
    p = Path(name)
    keys = [str(p.with_suffix("")).replace(os.sep, "/"), p.stem]
    return list(dict.fromkeys(keys))


def _find_key(f, name: str) -> str | None:
    for k in image_keys(name):
        if k in f:
            obj = f[k]
            if hasattr(obj, "shape"):
                return k
    return None


def files_signature(folder: Path) -> str:
    """Identity of a folder's h5 files (path, size, mtime) for cache keys: edits invalidate."""
    h = hashlib.sha1()
    for f in scene_folders(folder, FILES + MATCH_FILES):
        for n in FILES:
            p = f / n
            if p.is_file():
                st = p.stat()
                h.update(f"{p}|{st.st_size}|{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


_DIMS: dict[tuple, dict[str, int]] = {}


def _descriptor_dims(path: Path) -> dict[str, int]:
    """key -> descriptor dimension of every dataset of a descriptors.h5 (metadata only; memoised)."""
    import h5py
    st = path.stat()
    memo = (str(path), st.st_size, st.st_mtime_ns)
    if memo not in _DIMS:
        dims: dict[str, int] = {}

        def visit(k, obj):
            if isinstance(obj, h5py.Dataset):
                dims[k] = int(obj.shape[1]) if len(obj.shape) == 2 else -1
        with h5py.File(path, "r") as f:
            f.visititems(visit)
        _DIMS[memo] = dims
    return _DIMS[memo]


def h5_file_present(path: Path) -> bool:
    """``path`` is a regular file (False when nothing is there). A folder, a FIFO or a broken link at its name is a
    one-line ImtuneError naming it: read as absent, a folder at scales.h5 ran AdaLAM without scales, unsaid."""
    from pipeline.fileio import kind_at
    kind = kind_at(path)
    if kind is None:
        return False
    if kind == "a broken link":
        raise ImtuneError(f"{path} is a broken link: point it at the h5 file, or remove it")
    if kind != "a file":
        raise ImtuneError(f"{path} is {kind}, not an h5 file: move it away, or put the file there")
    return True


@overload
def _read(path: Path, name: str, required: Literal[True] = ...) -> np.ndarray: ...
@overload
def _read(path: Path, name: str, required: bool) -> np.ndarray | None: ...
def _read(path: Path, name: str, required: bool = True) -> np.ndarray | None:
    """The dataset of image ``name`` in ``path`` (None when the file is absent and not required)."""
    import h5py
    if not h5_file_present(path):
        if required:
            raise ImtuneError(f"{path}: file not found")
        return None
    try:
        with h5py.File(path, "r") as f:
            key = _find_key(f, name)
            if key is None:
                raise ImtuneError(f"{path}: no key {image_keys(name)[0]!r} for image {name} "
                                  f"({len(f.keys())} keys, e.g. {', '.join(list(f.keys())[:3])})")
            return np.asarray(f[key][()])
    except OSError as e:
        raise ImtuneError(f"{path}: not a readable h5 file ({str(e).splitlines()[0]})") from None


class CustomFeatures(Extractor):
    """Features imported from h5 files (IMC layout); subclasses made by :func:`custom_class` set ``root``."""
    version: ClassVar[str] = "1"
    binary: ClassVar[bool] = False  # decided per file (uint8 descriptors -> Hamming)
    root: ClassVar[Path]
    custom: ClassVar[bool] = True
    option_defaults: ClassVar[dict[str, Any]] = {"distance": "auto"}

    @classmethod
    def check_available(cls) -> None:
        if not cls.root.is_dir():
            raise ImtuneError(f"custom features: folder {cls.root} does not exist")
        if not scene_folders(cls.root):
            raise ImtuneError(f"{cls.root}: no keypoints.h5 in this folder or its subfolders")

    def __init__(self, conf):
        from pipeline.features._opencv import parse_options
        super().__init__(conf)
        self.opts = parse_options(conf.name, conf.options, self.option_defaults)
        if self.opts["distance"] not in ("auto", "l2", "hamming"):
            raise ImtuneError(f"feature {conf.name!r}: option distance must be auto, l2 or hamming, "
                              f"got {self.opts['distance']!r}")
        for flag in ("upright", "upright_plus"):
            if getattr(conf, flag):
                raise ImtuneError(f"feature {conf.name!r}: {flag} does not apply to imported features")
        if conf.clahe != "none" or conf.mr_size is not None:
            raise ImtuneError(f"feature {conf.name!r}: clahe / mr_size do not apply to imported features")

    def extract(self, image: np.ndarray) -> Features:
        raise ImtuneError(f"feature {self.conf.name!r} is read per image file, not computed from pixels: "
                          "use pipeline.tasks.prepare.image_features or .extract_from_file(info, image, sx, sy)")

    def extract_from_file(self, info, image: np.ndarray, sx: float, sy: float, scene: str | None = None) -> Features:
        """The features of one image (``info``: ImageInfo with ``name`` and ``path``), at the working
        resolution of ``image`` (the resized image; ``sx``, ``sy``: working / file size)."""
        from pipeline.data.resize import scale_points
        name = info.name
        folder = folder_for(self.root, info.path, scene)
        kp_path = folder / "keypoints.h5"
        h, w = image.shape[:2]
        W = info.size[0] if info.size else int(round(w / sx))
        H = info.size[1] if info.size else int(round(h / sy))
        key = image_keys(name)[0]
        kp = _read(kp_path, name)
        if kp.ndim != 2 or kp.shape[1] < 2:
            raise ImtuneError(f"{kp_path}: key {key!r}: keypoints must be (N, 2), got shape {kp.shape}")
        kp = kp[:, :2].astype(np.float64)
        n = len(kp)
        if not np.all(np.isfinite(kp)):
            raise ImtuneError(f"{kp_path}: key {key!r}: {int((~np.isfinite(kp)).any(1).sum())} keypoints are NaN or inf")
        tol = BOUNDS_TOLERANCE
        out = (kp[:, 0] < -tol) | (kp[:, 1] < -tol) | (kp[:, 0] > W - 1 + tol) | (kp[:, 1] > H - 1 + tol)
        if out.any():
            i = int(np.flatnonzero(out)[0])
            raise ImtuneError(f"{kp_path}: key {key!r}: {int(out.sum())} keypoints outside the {W}x{H} image "
                              f"(e.g. #{i} at ({kp[i, 0]:.1f}, {kp[i, 1]:.1f}))")
        desc, binary = self._descriptors(folder, name, key, n)
        extra = {}
        for fname, field in (("scores.h5", "scores"), ("scales.h5", "scales"), ("orientations.h5", "orientations")):
            a = _read(folder / fname, name, required=False)
            if a is None:
                continue
            a = np.asarray(a).reshape(-1) if a.ndim == 2 and 1 in a.shape else np.asarray(a)
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise ImtuneError(f"{folder / fname}: key {key!r}: expected {n} finite values, got shape {a.shape}")
            extra[field] = a.astype(np.float32)
        k = self.conf.num_features
        if n > k:  # the budget: the strongest by score, as the official import
            if "scores" not in extra:
                raise ImtuneError(f"{kp_path}: key {key!r}: {n} keypoints > num_features {k} and no scores.h5 "
                                  "to keep the strongest: raise --num-features or add scores.h5")
            keep = np.sort(np.argsort(-extra["scores"], kind="stable")[:k])
            kp, desc = kp[keep], desc[keep]
            extra = {f: v[keep] for f, v in extra.items()}
        xy = scale_points(kp, sx, sy).astype(np.float32) if (sx, sy) != (1.0, 1.0) else kp.astype(np.float32)
        if "scales" in extra:
            extra["scales"] = extra["scales"] * np.float32(0.5 * (sx + sy))
        return Features(keypoints=np.ascontiguousarray(xy), descriptors=np.ascontiguousarray(desc),
                        binary=binary, **extra)

    def _descriptors(self, folder: Path, name: str, key: str, n: int) -> tuple[np.ndarray, bool]:
        path = folder / "descriptors.h5"
        if not h5_file_present(path):  # allowed with custom matches (the matcher is skipped)
            return np.zeros((n, 0), np.float32), False
        d = _read(path, name)
        if d.ndim != 2 or d.shape[0] != n:
            raise ImtuneError(f"{path}: key {key!r}: descriptors must be ({n}, D) to match {n} keypoints, "
                              f"got shape {d.shape}")
        dims = {v for v in _descriptor_dims(path).values() if v >= 0}
        if len(dims) > 1:
            by = _descriptor_dims(path)
            ref = max(dims, key=lambda v: sum(1 for x in by.values() if x == v))
            odd = next(k for k, v in by.items() if v != ref)
            raise ImtuneError(f"{path}: key {odd!r}: descriptor dimension {by[odd]} differs from the file's "
                              f"{ref} (wrong dimension)")
        dist = self.opts["distance"]
        binary = dist == "hamming" or (dist == "auto" and d.dtype == np.uint8)
        if binary:
            if d.dtype != np.uint8:
                raise ImtuneError(f"{path}: key {key!r}: Hamming distance needs uint8 (packed bits), got {d.dtype}")
            return np.ascontiguousarray(d), True
        if not np.issubdtype(d.dtype, np.number):
            raise ImtuneError(f"{path}: key {key!r}: descriptors must be numbers, got {d.dtype}")
        d = d.astype(np.float32)
        bad = ~np.all(np.isfinite(d), axis=1)
        if bad.any():
            raise ImtuneError(f"{path}: key {key!r}: {int(bad.sum())} descriptors contain NaN or inf "
                              f"(e.g. row {int(np.flatnonzero(bad)[0])})")
        return d, False


_CLASSES: dict[tuple, type[CustomFeatures]] = {}


def custom_class(name: str) -> type[CustomFeatures]:
    """The extractor class of ``custom:DIR``; its ``version`` (part of every cache key) changes when
    any h5 file under DIR changes."""
    root = parse_custom(name)
    sig = files_signature(root)
    key = (str(root), sig)
    if key not in _CLASSES:
        _CLASSES[key] = type(f"Custom[{root.name}]", (CustomFeatures,), {
            "__doc__": f"features imported from {root} (IMC h5 layout)", "__module__": __name__,
            "root": root, "version": f"2+{sig}"})  # 2: a lone scene folder serves its own scene only
    return _CLASSES[key]
