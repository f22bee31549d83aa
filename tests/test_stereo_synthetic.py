"""The stereo task's geometry on synthetic scenes with known poses."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.config import GeometryConfig, MatchConfig, PipelineConfig
from pipeline.data.scene import ImageInfo, Pair, Scene
from pipeline.metrics.pose import pose_error_deg
from pipeline.tasks.prepare import ImageFeatures
from pipeline.tasks.stereo import evaluate_pair, pose_from_F


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def synthetic_two_view(n=600, outliers=0.3, noise=0.3, seed=0, rot_deg=20.0):
    rng = np.random.default_rng(seed)
    K1 = np.array([[800.0, 0, 511.5], [0, 800.0, 383.5], [0, 0, 1]])
    K2 = np.array([[760.0, 0, 500.0], [0, 770.0, 390.0], [0, 0, 1]])
    R = Rotation.from_rotvec(np.radians(rot_deg) * np.array([0.1, 1.0, 0.05]) / np.linalg.norm([0.1, 1.0, 0.05])).as_matrix()
    t = np.array([-1.0, 0.1, 0.2])
    X = np.c_[rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(6, 12, n)]
    x1 = (K1 @ X.T).T
    x1 = x1[:, :2] / x1[:, 2:]
    Xc2 = (R @ X.T).T + t
    x2 = (K2 @ Xc2.T).T
    x2 = x2[:, :2] / x2[:, 2:]
    x1 += rng.normal(0, noise, x1.shape)
    x2 += rng.normal(0, noise, x2.shape)
    n_out = int(outliers * n)
    x2[:n_out] = np.c_[rng.uniform(0, 1024, n_out), rng.uniform(0, 768, n_out)]
    F = np.linalg.inv(K2).T @ skew(t) @ R @ np.linalg.inv(K1)
    return K1, K2, R, t, x1.astype(np.float32), x2.astype(np.float32), F / np.linalg.norm(F)


def test_pose_from_true_F_recovers_the_pose():
    K1, K2, R, t, x1, x2, F = synthetic_two_view(outliers=0.0, noise=0.0)
    R_est, t_est = pose_from_F(F, K1, K2, x1.astype(float), x2.astype(float))
    err, er, et = pose_error_deg(R, t, R_est, t_est)
    assert err < 0.01, (er, et)


def test_pose_from_transposed_F_is_wrong():
    # guards the x2^T F x1 convention: the transpose must not give the right pose
    K1, K2, R, t, x1, x2, F = synthetic_two_view(outliers=0.0, noise=0.0)
    R_est, t_est = pose_from_F(F.T, K1, K2, x1.astype(float), x2.astype(float))
    assert pose_error_deg(R, t, R_est, t_est)[0] > 1.0


class _Tables:
    pass


def _scene_and_features(K1, K2, R, t, x1, x2):
    scene = Scene("syn", root=None, images={
        "a": ImageInfo("a", path=None, K=K1, size=(1024, 768)),
        "b": ImageInfo("b", path=None, K=K2, size=(1024, 768))},
        pairs=[Pair("a", "b", R=R, t=t)])
    rng = np.random.default_rng(1)
    d = rng.normal(size=(len(x1), 32)).astype(np.float32)
    fa = ImageFeatures("ka", x1, d, False, 1.0, 1.0, 1024, 768, 0.0)
    fb = ImageFeatures("kb", x2, d, False, 1.0, 1.0, 1024, 768, 0.0)
    return scene, fa, fb, d


@pytest.mark.parametrize("ransac,eta", [("degensac", 1.0), ("magsac++", 2.0), ("cv-usac", 1.0)])
def test_evaluate_pair_end_to_end_on_synthetic_matches(ransac, eta):
    from pipeline.geometry import get_estimator
    from pipeline.matching.knn import knn_tables
    K1, K2, R, t, x1, x2, _ = synthetic_two_view()
    scene, fa, fb, d = _scene_and_features(K1, K2, R, t, x1, x2)
    tables = knn_tables(d, d, binary=False, k=2)  # identical descriptors: match i <-> i
    conf = PipelineConfig(matching=MatchConfig(ratio=1.0, strategy="both"),
                          geometry=GeometryConfig(ransac=ransac, threshold=eta, max_iters=5000))
    est = get_estimator(ransac)
    # an unseedable backend (MAGSAC++) draws its own samples: its pose error has a rare tail (3.8 deg once in
    # CI, against a 0.9 deg 90th percentile over 40 runs), so its error is the median of 5 independent runs
    runs = [evaluate_pair(scene, scene.pairs[0], fa, fb, tables, 0.0, conf, est)
            for _ in range(1 if est.seedable else 5)]
    pr = sorted(runs, key=lambda r: r.record["err"])[len(runs) // 2]
    rec = pr.record
    # the PairResult carries what the record summarises: the inliers it counted, the pose it scored
    assert pr.F is not None and int(pr.inliers.sum()) == rec["NI"] and len(pr.matches) == rec["NM"]
    assert pr.R is not None and pr.t is not None
    assert rec["failure"] is None
    assert rec["NM"] == len(x1)
    assert 0.6 * len(x1) <= rec["NI"] <= 0.8 * len(x1)  # 70% are inliers
    assert rec["err"] < 3.0, rec  # 0.3 px noise, ~1:9 baseline-to-depth


def test_too_few_matches_is_a_recorded_failure():
    from pipeline.geometry import get_estimator
    from pipeline.matching.knn import knn_tables
    K1, K2, R, t, x1, x2, _ = synthetic_two_view(n=6, outliers=0.0)
    scene, fa, fb, d = _scene_and_features(K1, K2, R, t, x1, x2)
    conf = PipelineConfig(matching=MatchConfig(ratio=1.0))
    rec = evaluate_pair(scene, scene.pairs[0], fa, fb, knn_tables(d, d, binary=False, k=2), 0.0, conf,
                        get_estimator("degensac")).record
    assert math.isinf(rec["err"]) and "fewer than 8" in rec["failure"]


def _portrait_two_view(seed, n=700, outliers=0.3, noise=0.5):
    """A portrait 640 x 1024 pair, non-square pixels and principal points off centre, known pose and inliers."""
    rng = np.random.default_rng(seed)
    K1 = np.array([[700.0, 0, 300.0], [0, 690.0, 540.0], [0, 0, 1]])
    K2 = np.array([[650.0, 0, 340.0], [0, 660.0, 500.0], [0, 0, 1]])
    R = Rotation.from_rotvec(np.radians(rng.uniform(-12, 12, 3))).as_matrix()
    t = -R @ np.array([rng.uniform(1.5, 2.5), rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4)])
    X = np.c_[rng.uniform(-3, 3, n), rng.uniform(-4, 4, n), rng.uniform(7, 13, n)]
    x1 = (K1 @ X.T).T
    x1 = x1[:, :2] / x1[:, 2:]
    x2 = (K2 @ ((R @ X.T).T + t).T).T
    x2 = x2[:, :2] / x2[:, 2:]
    ok = (x1[:, 0] > 0) & (x1[:, 0] < 640) & (x1[:, 1] > 0) & (x1[:, 1] < 1024) & \
         (x2[:, 0] > 0) & (x2[:, 0] < 640) & (x2[:, 1] > 0) & (x2[:, 1] < 1024)
    x1, x2 = x1[ok] + rng.normal(0, noise, (ok.sum(), 2)), x2[ok] + rng.normal(0, noise, (ok.sum(), 2))
    out = rng.choice(len(x1), int(outliers * len(x1)), replace=False)
    x2[out] = np.c_[rng.uniform(0, 640, len(out)), rng.uniform(0, 1024, len(out))]
    truth = np.ones(len(x1), bool)
    truth[out] = False
    return K1, K2, R, t, x1, x2, truth


@pytest.mark.parametrize("ransac", ["pyransac", "degensac", "magsac", "magsac++", "gcransac", "cv-ransac", "cv-usac",
                                    "cv-magsac", "cv-accurate", "poselib", "colmap"])
def test_every_estimator_recovers_a_known_pose_with_true_inliers(ransac):
    """Each estimator as the pipeline calls it (estimate at eta = 1 px, Gamma 10k, then pose_from_F on its inliers)
    on a portrait pair with non-square, off-centre K, 0.5 px noise and 30% outliers. Measured (3 scenes each): pose
    error 0.09-2.6 deg (pyransac and cv-ransac the largest), inlier precision >= 0.99, recall 0.85-0.97 and 0.72 for
    cv-ransac (its eta bounds the epipolar-line distance in both images: its inliers' Sampson distance <= 0.7 eta);
    the inliers' Sampson distance is <= eta (poselib's mask is scored before its final refinement: 1.02 eta).
    pymagsac and pygcransac take no seed, so their pose error is a random variable: each scene is solved 8 times and
    the bound is on the median of the 24 errors, with at most 2 above 6 deg. Measured for magsac++ (100 runs per
    scene): median 0.65-1.34 deg, 90th percentile 1.6-2.9, max 6.7; a median of 3 single runs was >= 2 deg in 10%
    of runs (the CI failure of Dec 2026), the rule below failed in none of 20,000 bootstrap draws."""
    from pipeline.geometry import get_estimator
    from pipeline.geometry.base import sampson_distance
    est = get_estimator(ransac)
    draws = 1 if est.seedable else 8
    errs = []
    for seed in range(3):
        K1, K2, R, t, x1, x2, truth = _portrait_two_view(seed)
        for _ in range(draws):
            res = est.estimate(x1, x2, 1.0, 0.999999, 10000, seed=0, sizes=((640, 1024), (640, 1024)))
            assert res.F is not None
            inl = res.inliers
            assert (inl & truth).sum() >= 0.98 * inl.sum() and (inl & truth).sum() >= 0.6 * truth.sum()
            d = sampson_distance(res.F, x1, x2)[inl]
            assert d.max() <= (1.15 if ransac == "poselib" else 1.0) + 1e-6, d.max()
            R_est, t_est = pose_from_F(res.F, K1, K2, x1[inl], x2[inl])
            errs.append(pose_error_deg(R, t, R_est, t_est)[0])
    errs = np.asarray(errs)
    assert np.median(errs) < 2.0 and (errs >= 6.0).sum() <= (0 if draws == 1 else 2), errs
