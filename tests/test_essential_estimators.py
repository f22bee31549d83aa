"""Calibrated (E) estimators and SupeRANSAC F on synthetic two-view scenes with known poses and inliers."""
import numpy as np
import pytest

from pipeline.config import GeometryConfig, MatchConfig, PipelineConfig
from pipeline.errors import ImtuneError
from pipeline.geometry import ESTIMATORS, get_estimator
from pipeline.metrics.pose import pose_error_deg
from pipeline.tasks.stereo import evaluate_pair, pose_from_F
from tests.test_stereo_synthetic import _portrait_two_view, _scene_and_features, synthetic_two_view

E_NAMES = ["poselib-e", "cv-e-ransac", "cv-e-magsac", "colmap-e", "superansac-e"]
SIZES = ((1024, 768), (1024, 768))


def _pose(name, x1, x2, K1, K2, eta=1.0, sizes=SIZES):
    """(R, t, result) as the stereo task gets them: E's own pose, or F -> E -> recoverPose."""
    est = get_estimator(name)
    if est.model == "E":
        res = est.estimate(x1, x2, eta, 0.999999, 10000, seed=0, sizes=sizes, K1=K1, K2=K2)
        return res.R, res.t, res
    res = est.estimate(x1, x2, eta, 0.999999, 10000, seed=0, sizes=sizes)
    R, t = pose_from_F(res.F, K1, K2, x1[res.inliers], x2[res.inliers]) if res.ok else (None, None)
    return R, t, res


def test_names_and_models():
    for n in E_NAMES:
        assert ESTIMATORS.get(n).model == "E", n
    for n in ("superansac", "degensac", "poselib", "colmap", "cv-magsac"):
        assert ESTIMATORS.get(n).model == "F", n


@pytest.mark.parametrize("outliers", [0.0, 0.5])
@pytest.mark.parametrize("name", [*E_NAMES, "superansac"])
def test_recovers_the_pose_on_clean_correspondences(name, outliers):
    """Exact calibrated correspondences (no noise), two different cameras, 0% and 50% random outliers: the pose
    to < 0.1 deg (measured: 1e-6 to 0.06 deg; poselib-e and colmap-e are the largest at 50% outliers, where one
    random outlier falls within 1 px of its epipolar line and enters their final refinement)."""
    K1, K2, R, t, x1, x2, _ = synthetic_two_view(n=600, outliers=outliers, noise=0.0)
    # an estimator that takes no seed (SupeRANSAC) differs run to run, and at 50% outliers about 1 run in 150 ends
    # on a wrong model of ~40 inliers (measured: 2 of 300 runs; once in CI): the run of median error of 3 is
    # judged, so the test checks our wrapper, not the library's rare miss (2 misses in 3: p ~ 1.5e-4)
    runs = []
    for _ in range(1 if get_estimator(name).seedable else 3):
        R_est, t_est, res = _pose(name, x1.astype(float), x2.astype(float), K1, K2)
        assert R_est is not None, res
        runs.append((pose_error_deg(R, t, R_est, t_est)[0], res))
    err, res = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
    assert err < 0.1, [e for e, _ in runs]
    n_out = int(outliers * 600)
    assert res.inliers[n_out:].mean() > 0.99  # every true inlier kept
    assert res.inliers[:n_out].mean() < 0.02 if n_out else True  # the outliers rejected


