"""Bring your own matches: the official IMC benchmark's custom-match h5 files, as ``--matches custom:DIR``.

Layout (ubc-vision/image-matching-benchmark, ``import_features.py`` / ``submission_validator.py``): in
each scene folder beside ``keypoints.h5`` (see ``pipeline.features.custom_h5``), one file with a dataset per
image pair keyed ``"<keyA>-<keyB>"`` (image names without extension), shape (2, M) integer: row 0 indexes
the keypoints of image A, row 1 those of image B. The benchmark's validator expects keyA > keyB
(string order); either order is accepted here (the rows are swapped as needed), and (M, 2) is accepted too.

Files, first found wins: stereo ``matches_stereo_0.h5``, ``matches_stereo.h5``, ``matches.h5``; multiview
``matches_multiview.h5``, ``matches.h5`` (the benchmark's names: one ``matches.h5`` serves both tasks).

Custom matches skip the matcher (no k-NN search, no ratio test, strategy or distance filter); a
pre-filter, if set, still applies, then the estimator. The indices refer to *all* keypoints of
``keypoints.h5``: use them with ``--feature custom:DIR`` and a ``--num-features`` at least the largest
keypoint count (checked: a count mismatch is an error, never a silent misalignment).

Errors (one line naming the file and key): missing file, missing pair key, wrong shape, non-integer
indices, an index out of range, a match listed twice.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import ImtuneError
from pipeline.features.custom_h5 import PREFIX, folder_for, h5_file_present, image_keys, parse_custom
from pipeline.matching.knn import KnnTables

STEREO_FILES = ("matches_stereo_0.h5", "matches_stereo.h5", "matches.h5")
MULTIVIEW_FILES = ("matches_multiview.h5", "matches.h5")

_MEMO: dict[tuple, Any] = {}  # file identity + pair / image -> parsed content (a count, or (matches, key))


@dataclass
class CustomTables(KnnTables):
    """Stand-in for a pair's k-NN tables when the matches are imported: ``matches`` (M, 2) holds them
    exactly (``pipeline.tasks.prepare.tentative_matches`` reads it). The tables themselves encode each match
    as a nearest neighbour at distance 0 with no second neighbour, so ``filter_matches`` on them (any r)
    returns the same matches for the strategies "both" and "uni" when they are one-to-one (callers that
    use ``filter_matches`` directly see a subset otherwise)."""
    matches: np.ndarray | None = None

    @classmethod
    def from_matches(cls, m: np.ndarray, n1: int, n2: int, k: int = 2) -> CustomTables:
        m = np.asarray(m, np.int64).reshape(-1, 2)
        idx12 = np.full((n1, k), -1, np.int32)
        idx21 = np.full((n2, k), -1, np.int32)
        d12 = np.full((n1, k), np.inf, np.float32)
        d21 = np.full((n2, k), np.inf, np.float32)
        idx12[m[:, 0], 0] = m[:, 1]
        idx21[m[:, 1], 0] = m[:, 0]
        d12[m[:, 0], 0] = 0.0
        d21[m[:, 1], 0] = 0.0
        return cls(idx12, d12, idx21, d21, matches=m.astype(np.int32))


def parse_matches_source(value: str | None) -> str | None:
    """``custom:DIR`` -> absolute DIR (as a string, for MatchConfig.custom_matches); None/"" -> None."""
    if value is None or value == "" or value == "none":
        return None
    if not str(value).startswith(PREFIX):
        raise ImtuneError(f"--matches: expected custom:DIR, got {value!r}")
    return str(parse_custom(str(value)))


def match_file(root: Path | str, image_path, scene: str | None = None, task: str = "stereo") -> Path:
    """The match file of the scene holding ``image_path`` under ``root``."""
    names = STEREO_FILES if task == "stereo" else MULTIVIEW_FILES
    folder = folder_for(Path(root), image_path, scene, marker=names, what=" or ".join(names))
    for n in names:  # a folder or FIFO at a preferred name is said, not passed over for the next (matches.h5)
        if h5_file_present(folder / n):
            return folder / n
    raise ImtuneError(f"{folder}: none of {', '.join(names)}")  # pragma: no cover - folder_for found one


def _keypoint_count(folder: Path, name: str) -> int | None:
    """Number of keypoints of image ``name`` in the folder's keypoints.h5 (None if absent)."""
    import h5py
    p = folder / "keypoints.h5"
    if not p.is_file():
        return None
    st = p.stat()
    memo = ("count", str(p), st.st_size, st.st_mtime_ns, name)
    if memo not in _MEMO:
        n = None
        with h5py.File(p, "r") as f:
            for k in image_keys(name):
                if k in f and hasattr(f[k], "shape"):
                    n = int(f[k].shape[0])
                    break
        _MEMO[memo] = n
    return _MEMO[memo]


