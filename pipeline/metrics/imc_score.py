"""The Image Matching Challenge 2024 / 2025 reconstruction score: clustering-aware camera-centre mAA, clusterness and
their harmonic mean (the challenge's published metric, Kaggle "image-matching-challenge-2025").

A dataset mixes ground-truth scenes (and, under the scene name ``outliers``, images that belong to none); a
submission puts every image of the dataset into one predicted cluster (or ``outliers``) with a camera pose, ``nan``
where it was not registered. Only camera centres c = -R^T t matter.

Per ground-truth scene S and predicted cluster C, over the images they share with a finite predicted centre:

- for each threshold th (metres) of S, the predicted centres are aligned to the ground-truth ones by a similarity:
  every triplet of shared cameras gives a minimal alignment; its inliers at any threshold (distance < th, at least 3)
  give a refined least-squares alignment; ``within(th)`` is the most cameras any refined alignment brings within th
  (the challenge keeps one best model per threshold; its inlier count is this maximum);
- the first ``SKIP`` (2) of the 6 thresholds are skipped and ``DEDUCT`` (3) cameras, those that fix the alignment,
  are deducted: numerator(S, C) = sum over the remaining thresholds of max(0, within(th) - 3).

Each ground-truth scene (not ``outliers``) is matched to the cluster sharing the most images with it, ties broken by
the higher per-pair mAA (numerator / (4 (|S| - 3))), then by the cluster's position in the submission (the
challenge's stable sort: a scene sharing no image with any cluster is matched to the first cluster written; a
cluster named ``outliers`` shares nothing and has size 0). Over a dataset:

- mAA = sum of the matched numerators / (4 x (sum of |S| - 3 x number of scenes));
- clusterness = sum of the shared images / sum of the matched clusters' sizes (every image written under the cluster,
  registered or not);
- score = harmonic mean of mAA and clusterness (0 when both are 0).

The challenge's final score is the mean over datasets (x 100 in its print-out). Unregistered images are misses.

Alignment: the similarity (s, R, t) of a point set is the closed form of Horn / Umeyama with the challenge's scale
(the ratio of the root-mean-square spreads about the centroids), written here in numpy and batched over all
triplets at once: no library offers a batched similarity fit (scipy's ``Rotation.align_vectors`` fits one rotation,
without scale or translation, per call, which is ~1000x slower over the ~20k triplets of a 50-image scene).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SKIP = 2  # the first thresholds are skipped
DEDUCT = 3  # cameras that fix the alignment, deducted at every threshold
OUTLIERS = "outliers"
_CHUNK = 4096  # triplets aligned at once (memory: chunk x cameras x thresholds booleans)


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched similarity fits: src, dst (B, k, 3) -> scale (B,), R (B, 3, 3), t (B, 3) with dst ~ s R src + t.
    Scale: RMS spread of dst over that of src (the challenge's). A degenerate set (all points equal) gives a
    non-finite transform, hence no inliers."""
    ms, md = src.mean(axis=1, keepdims=True), dst.mean(axis=1, keepdims=True)
    xs, xd = src - ms, dst - md
    H = np.einsum("bki,bkj->bij", xd, xs)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    D = np.ones((len(src), 3))
    D[:, 2] = d
    R = np.einsum("bij,bj,bjk->bik", U, D, Vt)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sqrt((xd ** 2).sum(axis=(1, 2)) / (xs ** 2).sum(axis=(1, 2)))
    t = md[:, 0] - s[:, None] * np.einsum("bij,bj->bi", R, ms[:, 0])
    return s, R, t


