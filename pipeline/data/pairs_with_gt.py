"""SuperGlue / LoFTR "pairs with ground truth" text lists (ScanNet, YFCC100M, ... test pairs), and glue-factory's
``pairs_calibrated.txt`` (the MegaDepth-1500 and ScanNet-1500 lists of LightGlue / glue-factory).

One line per pair: ``name0 name1 rot0 rot1 K0(9) K1(9) T_0to1(16)`` (``pairs_with_gt.txt``, 38 fields) or
``name0 name1 K0(9) K1(9) R(9) t(3)`` / ``name0 name1 K0(9) K1(9) T_0to1(16)`` (``pairs_calibrated.txt``, 32 or 36
fields) — K row-major in px, T_0to1 = [R | t] the row-major 4x4 mapping camera-0 coordinates to camera-1 coordinates
(translation in the dataset's units: metres for ScanNet).
rot0 / rot1 are EXIF rotation codes; only 0 is supported (the intrinsics refer to the stored pixel grid).
Image names are paths as written, resolved against ``<root>/images/`` first, then ``<root>/``. The scene is the
folder holding the list; its name is the folder name. Stereo only: images carry K but no absolute pose.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.data._common import check_K, check_principal_point, check_rotation, parse_floats, pick_scene, scene_dirs
from pipeline.data.imagefile import check_image_file, image_size
from pipeline.data.scene import ImageInfo, Pair, Scene
from pipeline.errors import ImtuneError

NAME = "pairs_with_gt"
DEFAULT_FILE = "pairs_with_gt.txt"
CALIBRATED_FILE = "pairs_calibrated.txt"  # glue-factory's lists (MegaDepth-1500, ScanNet-1500)
_NUMS = 2 + 9 + 9 + 16
_FIELDS = {2 + _NUMS: "rot0 rot1 K0 K1 T_0to1", 2 + 9 + 9 + 12: "K0 K1 R t", 2 + 9 + 9 + 16: "K0 K1 T_0to1"}


def pairs_files(folder: Path) -> list[Path]:
    """The pairs lists in ``folder``: ``pairs_with_gt.txt`` or ``pairs_calibrated.txt`` alone when there, else every
    ``*pairs_with_gt*.txt`` and ``*pairs_calibrated*.txt`` (sorted)."""
    folder = Path(folder)
    for name in (DEFAULT_FILE, CALIBRATED_FILE):
        if (folder / name).is_file():
            return [folder / name]
    if not folder.is_dir():
        return []
    return sorted({p for pattern in ("*pairs_with_gt*.txt", "*pairs_calibrated*.txt") for p in folder.glob(pattern)
                   if p.is_file()})


def find_pairs_file(folder: Path) -> Path | None:
    """The folder's one pairs list (see :func:`pairs_files`); None if there is none; ImtuneError naming them if there
    are several (it was read as a plain image folder, whose advice, SfM, replaced the lists' ground truth)."""
    found = pairs_files(folder)
    if len(found) > 1:
        raise ImtuneError(f"{folder} holds several pairs lists ({', '.join(p.name for p in found)}): a scene is one "
                          f"list; keep one there (or name it {DEFAULT_FILE}), the others in folders of their own")
    return found[0] if found else None


def _is_scene(p: Path) -> bool:
    return bool(pairs_files(p))


def detect(root: Path) -> bool:
    return bool(scene_dirs(root, _is_scene))


def list_scenes(root: Path) -> list[str]:
    return list(scene_dirs(root, _is_scene))


def read_pairs_file(path: Path) -> list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray]]:
    """Parse the list: [(name0, name1, K0, K1, T_0to1 4x4)]. Blank lines and ``#`` comments are skipped;
    a malformed line raises ImtuneError naming the file and the line number. A pair listed twice (also as
    ``b a`` after ``a b``) would count twice in every mAA, and a line pairing an image with itself has no
    relative pose to estimate: both make the list malformed (the error names the line numbers)."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ImtuneError(f"cannot read pairs file {path}: {e}") from None
    out = []
    first_line: dict[frozenset, int] = {}  # {name0, name1} -> the line that listed the pair first
    for lineno, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}, line {lineno}"
        tokens = line.split()
        if len(tokens) not in _FIELDS:
            raise ImtuneError(f"{where}: expected 2 names and {_NUMS} numbers (name0 name1 rot0 rot1 K0 K1 T_0to1), "
                              f"or 30 or 34 (name0 name1 K0 K1 R t, or K0 K1 T_0to1), found {len(tokens)} fields")
        if tokens[0] == tokens[1]:
            raise ImtuneError(f"{where}: pairs image {tokens[0]} with itself (a pair needs two images): remove the "
                              "line")
        key = frozenset(tokens[:2])
        if key in first_line:
            raise ImtuneError(f"{path}, lines {first_line[key]} and {lineno}: the pair {tokens[0]} {tokens[1]} is "
                              "listed twice (in either order): keep one of the lines")
        first_line[key] = lineno
        v = parse_floats(" ".join(tokens[2:]), len(tokens) - 2, where)
        if len(tokens) == 2 + _NUMS:
            if v[0] != 0 or v[1] != 0:
                raise ImtuneError(f"{where}: EXIF rotation codes {v[0]:g} {v[1]:g} are not supported (only 0)")
            v = v[2:]
        K0, K1 = check_K(v[0:9], f"{where} (K0)"), check_K(v[9:18], f"{where} (K1)")
        if len(v) == 9 + 9 + 12:  # R (9) t (3)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = v[18:27].reshape(3, 3), v[27:30]
        else:
            T = v[18:34].reshape(4, 4)
        if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6:
            raise ImtuneError(f"{where}: T_0to1 last row must be 0 0 0 1")
        check_rotation(T[:3, :3], f"{where} (T_0to1)", tol=1e-3)
        out.append((tokens[0], tokens[1], K0, K1, T))
    return out


def _resolve(root: Path, name: str) -> Path:
    for cand in (root / "images" / name, root / name):
        if cand.is_file():
            return cand
    return root / "images" / name


def load_pairs_with_gt(root: Path, scene: str | None = None, pairs_file: Path | None = None,
                       verify: bool = True) -> Scene:
    """Load a pairs-with-GT list as a stereo-only Scene (per-pair R, t and K; image K from the first listing).

    ``root``: the folder holding the list (or a folder of such folders, with ``scene``); ``pairs_file`` overrides
    the list's location. ``verify`` checks every image exists and is complete, and reads its size.
    """
    root = Path(root)
    if pairs_file is not None:
        sdir, name = root, scene or root.name
        pfile: Path | None = Path(pairs_file)
    else:
        dirs = scene_dirs(root, _is_scene)
        name = pick_scene(root, scene, list(dirs), NAME)
        sdir = dirs[name]
        pfile = find_pairs_file(sdir)
    if pfile is None or not pfile.is_file():
        raise ImtuneError(f"pairs file not found: {pfile or sdir}")
    rows = read_pairs_file(pfile)
    if not rows:
        raise ImtuneError(f"no pairs in {pfile}")
    images: dict[str, ImageInfo] = {}
    pairs: list[Pair] = []
    for n0, n1, K0, K1, T in rows:
        for n, K in ((n0, K0), (n1, K1)):
            if n not in images:
                path = _resolve(sdir, n)
                size = None
                if verify:
                    check_image_file(path)
                    size = image_size(path)
                images[n] = ImageInfo(name=n, path=path, K=K, size=size)
            if verify:
                size = images[n].size
                assert size is not None  # read above whenever verify is set
                check_principal_point(K, size, images[n].path)
        pairs.append(Pair(n0, n1, R=T[:3, :3].copy(), t=T[:3, 3].copy(), K_i=K0, K_j=K1))
    return Scene(name=name, root=sdir, images=images, pairs=pairs, source=NAME)


load = load_pairs_with_gt
