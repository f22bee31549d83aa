"""The IMC 2025 score (pipeline.metrics.imc_score) on hand-computed answers, and against an independent
implementation that follows the challenge's metric code (tests/imc_reference_metric.py) on synthetic datasets."""
from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from pipeline.metrics.imc_score import OUTLIERS, score_dataset, within_counts
from tests import imc_reference_metric as ref

TH = (0.025, 0.05, 0.1, 0.2, 0.5, 1.0)


def _rot(seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.random(random_state=seed).as_matrix()


def _centres(n: int, seed: int, spread: float = 10.0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-spread, spread, size=(n, 3))


def _dataset(sizes: dict[str, int], outliers: int = 0, seed: int = 0):
    """Ground truth: scene -> image -> centre (each scene in its own frame), outliers without pose."""
    truth: dict[str, dict] = {}
    for k, (s, n) in enumerate(sizes.items()):
        c = _centres(n, seed + k)
        truth[s] = {f"{s}_{i:03d}.jpg": c[i] for i in range(n)}
    if outliers:
        truth[OUTLIERS] = {f"out_{i:03d}.jpg": None for i in range(outliers)}
    return truth


def _moved(centres: dict, s: float = 3.7, seed: int = 5, t=(4.0, -2.0, 1.5)) -> dict:
    R = _rot(seed)
    return {n: s * R @ c + np.asarray(t) for n, c in centres.items()}


def _score(truth, clusters):
    th = {s: TH for s in truth if s != OUTLIERS}
    return score_dataset(truth, clusters, th, dataset="d")


def _write(tmp_path, truth, clusters, name="d"):
    """The same data as the challenge's CSV files, for the reference implementation."""
    def pose(c):
        if c is None or not np.all(np.isfinite(c)):
            return ";".join(["nan"] * 9), ";".join(["nan"] * 3)
        R = _rot(11)  # any rotation: only the centre c = -R^T t counts
        t = -R @ np.asarray(c, float)
        return ";".join(repr(float(x)) for x in R.ravel()), ";".join(repr(float(x)) for x in t)
    gt_csv, sub_csv, th_csv = tmp_path / "gt.csv", tmp_path / "sub.csv", tmp_path / "th.csv"
    with open(gt_csv, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["dataset", "scene", "image", "rotation_matrix", "translation_vector"])
        for s, imgs in truth.items():
            for n, c in imgs.items():
                w.writerow([name, s, n, *pose(c)])
    with open(sub_csv, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["dataset", "scene", "image", "rotation_matrix", "translation_vector"])
        for cl, imgs in clusters.items():
            for n, c in imgs.items():
                w.writerow([name, cl, n, *pose(c)])
    with open(th_csv, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["dataset", "scene", "thresholds"])
        for s in truth:
            if s != OUTLIERS:
                w.writerow([name, s, ";".join(map(str, TH))])
    return ref.score(gt_csv, sub_csv, th_csv)


def _check(tmp_path, truth, clusters, score, maa, clus):
    got = _score(truth, clusters)
    assert got.mAA == pytest.approx(maa, abs=1e-12)
    assert got.clusterness == pytest.approx(clus, abs=1e-12)
    assert got.score == pytest.approx(score, abs=1e-12)
    r = _write(tmp_path, truth, clusters)
    assert r["mAA"] == pytest.approx(maa, abs=1e-9)
    assert r["clusterness"] == pytest.approx(clus, abs=1e-9)
    assert r["score"] == pytest.approx(score, abs=1e-9)
    return got


def test_perfect_reconstruction(tmp_path):
    truth = _dataset({"A": 10, "B": 8})
    got = _check(tmp_path, truth, {"c0": dict(truth["A"]), "c1": dict(truth["B"])}, 1.0, 1.0, 1.0)
    assert got.scenes["A"].numerator == 4 * (10 - 3) and got.scenes["B"].within == [8] * 6


def test_similarity_transformed_copy(tmp_path):
    truth = _dataset({"A": 10, "B": 8})
    _check(tmp_path, truth, {"c0": _moved(truth["A"]), "c1": _moved(truth["B"], s=0.01, seed=9)}, 1.0, 1.0, 1.0)


def test_one_scene_split_in_two_clusters(tmp_path):
    truth = _dataset({"A": 10, "B": 8})
    a = list(truth["A"].items())
    clusters = {"c0": dict(a[:6]), "c1": _moved(dict(a[6:])), "c2": dict(truth["B"])}
    # A matched to c0 (6 shared): 4 x (6 - 3) = 12; B: 4 x 5 = 20; mAA = 32 / (4 x (18 - 6)) = 2/3; clusters pure
    got = _check(tmp_path, truth, clusters, 0.8, 2 / 3, 1.0)
    assert got.scenes["A"].cluster == "c0" and got.scenes["A"].numerator == 12


def test_two_scenes_merged_into_one_cluster(tmp_path):
    truth = _dataset({"A": 10, "B": 8})
    merged = {**truth["A"], **_moved(truth["B"])}
    # each scene aligns on its own images: mAA 1; both matched to the 18-image cluster: clusterness 18 / 36
    _check(tmp_path, truth, {"c0": merged}, 2 / 3, 1.0, 0.5)


def test_outliers_registered(tmp_path):
    truth = _dataset({"A": 10, "B": 8}, outliers=4)
    outl = list(truth[OUTLIERS])
    c0 = {**truth["A"], outl[0]: np.array([1.0, 2.0, 3.0]), outl[1]: np.array([-4.0, 0.0, 2.0])}
    clusters = {"c0": c0, "c1": dict(truth["B"]), OUTLIERS: {n: np.full(3, math.nan) for n in outl[2:]}}
    got = _check(tmp_path, truth, clusters, 2 * 0.9 / 1.9, 1.0, 18 / 20)
    assert got.outliers_registered == 2


def test_nothing_registered(tmp_path):
    truth = _dataset({"A": 10, "B": 8})
    nan = np.full(3, math.nan)
    _check(tmp_path, truth, {OUTLIERS: {n: nan for s in truth.values() for n in s}}, 0.0, 0.0, 0.0)


def test_registered_without_pose_counts_for_clusters_not_for_maa(tmp_path):
    truth = _dataset({"A": 10})
    nan = np.full(3, math.nan)
    _check(tmp_path, truth, {"c0": {n: nan for n in truth["A"]}}, 0.0, 0.0, 1.0)


def test_misplaced_cameras_are_misses(tmp_path):
    truth = _dataset({"A": 10})
    pred = dict(truth["A"])
    for k, n in enumerate(list(pred)[7:]):  # 3 cameras 3 m off: within no threshold
        d = np.zeros(3)
        d[k] = 3.0
        pred[n] = pred[n] + d
    # 7 within at every threshold: numerator 4 x (7 - 3) = 16 over 4 x (10 - 3)
    got = _check(tmp_path, truth, {"c0": _moved(pred)}, 2 * (16 / 28) / (1 + 16 / 28), 16 / 28, 1.0)
    assert got.scenes["A"].within == [7] * 6


def test_displaced_cameras_count_at_the_larger_thresholds(tmp_path):
    truth = _dataset({"A": 10})
    pred = dict(truth["A"])
    for k, n in enumerate(list(pred)[7:]):  # 0.3 m off: within 0.5 and 1.0, not within 0.1
        d = np.zeros(3)
        d[k] = 0.3
        pred[n] = pred[n] + d
    got = _score(truth, {"c0": _moved(pred)})
    assert got.scenes["A"].within[2] == 7 and got.scenes["A"].within[4:] == [10, 10]
    r = _write(tmp_path, truth, {"c0": _moved(pred)})
    assert abs(got.score - r["score"]) < 1e-9 and abs(got.mAA - r["mAA"]) < 1e-9


def test_a_scene_sharing_no_image_is_matched_to_the_first_cluster(tmp_path):
    """The challenge's stable sort: an unregistered scene takes the first cluster written, whose size counts."""
    truth = _dataset({"A": 10, "B": 8})
    nan = np.full(3, math.nan)
    clusters = {"c0": dict(truth["B"]), OUTLIERS: {n: nan for n in truth["A"]}}
    _check(tmp_path, truth, clusters, 2 * (20 / 48) * 0.5 / (20 / 48 + 0.5), 20 / 48, 8 / 16)
    clusters = {OUTLIERS: {n: nan for n in truth["A"]}, "c0": dict(truth["B"])}
    _check(tmp_path, truth, clusters, 2 * (20 / 48) / (20 / 48 + 1), 20 / 48, 1.0)


def test_within_counts_needs_three_cameras():
    c = _centres(2, 0)
    assert within_counts(c, c, TH).tolist() == [0] * 6


@pytest.mark.parametrize("seed", [101, 202, 303])
def test_agrees_with_the_reference_on_unseen_synthetic_data(tmp_path, seed):
    """Random datasets (scene sizes, noise, splits, merges, outliers, unregistered images) never seen by the project:
    the product's score and the Kaggle-structured reference agree within 1e-6."""
    rng = np.random.default_rng(seed)
    sizes = {f"s{k}": int(rng.integers(4, 14)) for k in range(int(rng.integers(1, 4)))}
    truth = _dataset(sizes, outliers=int(rng.integers(0, 5)), seed=seed)
    clusters: dict[str, dict] = {}
    homeless: dict[str, np.ndarray] = {}
    for k, (s, imgs) in enumerate(truth.items()):
        names = list(imgs)
        rng.shuffle(names)
        if s == OUTLIERS:
            for n in names:
                clusters.setdefault(f"c{rng.integers(0, 3)}", {})[n] = rng.normal(size=3) * 5
            continue
        cut = int(rng.integers(1, len(names) + 1))
        noise = rng.choice([0.01, 0.08, 0.3, 0.7], size=len(names))
        moved = _moved({n: imgs[n] + rng.normal(size=3) * noise[i] for i, n in enumerate(names)},
                       s=float(rng.uniform(0.2, 5)), seed=seed + k)
        target = f"c{k % 3}"
        for i, n in enumerate(names):
            if i < cut:
                clusters.setdefault(target, {})[n] = moved[n]
            else:
                homeless[n] = np.full(3, math.nan) if rng.random() < 0.5 else moved[n]
    for n, c in homeless.items():
        clusters.setdefault(OUTLIERS if not np.all(np.isfinite(c)) else "c9", {})[n] = c
    got = _score(truth, clusters)
    r = _write(tmp_path, truth, clusters)
    assert abs(got.score - r["score"]) < 1e-6
    assert abs(got.mAA - r["mAA"]) < 1e-6
    assert abs(got.clusterness - r["clusterness"]) < 1e-6