def _squared_errors(s, R, t, pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(B, n) squared distances between the aligned predicted centres and the ground-truth ones."""
    with np.errstate(invalid="ignore", over="ignore"):
        moved = s[:, None, None] * np.einsum("bij,nj->bni", R, pred) + t[:, None, :]
        return ((moved - gt[None]) ** 2).sum(axis=2)


def within_counts(pred: np.ndarray, gt: np.ndarray, thresholds) -> np.ndarray:
    """For each threshold, the most cameras that one refined similarity alignment of the predicted centres ``pred``
    (n, 3; non-finite rows = unregistered, left out) brings within that distance of ``gt`` (n, 3). (r,) ints."""
    th2 = np.asarray(thresholds, float) ** 2
    pred = np.asarray(pred, float).reshape(-1, 3)
    gt = np.asarray(gt, float).reshape(-1, 3)
    ok = np.all(np.isfinite(pred), axis=1)
    pred, gt = pred[ok], gt[ok]
    n = len(pred)
    best = np.zeros(len(th2), int)
    if n < 3:
        return best
    import itertools
    triplets = np.array(list(itertools.combinations(range(n), 3)), dtype=np.intp)
    seen: set[bytes] = set()
    for a in range(0, len(triplets), _CHUNK):
        tri = triplets[a:a + _CHUNK]
        s, R, t = _similarity(pred[tri], gt[tri])
        err = _squared_errors(s, R, t, pred, gt)  # (B, n)
        inl = err[:, :, None] < th2[None, None, :]  # (B, n, r); NaN compares False
        sets = inl.transpose(0, 2, 1).reshape(-1, n)  # (B r, n)
        sets = sets[sets.sum(axis=1) > 2]
        if not len(sets):
            continue
        fresh = []
        for row in np.unique(np.packbits(sets, axis=1), axis=0):
            key = row.tobytes()
            if key not in seen:
                seen.add(key)
                fresh.append(np.unpackbits(row)[:n].astype(bool))
        for S in fresh:  # refine on each distinct inlier set, once
            s1, R1, t1 = _similarity(pred[S][None], gt[S][None])
            e = _squared_errors(s1, R1, t1, pred, gt)[0]
            best = np.maximum(best, (e[:, None] < th2[None, :]).sum(axis=0))
    return best


def numerator(counts, skip: int = SKIP, deduct: int = DEDUCT) -> int:
    """sum over the thresholds after the first ``skip`` of max(0, within - deduct)."""
    return int(sum(max(0, int(c) - deduct) for c in list(counts)[skip:]))


@dataclass
class SceneScore:
    """A ground-truth scene's figures: its size, the matched cluster (None: no cluster), the images they share, that
    cluster's size, the cameras within each threshold, the numerator and the scene's own mAA (numerator over
    4 x (size - 3))."""
    scene: str
    size: int
    cluster: str | None
    shared: int
    cluster_size: int
    registered: int  # shared images with a finite predicted pose
    within: list[int]
    numerator: int
    mAA: float

    @property
    def clusterness(self) -> float:
        """The scene's own share of its matched cluster (shared / cluster size; 0 without a cluster)."""
        return self.shared / self.cluster_size if self.cluster_size else 0.0

    def to_dict(self) -> dict:
        return {**self.__dict__, "clusterness": self.clusterness}


@dataclass
class DatasetScore:
    """A dataset's score (harmonic mean), mAA, clusterness, and its scenes' :class:`SceneScore`."""
    dataset: str
    score: float
    mAA: float
    clusterness: float
    scenes: dict[str, SceneScore] = field(default_factory=dict)
    clusters: dict[str, int] = field(default_factory=dict)  # cluster -> images written under it
    outliers_registered: int = 0  # ground-truth outlier images the submission put in a (non-outlier) cluster

    def to_dict(self) -> dict:
        return {"dataset": self.dataset, "score": self.score, "mAA": self.mAA, "clusterness": self.clusterness,
                "clusters": dict(self.clusters), "outliers_registered": self.outliers_registered,
                "scenes": {k: v.to_dict() for k, v in self.scenes.items()}}


def harmonic(a: float, b: float) -> float:
    return 0.0 if a + b == 0 else 2.0 * a * b / (a + b)


def score_dataset(truth: dict[str, dict[str, np.ndarray | None]], clusters: dict[str, dict[str, np.ndarray]],
                  thresholds: dict[str, list[float]], dataset: str = "", skip: int = SKIP,
                  deduct: int = DEDUCT) -> DatasetScore:
    """Score one dataset.

    truth: ground-truth scene -> image -> camera centre (3,) (the ``outliers`` scene's centres may be None);
    clusters: predicted cluster -> image -> predicted camera centre (3,), NaN where unregistered, in the order the
    submission writes them (it breaks ties); a cluster named ``outliers`` is no cluster;
    thresholds: scene -> thresholds in metres (the challenge's six).
    Every image must be in exactly one cluster (callers write unregistered images under ``outliers``)."""
    scenes = [s for s in truth if s != OUTLIERS]
    names = list(clusters)
    num_th = {s: len(thresholds[s]) - skip for s in scenes}
    out_images = set(truth.get(OUTLIERS, {}))
    result = DatasetScore(dataset=dataset, score=0.0, mAA=0.0, clusterness=0.0,
                          clusters={c: len(v) for c, v in clusters.items()},
                          outliers_registered=sum(1 for c, v in clusters.items() if c != OUTLIERS
                                                  for n in v if n in out_images))
    total_num, total_size, total_shared, total_cluster = 0, 0, 0, 0
    for s in scenes:
        gt_imgs = truth[s]
        m = len(gt_imgs)
        table: list[tuple] = []
        for k, c in enumerate(names):
            if c == OUTLIERS:
                table.append((0, 0.0, k, None))
                continue
            shared = [n for n in gt_imgs if n in clusters[c]]
            if shared:
                pred = np.array([clusters[c][n] for n in shared], float).reshape(-1, 3)
                gt = np.array([gt_imgs[n] for n in shared], float).reshape(-1, 3)
                counts = within_counts(pred, gt, thresholds[s])
            else:
                counts = np.zeros(len(thresholds[s]), int)
            num = numerator(counts, skip, deduct)
            denom = num_th[s] * (m - deduct)
            maa = num / denom if num and denom > 0 else 0.0
            table.append((len(shared), maa, k, (counts, num, shared)))
        if not table:
            result.scenes[s] = SceneScore(s, m, None, 0, 0, 0, [0] * len(thresholds[s]), 0, 0.0)
            total_size += m
            continue
        # the most shared images, then the higher mAA, then the first written (a stable sort on both keys)
        shared_n, maa, k, extra = min(table, key=lambda row: (-row[0], -row[1], row[2]))
        c = names[k]
        size = 0 if c == OUTLIERS else len(clusters[c])
        if extra is None:
            counts, num, shared = np.zeros(len(thresholds[s]), int), 0, []
        else:
            counts, num, shared = extra
        reg = sum(1 for n in shared if np.all(np.isfinite(np.asarray(clusters[c][n], float))))
        result.scenes[s] = SceneScore(s, m, c, shared_n, size, reg, [int(x) for x in counts], num, maa)
        total_num += num
        total_size += m
        total_shared += shared_n
        total_cluster += size
    lt = max(num_th.values()) if num_th else 0
    denom = max(0, lt * (total_size - len(scenes) * deduct))
    result.mAA = total_num / denom if denom > 0 and total_num else 0.0
    result.clusterness = total_shared / total_cluster if total_cluster else 0.0
    result.score = harmonic(result.mAA, result.clusterness)
    return result


def centre(R, t) -> np.ndarray:
    """Camera centre c = -R^T t of a world-to-camera pose (NaN when either is missing)."""
    if R is None or t is None:
        return np.full(3, math.nan)
    R = np.asarray(R, float).reshape(3, 3)
    return -R.T @ np.asarray(t, float).reshape(3)
