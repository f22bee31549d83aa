"""An independent implementation of the IMC 2025 metric, for the tests only.

Written apart from ``pipeline.metrics.imc_score`` and following the structure of the challenge's published metric
code (Kaggle "image-matching-challenge-2025", ``imc25_metric``): CSV files in, a RANSAC-like loop over every camera
triplet with Horn's quaternion method for the minimal model and an SVD (Kabsch) refinement on its inliers, one best
model per threshold (more inliers, then a smaller summed squared error), a (scene x cluster) table of mAA and shared
images, a per-scene greedy choice by ``np.lexsort`` (most shared images, then mAA, then the first cluster), the
``outliers`` scene and cluster left out, clusterness and mAA summed over scenes, their harmonic mean per dataset, the
mean over datasets. The product's module computes the same numbers another way (all triplets batched, the per
threshold maximum of the refined models' inlier counts); the tests require them to agree within 1e-6.
"""
from __future__ import annotations

import csv
import math

import numpy as np


def read_rows(path) -> dict:
    """{dataset: {scene: {image: centre (3,)}}} in file order; the centre of a nan pose is nan."""
    data: dict = {}
    seen: set = set()
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            key = (row["dataset"], row["image"])
            assert key not in seen, f"{path}: image {row['image']} of {row['dataset']} is written twice"  # check_data
            seen.add(key)
            R = np.array([float(x) for x in row["rotation_matrix"].split(";")]).reshape(3, 3)
            t = np.array([float(x) for x in row["translation_vector"].split(";")])
            data.setdefault(row["dataset"], {}).setdefault(row["scene"], {})[row["image"]] = -R.T @ t
    return data


def read_thresholds(path) -> dict:
    out: dict = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            out.setdefault(row["dataset"], {})[row["scene"]] = np.array([float(x) for x in row["thresholds"].split(";")])
    return out


def _quaternion_rotation(q):
    q = np.array(q, float)
    n = q @ q
    if n < np.finfo(float).eps * 4:
        return np.eye(3)
    q *= math.sqrt(2.0 / n)
    q = np.outer(q, q)
    return np.array([[1 - q[2, 2] - q[3, 3], q[1, 2] - q[3, 0], q[1, 3] + q[2, 0]],
                     [q[1, 2] + q[3, 0], 1 - q[1, 1] - q[3, 3], q[2, 3] - q[1, 0]],
                     [q[1, 3] - q[2, 0], q[2, 3] + q[1, 0], 1 - q[1, 1] - q[2, 2]]])


