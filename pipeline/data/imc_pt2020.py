"""IMC-PT 2020 (Image Matching Challenge, phototourism) in the official benchmark's layout.

``phototourism/<scene>/set_100/``: ``images/<key>.jpg`` (listed in ``images.txt`` when present),
``calibration/calibration_<key>.h5`` (datasets K 3x3 px, R 3x3 world-to-camera, T (3,) or (3, 1) — SfM units),
``depth_maps/<key>.h5`` (dataset ``depth``), ``new-vis-pairs/keys-th-<v>.npy`` ("keyA-keyB" strings of the pairs
with co-visibility >= v; a pair's co-visibility is the largest v whose list holds it) and multiview bags
``sub_set/<n>bag_<k:03d>.txt`` (one image path per line, relative to set_100, e.g. ``images/<key>.jpg``).
``root`` may be the phototourism folder, a scene folder or its set_100 folder. Image names are file names.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pipeline.data._common import check_K, check_principal_point, check_rotation, pick_scene, split_pair_key, unique
from pipeline.data.imagefile import check_image_file, image_size, list_images
from pipeline.data.scene import ImageInfo, Pair, Scene, all_pairs
from pipeline.errors import ImtuneError

NAME = "imc_pt2020"
SET = "set_100"
_BAG_RE = re.compile(r"^(\d+)bag_(\d+)\.txt$")
_TH_RE = re.compile(r"^keys-th-([0-9.]+)\.npy$")


def _is_set(p: Path) -> bool:
    return (p / "images").is_dir() and (p / "calibration").is_dir()


def _scene_sets(root: Path) -> dict[str, Path]:
    """scene name -> its set_100 folder."""
    root = Path(root)
    if _is_set(root / SET):
        return {root.name: root / SET}
    if root.name == SET and _is_set(root):
        return {root.parent.name: root}
    if not root.is_dir():
        return {}
    return {p.name: p / SET for p in sorted(root.iterdir())
            if p.is_dir() and not p.name.startswith(".") and _is_set(p / SET)}


def detect(root: Path) -> bool:
    return bool(_scene_sets(root))


def list_scenes(root: Path) -> list[str]:
    return list(_scene_sets(root))


def _read_list(path: Path) -> list[str]:
    try:
        return [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    except (OSError, UnicodeDecodeError) as e:
        raise ImtuneError(f"cannot read {path}: {e}") from None


def read_calibration(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K 3x3, R 3x3 world-to-camera, t (3,)) from a ``calibration_<key>.h5``; ImtuneError naming the file."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in ("K", "R", "T") if k not in f]
            if missing:
                raise ImtuneError(f"calibration file {path}: missing dataset(s) {', '.join(missing)}")
            K, R, T = (np.asarray(f[k][()], dtype=np.float64) for k in ("K", "R", "T"))
    except ImtuneError:
        raise
    except (OSError, ValueError, TypeError) as e:
        raise ImtuneError(f"unreadable calibration file {path}: {e}") from None
    if K.size != 9 or R.size != 9 or T.size != 3:
        raise ImtuneError(f"calibration file {path}: expected K 3x3, R 3x3, T 3 values "
                          f"(got {K.shape}, {R.shape}, {T.shape})")
    where = f"calibration file {path}"
    if not np.all(np.isfinite(T)):  # K and R are checked below; a NaN T was ground truth no pose error can meet
        raise ImtuneError(f"{where}: non-finite value in T")
    return check_K(K, where), check_rotation(R, where), T.reshape(3)


def read_vis_pairs(folder: Path) -> list[tuple[str, float]]:
    """[(pair key "keyA-keyB", co-visibility)] from ``new-vis-pairs/keys-th-<v>.npy`` files, in the order of the
    lowest threshold's list; co-visibility = the largest v whose list contains the pair."""
    files = []
    for p in folder.glob("keys-th-*.npy"):
        m = _TH_RE.match(p.name)
        if m:
            try:
                files.append((float(m.group(1).rstrip(".")), p))
            except ValueError:
                continue
    covis: dict[str, float] = {}
    for v, p in sorted(files):
        try:
            keys = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise ImtuneError(f"unreadable pair list {p}: {e}") from None
        if keys.size == 0:  # an empty list may be saved with any dtype
            continue
        if keys.dtype.kind not in "US":
            raise ImtuneError(f"pair list {p}: expected an array of 'keyA-keyB' strings, got dtype {keys.dtype}")
        for k in keys.reshape(-1):
            k = k.decode() if isinstance(k, bytes) else str(k)
            covis[k] = max(covis.get(k, -1.0), v)
    return list(covis.items())