@pytest.mark.parametrize("name", E_NAMES)
def test_threshold_is_in_pixels(name):
    """eta = 1 px on 0.5 px noise with non-square, off-centre K: the inliers are the true ones (recall >= 0.8,
    precision >= 0.97) and the pose is right. A threshold read as normalised (1.0 ~ 700 px) would accept the
    outliers; one divided twice by the focal length would keep almost nothing."""
    K1, K2, R, t, x1, x2, truth = _portrait_two_view(seed=3)
    # no seed (SupeRANSAC): its rare wrong model (see above; 1 run in 40 of this test) is not our wrapper's fault:
    # the run with the median inlier count of 3 is judged
    runs = [_pose(name, x1, x2, K1, K2, eta=1.0, sizes=((640, 1024), (640, 1024)))
            for _ in range(1 if get_estimator(name).seedable else 3)]
    R_est, t_est, res = sorted(runs, key=lambda r: int(r[2].inliers.sum()))[len(runs) // 2]
    assert res.ok
    inl = res.inliers
    assert inl[truth].mean() >= 0.8, inl[truth].mean()
    assert truth[inl].mean() >= 0.97, truth[inl].mean()
    assert pose_error_deg(R, t, R_est, t_est)[0] < 2.0
    # E and the F it implies agree with the returned pose: x2^T F x1 ~ 0 on the true inliers (px)
    from pipeline.geometry.base import sampson_distance
    assert np.median(sampson_distance(res.F, x1[truth], x2[truth])) < 1.0


@pytest.mark.parametrize("name", E_NAMES)
def test_refuses_a_pair_without_intrinsics(name):
    K1, K2, R, t, x1, x2, _ = synthetic_two_view(n=100, outliers=0.0, noise=0.0)
    est = get_estimator(name)
    for kw in ({}, {"K1": K1}, {"K1": K1, "K2": np.full((3, 3), np.nan)}):
        with pytest.raises(ImtuneError) as ei:
            est.estimate(x1, x2, 1.0, 0.999999, 1000, sizes=SIZES, **kw)
        msg = str(ei.value)
        assert "\n" not in msg and name in msg and "intrinsics" in msg


@pytest.mark.parametrize("name", E_NAMES)
def test_degenerate_input_is_a_failure(name):
    K1, K2, *_ = synthetic_two_view(n=10)
    est = get_estimator(name)
    res = est.estimate(np.zeros((4, 2)), np.zeros((4, 2)), 1.0, 0.99, 100, K1=K1, K2=K2)
    assert not res.ok and res.E is None and res.R is None and res.inliers.shape == (4,)


def test_stereo_task_takes_the_pose_from_E():
    """evaluate_pair with an E estimator: the record's pose is the estimator's own (not F -> E)."""
    from pipeline.matching.knn import knn_tables
    K1, K2, R, t, x1, x2, _ = synthetic_two_view()
    scene, fa, fb, d = _scene_and_features(K1, K2, R, t, x1, x2)
    tables = knn_tables(d, d, binary=False, k=2)
    conf = PipelineConfig(matching=MatchConfig(ratio=1.0, strategy="both"),
                          geometry=GeometryConfig(ransac="poselib-e", threshold=1.0, max_iters=5000))
    est = get_estimator("poselib-e")
    pr = evaluate_pair(scene, scene.pairs[0], fa, fb, tables, 0.0, conf, est)
    direct = est.estimate(pr.pts1, pr.pts2, 1.0, conf.geometry.confidence, 5000, seed=conf.geometry.seed,
                          sizes=pr.sizes, K1=pr.K1, K2=pr.K2)
    assert pr.record["failure"] is None and pr.record["err"] < 1.0
    assert np.allclose(pr.R, direct.R) and np.allclose(pr.t, direct.t)


@pytest.mark.parametrize("name,space", [("poselib-e", "degensac.yaml"), ("cv-e-ransac", "degensac.yaml"),
                                        ("colmap-e", "degensac.yaml"), ("cv-e-magsac", "magsac.yaml"),
                                        ("superansac-e", "magsac.yaml"), ("superansac", "magsac.yaml")])
def test_default_search_space(name, space):
    """E estimators take eta in px: the DEGENSAC-like (0.1-2 px) or, MAGSAC-scored, the MAGSAC-like (0.5-10 px) space."""
    from tuner.space import default_space_file, load_space
    assert default_space_file(name).name == space
    th = load_space(estimator=name).params["threshold"]
    assert (th.low, th.high) == ((0.1, 2.0) if space == "degensac.yaml" else (0.5, 10.0))
