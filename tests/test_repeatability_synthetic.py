"""Repeatability and matching score from depth maps, and the epipolar matching score, on a synthetic
scene: a fronto-parallel plane seen by two cameras with known poses and exact depth maps."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.metrics.repeatability import (
    depth_at,
    epipolar_matching_score,
    load_depth,
    match_reprojection_errors,
    matching_score,
    pair_intermediate,
    repeatability,
    transfer,
)

W, H = 640, 480
K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


def plane_depth(R, t, n=(0.0, 0.0, 1.0), d=5.0):
    """Depth map of camera (R, t) viewing the world plane n . X = d."""
    n = np.asarray(n, dtype=float)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays_c = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    C = -R.T @ t
    rays_w = R.T @ rays_c
    lam = (d - n @ C) / (n @ rays_w)  # X = C + lam * ray, z_cam = lam (ray has z_cam = 1)
    return lam.reshape(H, W)


def two_views():
    R1, t1 = np.eye(3), np.zeros(3)
    R2 = Rotation.from_euler("y", 8, degrees=True).as_matrix()
    t2 = np.array([-0.6, 0.05, 0.1])
    R12 = R2 @ R1.T
    t12 = t2 - R12 @ t1
    return (R1, t1), (R2, t2), R12, t12


def world_points(n=400, seed=0):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), np.full(n, 5.0)]


def project(X, R, t):
    x = (K @ ((R @ X.T).T + t).T).T
    return x[:, :2] / x[:, 2:]


def test_depth_maps_are_consistent_with_projection():
    (R1, t1), (R2, t2), R12, t12 = two_views()
    D1 = plane_depth(R1, t1)
    X = world_points()
    x1 = project(X, R1, t1)
    ok = (x1[:, 0] > 1) & (x1[:, 0] < W - 2) & (x1[:, 1] > 1) & (x1[:, 1] < H - 2)
    z = depth_at(np.round(x1[ok]), D1)
    p, _ = transfer(np.round(x1[ok]), z, K, K, R12, t12)
    x2 = project(X[ok], R2, t2)
    assert np.median(np.linalg.norm(p - x2, axis=1)) < 0.8  # rounding of x1 only


def test_perfect_keypoints_are_fully_repeatable_and_matches_all_correct():
    (R1, t1), (R2, t2), R12, t12 = two_views()
    D1, D2 = plane_depth(R1, t1), plane_depth(R2, t2)
    X = world_points()
    x1, x2 = project(X, R1, t1), project(X, R2, t2)
    keep = (x1[:, 0] >= 0) & (x1[:, 0] < W) & (x1[:, 1] >= 0) & (x1[:, 1] < H) & \
           (x2[:, 0] >= 0) & (x2[:, 0] < W) & (x2[:, 1] >= 0) & (x2[:, 1] < H)
    x1, x2 = x1[keep], x2[keep]
    rep = repeatability(x1, x2, D1, D2, K, K, R12, t12, (W, H), (W, H))
    assert rep[2] > 0.97 and np.all(np.diff(rep) >= 0)
    m = np.c_[np.arange(len(x1)), np.arange(len(x1))]
    ms = matching_score(match_reprojection_errors(x1, x2, m, D1, D2, K, K, R12, t12))
    assert ms[2] > 0.97
    assert epipolar_matching_score(x1, x2, m, K, K, R12, t12) == 1.0


def test_noise_and_wrong_matches_lower_the_scores_by_the_right_amount():
    (R1, t1), (R2, t2), R12, t12 = two_views()
    D1, D2 = plane_depth(R1, t1), plane_depth(R2, t2)
    rng = np.random.default_rng(1)
    X = world_points(600, seed=2)
    x1, x2 = project(X, R1, t1), project(X, R2, t2)
    keep = (x1.min(1) >= 0) & (x1[:, 0] < W) & (x1[:, 1] < H) & (x2.min(1) >= 0) & (x2[:, 0] < W) & (x2[:, 1] < H)
    x1, x2 = x1[keep], x2[keep] + rng.normal(0, 2.0, (keep.sum(), 2))  # 2 px noise in image 2
    n = len(x1)
    m = np.c_[np.arange(n), np.arange(n)]
    m[: n // 4, 1] = rng.permutation(n)[: n // 4]  # a quarter of the matches wrong
    res = pair_intermediate(x1, x2, m, K, K, R12, t12, (W, H), (W, H), D1, D2)
    rep, ms = np.array(res["repeatability"]), np.array(res["matching_score"])
    assert rep[0] < rep[4] and rep[9] > 0.9           # 2 px noise: few within 1 px, nearly all within 10
    assert 0.6 < ms[9] < 0.8                          # ~3/4 of matches correct at 10 px
    assert res["epipolar_matching_score"] < 0.8
    assert res["thresholds_px"] == list(range(1, 11))


def test_without_depth_only_the_epipolar_score():
    (R1, t1), (R2, t2), R12, t12 = two_views()
    X = world_points()
    x1, x2 = project(X, R1, t1), project(X, R2, t2)
    m = np.c_[np.arange(len(x1)), np.arange(len(x1))]
    res = pair_intermediate(x1, x2, m, K, K, R12, t12, (W, H), (W, H))
    assert set(res) == {"thresholds_px", "epipolar_matching_score"}
    assert res["epipolar_matching_score"] == 1.0
    assert pair_intermediate(x1, x2, np.zeros((0, 2), int), K, K, R12, t12, (W, H), (W, H))["epipolar_matching_score"] == 0.0


def test_depth_lookup_with_resolution_change_and_invalid_depth():
    D = np.arange(12, dtype=float).reshape(3, 4)
    D[0, 0] = 0
    # keypoints at half resolution (2 x 1.5 px image): working px = (disk + 0.5) * 0.5 - 0.5
    z = depth_at(np.array([[-0.25, -0.25], [1.25, 0.75], [-5, 0]]), D, depth_scale=(0.5, 0.5))
    assert z[0] == 0 and z[1] == D[2, 3] and z[2] == 0


def test_load_depth_h5(tmp_path):
    import h5py
    p = tmp_path / "d.h5"
    with h5py.File(p, "w") as f:
        f["depth"] = np.ones((4, 5))
    assert load_depth(p).shape == (4, 5)
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"nope")
    from pipeline.errors import ImtuneError
    with pytest.raises(ImtuneError, match="bad.h5"):
        load_depth(bad)