def similarity(v0, v1, horn: bool):
    """4x4 similarity mapping the columns of v0 (3, n) onto v1: Horn's quaternion (``horn``) or SVD rotation, scale =
    ratio of the RMS spreads, centroids moved."""
    v0 = np.array(v0, float)
    v1 = np.array(v1, float)
    c0, c1 = v0.mean(axis=1, keepdims=True), v1.mean(axis=1, keepdims=True)
    v0, v1 = v0 - c0, v1 - c1
    if horn:
        xx, yy, zz = np.sum(v0 * v1, axis=1)
        xy, yz, zx = np.sum(v0 * np.roll(v1, -1, axis=0), axis=1)
        xz, yx, zy = np.sum(v0 * np.roll(v1, -2, axis=0), axis=1)
        N = np.array([[xx + yy + zz, 0, 0, 0], [yz - zy, xx - yy - zz, 0, 0], [zx - xz, xy + yx, yy - xx - zz, 0],
                      [xy - yx, zx + xz, yz + zy, zz - xx - yy]])
        w, V = np.linalg.eigh(N)  # lower triangle
        R = _quaternion_rotation(V[:, np.argmax(w)])
    else:
        u, _, vh = np.linalg.svd(v1 @ v0.T)
        R = u @ vh
        if np.linalg.det(R) < 0:
            R -= np.outer(u[:, 2], vh[2, :] * 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = math.sqrt(np.sum(v1 * v1) / np.sum(v0 * v0)) if np.sum(v0 * v0) > 0 else math.inf
    M = np.eye(4)
    M[:3, :3] = s * R
    M[:3, 3] = (c1 - s * R @ c0).ravel()
    return M


def register(ev, gt, th):
    """Best errors per camera and threshold (n_valid, r): the challenge's triplet loop (inl_cf 0, strict_cf -1)."""
    ok = np.all(np.isfinite(ev), axis=0)
    ev, gt = ev[:, ok], gt[:, ok]
    n, r = ev.shape[1], len(th)
    th2 = np.asarray(th)[None] ** 2
    ev1 = np.vstack([ev, np.ones(n)])
    max_inl = np.zeros(r)
    best_sum = np.full(r, np.inf)
    best_err = np.full((n, r), np.inf)
    for i in range(n - 2):
        for j in range(i + 1, n - 1):
            for k in range(j + 1, n):
                idx = [i, j, k]
                with np.errstate(invalid="ignore", over="ignore"):
                    M = similarity(ev[:, idx], gt[:, idx], horn=True)
                    err = np.sum((M[:3] @ ev1 - gt) ** 2, axis=0)
                inl = err[:, None] < th2
                cnt = inl.sum(axis=0)
                for q in np.argwhere(cnt > 2).ravel():
                    if any(np.array_equal(inl[:, q], inl[:, p]) for p in range(q)):
                        continue
                    with np.errstate(invalid="ignore", over="ignore"):
                        M = similarity(ev[:, inl[:, q]], gt[:, inl[:, q]], horn=False)
                        e = np.sum((M[:3] @ ev1 - gt) ** 2, axis=0)
                    esum = e.sum()
                    c = (e[:, None] < th2).sum(axis=0)
                    upd = (c > max_inl) | ((c == max_inl) & (esum < best_sum))
                    if upd.any():
                        max_inl[upd] = c[upd]
                        best_sum[upd] = esum
                        best_err[:, upd] = np.sqrt(e)[:, None]
    return best_err


def score(gt_csv, user_csv, thresholds_csv, skip: int = 2, to_dec: int = 3) -> dict:
    """{"score", "mAA", "clusterness"} (0..1, means over datasets) and per dataset the same."""
    gt, user, ths = read_rows(gt_csv), read_rows(user_csv), read_thresholds(thresholds_csv)
    per = {}
    for ds, gscenes in gt.items():
        uscenes = user[ds]
        gl, ul = list(gscenes), list(uscenes)
        maa = np.zeros((len(gl), len(ul)))
        shared = np.zeros((len(gl), len(ul)))
        usize = np.zeros((len(gl), len(ul)))
        errs: dict = {}
        for i, g in enumerate(gl):
            for j, u in enumerate(ul):
                if g == "outliers" or u == "outliers":
                    continue
                th = ths[ds][g]
                common = [im for im in gscenes[g] if im in uscenes[u]]
                ev = np.array([uscenes[u][im] for im in common], float).reshape(-1, 3).T
                gc = np.array([gscenes[g][im] for im in common], float).reshape(-1, 3).T
                e = register(ev, gc, th)
                within = (e[:, skip:] < th[skip:][None]).sum(axis=0)
                num = np.sum(np.maximum(within - to_dec, 0))
                m = len(gscenes[g])
                maa[i, j] = 0 if num == 0 else num / ((len(th) - skip) * (m - to_dec))
                shared[i, j] = len(common)
                usize[i, j] = len(uscenes[u])
                errs[i, j] = num
        a = b_scenes = n_total = 0
        sh = us = 0.0
        for i, g in enumerate(gl):
            if g == "outliers":
                continue
            best = np.lexsort((-maa[i], -shared[i]))[0]
            a += errs.get((i, best), 0)
            sh += shared[i, best]
            us += usize[i, best]
            n_total += len(gscenes[g])
            b_scenes += 1
            lt = len(ths[ds][g]) - skip
        denom = max(0, lt * (n_total - b_scenes * to_dec))
        m_aa = 0.0 if denom == 0 else a / denom
        clus = 0.0 if us == 0 else sh / us
        sc = 0.0 if m_aa + clus == 0 else 2 * m_aa * clus / (m_aa + clus)
        per[ds] = {"score": sc, "mAA": m_aa, "clusterness": clus}
    return {"score": float(np.mean([p["score"] for p in per.values()])),
            "mAA": float(np.mean([p["mAA"] for p in per.values()])),
            "clusterness": float(np.mean([p["clusterness"] for p in per.values()])), "datasets": per}