def read_bags(folder: Path, known: dict[str, str]) -> dict[int, list[tuple[str, ...]]]:
    """Bags from ``sub_set/<n>bag_<k>.txt``: bag size -> list (ordered by k) of tuples of image names.
    ``known`` maps accepted spellings (file name, key, relative path) to image names."""
    found: dict[int, list[tuple[int, tuple[str, ...]]]] = {}
    for p in sorted(folder.glob("*bag_*.txt")):
        m = _BAG_RE.match(p.name)
        if not m:
            continue
        names = []
        for entry in _read_list(p):
            name = known.get(entry) or known.get(Path(entry).name) or known.get(Path(entry).stem)
            if name is None:
                raise ImtuneError(f"bag file {p}: unknown image {entry!r}")
            if name in names:  # a bag of n with an image twice: a smaller bag reconstructed under size n, unsaid
                raise ImtuneError(f"bag file {p}: image {entry!r} is listed twice: list each image of the bag once")
            names.append(name)
        if len(names) != int(m.group(1)):
            raise ImtuneError(f"bag file {p}: {len(names)} images in a bag of {int(m.group(1))} (its name): "
                              "is it cut short?")
        found.setdefault(int(m.group(1)), []).append((int(m.group(2)), tuple(names)))
    return {n: [b for _, b in sorted(v)] for n, v in sorted(found.items())}


def _optional(p: Path, folder: bool, what: str) -> bool:
    """``p`` is there as a folder (``folder``) or a regular file: True; nothing there: False. Anything else at its
    name (a file at new-vis-pairs/, a folder at a depth map) is a one-line ImtuneError: it was read as absent (every
    pair evaluated with co-visibility unknown, no bags, no depth), unsaid."""
    from pipeline.fileio import kind_at
    kind = kind_at(p)
    if kind is None:
        return False
    if kind == "a broken link":
        raise ImtuneError(f"{what} {p} is a broken link: point it at the {what}, or remove it")
    if kind == ("a folder" if folder else "a file"):
        return True
    raise ImtuneError(f"{what} {p} is {kind}, not a {'folder' if folder else 'file'}: put the {what} there, or move "
                      "it away")


def load_imc_pt2020(root: Path, scene: str | None = None, verify: bool = True) -> Scene:
    """Load one IMC-PT 2020 scene (the official set_100 subset): K, R, t per image, depth-map paths, pairs with
    co-visibility (all pairs with unknown co-visibility when new-vis-pairs/ is absent), and bags if present."""
    root = Path(root)
    sets = _scene_sets(root)
    name = pick_scene(root, scene, list(sets), NAME)
    sdir = sets[name]
    img_dir = sdir / "images"
    if (sdir / "images.txt").is_file():
        rel = _read_list(sdir / "images.txt")
        files = unique(Path(r).name for r in rel)
    else:
        files = list_images(img_dir)
    if not files:
        raise ImtuneError(f"no images in {img_dir}")
    images: dict[str, ImageInfo] = {}
    key_to_name: dict[str, str] = {}
    for fn in files:
        key = Path(fn).stem
        path = img_dir / fn
        calib = sdir / "calibration" / f"calibration_{key}.h5"
        if not calib.is_file():
            raise ImtuneError(f"missing calibration for image {path}: expected {calib}")
        K, R, t = read_calibration(calib)
        size = None
        if verify:
            check_image_file(path)
            size = image_size(path)
            check_principal_point(K, size, path)
        depth = sdir / "depth_maps" / f"{key}.h5"
        images[fn] = ImageInfo(name=fn, path=path, K=K, R=R, t=t, size=size,
                               depth_path=depth if _optional(depth, False, "depth map") else None)
        key_to_name[key] = fn
    vis_dir = sdir / "new-vis-pairs"
    vis = read_vis_pairs(vis_dir) if _optional(vis_dir, True, "pair list folder") else []
    if vis:
        pairs = []
        seen: dict[frozenset, str] = {}
        for key, v in vis:
            a, b = split_pair_key(key, set(key_to_name), f"pair list in {vis_dir}")
            if a == b or frozenset((a, b)) in seen:  # b-a after a-b was evaluated twice (twice in every mAA)
                what = (f"pairs image {a} with itself" if a == b else
                        f"lists the pair {seen[frozenset((a, b))]} again as {key}")
                raise ImtuneError(f"pair list in {vis_dir}: {what}: remove it from the keys-th-*.npy files")
            seen[frozenset((a, b))] = key
            pairs.append(Pair(key_to_name[a], key_to_name[b], covisibility=float(v)))
    else:
        pairs = all_pairs(list(images))
    bags = None
    if _optional(sdir / "sub_set", True, "bag folder"):
        known = {**key_to_name, **{n: n for n in images}, **{f"images/{n}": n for n in images}}
        bags = read_bags(sdir / "sub_set", known) or None
    return Scene(name=name, root=sdir, images=images, pairs=pairs, bags=bags, source=NAME)


load = load_imc_pt2020