def _read_pair(path: Path, name_i: str, name_j: str) -> tuple[np.ndarray, str]:
    """(M, 2) int64 [i, j] from the file (memoised on the file's identity), and the key used."""
    import h5py
    st = path.stat()
    memo = (str(path), st.st_size, st.st_mtime_ns, name_i, name_j)
    if memo in _MEMO:
        return _MEMO[memo]
    ki, kj = image_keys(name_i)[0], image_keys(name_j)[0]
    cands = [(f"{a}-{b}", False) for a in image_keys(name_i) for b in image_keys(name_j)]
    cands += [(f"{b}-{a}", True) for a in image_keys(name_i) for b in image_keys(name_j)]
    try:
        with h5py.File(path, "r") as f:
            hit = next(((k, sw) for k, sw in cands if k in f and hasattr(f[k], "shape")), None)
            if hit is None:
                raise ImtuneError(f"{path}: no key {ki}-{kj} (nor {kj}-{ki}) for pair {name_i}, {name_j}")
            key, swap = hit
            a = np.asarray(f[key][()])
    except OSError as e:
        raise ImtuneError(f"{path}: not a readable h5 file ({str(e).splitlines()[0]})") from None
    if a.ndim != 2 or (a.shape[0] != 2 and a.shape[1] != 2):
        raise ImtuneError(f"{path}: key {key!r}: matches must be (2, M) indices, got shape {a.shape}")
    if a.shape[0] != 2:
        a = a.T
    if a.size and not np.issubdtype(a.dtype, np.integer):
        if not (np.issubdtype(a.dtype, np.floating) and np.all(np.isfinite(a)) and np.all(a == np.round(a))):
            raise ImtuneError(f"{path}: key {key!r}: match indices must be integers, got {a.dtype}")
    a = a.astype(np.int64)
    uniq, first, counts = np.unique(a.T, axis=0, return_index=True, return_counts=True)
    if len(uniq) < a.shape[1]:  # each copy counted in NM and NI and weighed again by the estimator
        d = int(np.argmin(np.where(counts > 1, first, a.shape[1])))
        raise ImtuneError(f"{path}: key {key!r}: {a.shape[1] - len(uniq)} duplicate matches (e.g. {int(uniq[d, 0])}, "
                          f"{int(uniq[d, 1])} listed {int(counts[d])} times): list each match once")
    if swap:
        a = a[::-1]
    _MEMO[memo] = (np.ascontiguousarray(a.T), key)
    return _MEMO[memo]


def load_pair_matches(root: Path | str, name_i: str, name_j: str, path_i, n_i: int, n_j: int,
                      scene: str | None = None, task: str = "stereo") -> np.ndarray:
    """(M, 2) int32 matches [index in image i, index in image j] of the pair from the custom files.

    n_i, n_j: keypoint counts of the features in use (every index must be below them, and they must
    equal the counts in keypoints.h5 when that file is there)."""
    path = match_file(root, path_i, scene, task)
    m, key = _read_pair(path, name_i, name_j)
    for n, nm in ((n_i, name_i), (n_j, name_j)):
        c = _keypoint_count(path.parent, nm)
        if c is not None and c != n:
            raise ImtuneError(f"{path}: custom matches index the {c} keypoints of {path.parent / 'keypoints.h5'} "
                              f"for image {nm}, but the feature in use has {n}: use --feature custom:DIR "
                              f"with --num-features >= {c}")
    for col, n, nm in ((0, n_i, name_i), (1, n_j, name_j)):
        bad = m[:, col][(m[:, col] < 0) | (m[:, col] >= n)]
        if len(bad):
            raise ImtuneError(f"{path}: key {key!r}: match index {int(bad[0])} out of range for image {nm} "
                              f"({n} keypoints; {len(bad)} bad indices)")
    return m.astype(np.int32)
