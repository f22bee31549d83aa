"""Robust estimators on synthetic two-view scenes with known poses (pipeline.geometry).

The scene: 3D points in front of two 1024x768 cameras (f = 800 px), a 15-25 deg relative rotation
and a unit baseline; projections with 0.3 px Gaussian noise, plus 40% outliers drawn uniformly in
both images. Every available estimator must recover F (x2^T F x1 = 0), mark the true inliers, and
give the relative pose (E = K2^T F K1 -> recoverPose) within a couple of degrees.
No timing thresholds here (see benchmarks/ for figures).
"""
from __future__ import annotations

import sys

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from pipeline.errors import ImtuneError, UnavailableError  # noqa: E402
from pipeline.geometry import ESTIMATORS, estimate, get_estimator, sampson_distance  # noqa: E402
from pipeline.geometry.base import (  # noqa: E402
    EstimateResult,
    Estimator,
    RawSolution,
    sizes_from_points,
    timed,
)

W, H, FOCAL = 1024, 768, 800.0
# the F estimators (the E estimators need K1, K2: tests/test_essential_estimators.py)
AVAILABLE = [n for n, (ok, _) in ESTIMATORS.availability().items() if ok and ESTIMATORS.get(n).model == "F"]
THRESHOLD_FREE = {"cv-lmeds", "cv-8pt"}
ROBUST = [n for n in AVAILABLE if n not in THRESHOLD_FREE]


# -- synthetic scenes --------------------------------------------------------------------------
def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.deg2rad(deg)
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k


def make_scene(n_in: int = 720, n_out: int = 480, noise: float = 0.3, deg: float = 20.0, seed: int = 0,
               K2: np.ndarray | None = None, size2: tuple[int, int] = (W, H)):
    """(x1, x2, is_inlier, K1, K2, R, t, F_true): x1 ~ K1 [I | 0] X in a W x H image, x2 ~ K2 [R | t] X
    in a ``size2`` image (K2 defaults to K1); |t| = 1; F_true normalised, x2^T F x1 = 0."""
    rng = np.random.default_rng(seed)
    K1 = np.array([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]])
    K2 = K1 if K2 is None else K2
    R = _rotation(rng.normal(size=3), deg)
    t = np.array([1.0, 0.15, 0.25])
    t /= np.linalg.norm(t)
    rows = []
    while sum(len(r) for r in rows) < n_in:
        X = np.c_[rng.uniform(-4, 4, 4000), rng.uniform(-3, 3, 4000), rng.uniform(3, 12, 4000)]
        X2 = X @ R.T + t
        p1 = X @ K1.T
        p2 = X2 @ K2.T
        p1 = p1[:, :2] / p1[:, 2:]
        p2 = p2[:, :2] / p2[:, 2:]
        ok = (X2[:, 2] > 0.1)
        for p, (w, h) in ((p1, (W, H)), (p2, size2)):
            ok &= (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
        rows.append(np.c_[p1, p2][ok])
    inl = np.concatenate(rows)[:n_in]
    inl = inl + rng.normal(scale=noise, size=inl.shape)
    w2, h2 = size2
    out = np.c_[rng.uniform(0, W, n_out), rng.uniform(0, H, n_out), rng.uniform(0, w2, n_out), rng.uniform(0, h2, n_out)]
    allp = np.r_[inl, out]
    gt = np.r_[np.ones(n_in, bool), np.zeros(n_out, bool)]
    perm = rng.permutation(len(allp))
    allp, gt = allp[perm], gt[perm]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K2).T @ tx @ R @ np.linalg.inv(K1)
    return allp[:, :2].copy(), allp[:, 2:].copy(), gt, K1, K2, R, t, F / np.linalg.norm(F)


def pose_errors(F: np.ndarray, K1: np.ndarray, K2: np.ndarray, x1: np.ndarray, x2: np.ndarray,
                R: np.ndarray, t: np.ndarray):
    """(rotation error, sign-agnostic translation direction error) in degrees, as in the protocol:
    E = K2^T F K1, recoverPose on the inliers in normalised coordinates."""
    E = K2.T @ F @ K1
    n1 = (np.c_[x1, np.ones(len(x1))] @ np.linalg.inv(K1).T)[:, :2]
    n2 = (np.c_[x2, np.ones(len(x2))] @ np.linalg.inv(K2).T)[:, :2]
    _, R_est, t_est, _ = cv2.recoverPose(E, n1, n2, np.eye(3))
    e_r = np.degrees(np.arccos(np.clip((np.trace(R.T @ R_est) - 1) / 2, -1, 1)))
    t_est = t_est.ravel() / np.linalg.norm(t_est)
    e_t = np.degrees(np.arccos(np.clip(abs(float(t_est @ t)), 0, 1)))
    return float(e_r), float(e_t)


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=0)


# thresholds: Sampson-based backends at 1 px; FM_RANSAC bounds the epipolar-line distance in both
# images (stricter, about sqrt(2) x), so it gets 1.5 px.
def _threshold(name: str) -> float:
    return 1.5 if ESTIMATORS.get(name).threshold_kind == "epipolar-line" else 1.0


# FM_RANSAC has no local optimisation: its F is noticeably less accurate in translation direction.
# magsac / magsac++ / gcransac expose no seed: their translation error varies run to run around 1-2 deg
# on this synthetic scene (a transposed or wrong F gives tens of degrees, so 3 deg still discriminates)
POSE_TOL_DEG = {"cv-ransac": 5.0, "magsac": 3.0, "magsac++": 3.0, "gcransac": 3.0}


def _check_result(res: EstimateResult, m: int):
    assert isinstance(res, EstimateResult)
    assert isinstance(res.seconds, float) and res.seconds >= 0.0
    assert res.inliers.shape == (m,) and res.inliers.dtype == bool
    if res.F is not None:
        assert res.F.shape == (3, 3) and res.F.dtype == np.float64
        assert np.isclose(np.linalg.norm(res.F), 1.0)


# -- accuracy on outlier-contaminated data -------------------------------------------------------
def _typical_run(name, run, pose_error, runs: int = 5):
    """A seeded estimator: its one run (``run(seed)``). An unseedable one (pymagsac takes no seed, so each run
    differs): of ``runs`` runs, the one with the median ``pose_error(res)``, so the accuracy checks describe its
    typical run and not one draw (a single MAGSAC++ draw once missed the 3.0 deg tolerance with 3.01 deg)."""
    if ESTIMATORS.get(name).seedable:
        return run(0)
    results = [run(k) for k in range(runs)]
    assert all(r.F is not None for r in results), f"{name} found no model in some of {runs} runs"
    return sorted(results, key=pose_error)[runs // 2]


@pytest.mark.parametrize("name", ROBUST)
def test_recovers_geometry_with_outliers(name, scene):
    x1, x2, gt, K1, K2, R, t, _ = scene
    res = _typical_run(name, lambda seed: estimate(name, x1, x2, _threshold(name), 0.999999, 20000, seed=seed,
                                                   sizes=((W, H), (W, H))),
                       lambda r: max(pose_errors(r.F, K1, K2, x1[r.inliers], x2[r.inliers], R, t)))
    _check_result(res, len(x1))
    assert res.F is not None, f"{name} found no model"
    m = res.inliers
    precision = (m & gt).sum() / max(m.sum(), 1)
    recall = (m & gt).sum() / gt.sum()
    assert precision > 0.9 and recall > 0.9, (name, precision, recall)
    # x2^T F x1 = 0 on the true inliers ...
    d = sampson_distance(res.F, x1[gt], x2[gt])
    assert np.median(d) < 0.5 and np.percentile(d, 90) < 1.2, (name, np.median(d))
    # ... and not for the transpose: this is what makes the line above a convention check
    assert np.median(sampson_distance(res.F.T, x1[gt], x2[gt])) > 5.0
    e_r, e_t = pose_errors(res.F, K1, K2, x1[m], x2[m], R, t)
    tol = POSE_TOL_DEG.get(name, 2.0)
    assert e_r < tol and e_t < tol, (name, e_r, e_t)


@pytest.mark.parametrize("name", [n for n in ("cv-lmeds", "cv-8pt") if n in AVAILABLE])
def test_threshold_free_on_clean_data(name):
    x1, x2, gt, K1, K2, R, t, _ = make_scene(n_in=400, n_out=0, seed=1)
    res = estimate(name, x1, x2, 1.0, 0.999999, 2000, seed=0)
    _check_result(res, len(x1))
    assert res.F is not None
    assert res.inliers.mean() > 0.9
    if name == "cv-8pt":
        assert res.inliers.all()
    d = sampson_distance(res.F, x1, x2)
    assert np.median(d) < 0.5
    assert np.median(sampson_distance(res.F.T, x1, x2)) > 5.0
    e_r, e_t = pose_errors(res.F, K1, K2, x1[res.inliers], x2[res.inliers], R, t)
    assert e_r < 2.0 and e_t < 2.0, (name, e_r, e_t)


def test_lmeds_with_few_outliers():
    if "cv-lmeds" not in AVAILABLE:
        pytest.skip("opencv not available")
    x1, x2, gt, *_ = make_scene(n_in=600, n_out=150, seed=2)
    res = estimate("cv-lmeds", x1, x2, 1.0, 0.999999, 5000, seed=0)
    assert res.F is not None
    m = res.inliers
    assert (m & gt).sum() / m.sum() > 0.9 and (m & gt).sum() / gt.sum() > 0.9


@pytest.mark.parametrize("name", ROBUST)
def test_convention_with_two_different_cameras(name):
    """Image 1 is 1024x768 with f = 800; image 2 is 640x480 with f = 520 and an off-centre principal
    point. Swapping the images anywhere (a transposed F, x1 and x2 exchanged, K1 and K2 exchanged)
    would break either the epipolar check or the pose."""
    K2 = np.array([[520.0, 0, 300.0], [0, 520.0, 250.0], [0, 0, 1]])
    x1, x2, gt, K1, K2, R, t, F_true = make_scene(n_in=500, n_out=250, deg=25.0, seed=3, K2=K2,
                                                   size2=(640, 480))
    res = _typical_run(name, lambda seed: estimate(name, x1, x2, _threshold(name), 0.999999, 20000, seed=seed + 1,
                                                   sizes=((W, H), (640, 480))),
                       lambda r: max(pose_errors(r.F, K1, K2, x1[r.inliers], x2[r.inliers], R, t)))
    assert res.F is not None
    assert np.median(sampson_distance(res.F, x1[gt], x2[gt])) < 0.5
    assert np.median(sampson_distance(res.F.T, x1[gt], x2[gt])) > 5.0
    assert min(np.linalg.norm(res.F - F_true), np.linalg.norm(res.F + F_true)) < 0.05
    e_r, e_t = pose_errors(res.F, K1, K2, x1[res.inliers], x2[res.inliers], R, t)
    tol = POSE_TOL_DEG.get(name, 2.0)
    assert e_r < tol and e_t < tol, (name, e_r, e_t)


# -- degenerate input: F None, never an exception ------------------------------------------------
def _degenerate_cases():
    rng = np.random.default_rng(7)
    p = rng.uniform(0, 500, (100, 2))
    q = rng.uniform(0, 500, (100, 2))
    same = np.tile([[100.0, 200.0]], (100, 1))
    nan1 = p.copy()
    nan1[3, 0] = np.nan
    inf2 = q.copy()
    inf2[5, 1] = np.inf
    return {
        "five matches": (p[:5], q[:5]),
        "seven matches": (p[:7], q[:7]),
        "no matches": (np.zeros((0, 2)), np.zeros((0, 2))),
        "identical points": (same, same.copy()),
        "one image all identical": (same, q),
        "few distinct matches": (np.r_[p[:4], p[:4], p[:4]], np.r_[q[:4], q[:4], q[:4]]),
        "nan": (nan1, q),
        "inf": (p, inf2),
        "shape mismatch": (p, q[:50]),
        "wrong columns": (np.c_[p, p], np.c_[q, q]),
    }


@pytest.mark.parametrize("name", AVAILABLE)
def test_degenerate_input_gives_none(name):
    for case, (a, b) in _degenerate_cases().items():
        res = estimate(name, a, b, 1.0, 0.999999, 1000, seed=0)
        assert res.F is None, (name, case)
        assert res.inliers.dtype == bool and not res.inliers.any(), (name, case)
        assert res.inliers.shape == (len(a),), (name, case)


@pytest.mark.parametrize("name", AVAILABLE)
def test_accepts_float32_and_int_input(name, scene):
    x1, x2, gt, *_ = scene
    for dt in (np.float32, np.int64):
        res = estimate(name, x1.astype(dt), x2.astype(dt), 1.5, 0.9999, 5000, seed=0)
        _check_result(res, len(x1))


class _Raising(Estimator):
    def _solve(self, *a):
        raise RuntimeError("library exploded")


class _Stacked(Estimator):
    """Returns three stacked candidates, the true F in the middle, like OpenCV's 7-point output."""
    F_true = None

    def _solve(self, pts1, pts2, threshold, confidence, max_iters, seed, sizes):
        rng = np.random.default_rng(0)
        with timed() as t:
            stack = np.r_[rng.normal(size=(3, 3)), 7.0 * self.F_true, rng.normal(size=(3, 3))]
        return RawSolution(stack, np.ones(len(pts1), bool), t.seconds)


class _Garbage(Estimator):
    def __init__(self, F):
        self.F = F

    def _solve(self, pts1, pts2, *a):
        return RawSolution(self.F, None, 0.0)


def test_library_exception_is_a_failure(scene):
    x1, x2, *_ = scene
    res = _Raising().estimate(x1, x2, 1.0, 0.99, 100)
    assert res.F is None and not res.inliers.any() and res.inliers.shape == (len(x1),)


def test_non_finite_or_zero_F_is_a_failure(scene):
    x1, x2, *_ = scene
    for F in (np.zeros((3, 3)), np.full((3, 3), np.nan), np.ones((2, 3)), np.ones((3, 3, 1))):
        res = _Garbage(F).estimate(x1, x2, 1.0, 0.99, 100)
        assert res.F is None and not res.inliers.any()


def test_stacked_solutions_keep_the_best(scene):
    x1, x2, gt, K1, K2, R, t, F_true = scene
    est = _Stacked()
    est.F_true = F_true
    res = est.estimate(x1, x2, 1.0, 0.99, 100)
    assert res.F is not None
    assert min(np.linalg.norm(res.F - F_true), np.linalg.norm(res.F + F_true)) < 1e-9
    assert res.inliers.sum() >= 0.9 * gt.sum()  # mask recomputed from the chosen F


# -- determinism ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", [n for n in AVAILABLE if ESTIMATORS.get(n).seedable])
def test_fixed_seed_is_reproducible(name):
    # a hard case (35% inliers, small budget) where the outcome depends on the random samples
    x1, x2, *_ = make_scene(n_in=280, n_out=520, seed=4)
    runs = [estimate(name, x1, x2, 1.0, 0.999999, 300, seed=123) for _ in range(3)]
    for r in runs[1:]:
        assert (r.F is None) == (runs[0].F is None)
        if r.F is not None:
            assert np.allclose(r.F, runs[0].F, atol=1e-12)
        assert np.array_equal(r.inliers, runs[0].inliers)


@pytest.mark.parametrize("name", [n for n in AVAILABLE if ESTIMATORS.get(n).seed_used])
def test_seed_reaches_the_library(name):
    x1, x2, *_ = make_scene(n_in=280, n_out=520, seed=4)
    masks = [estimate(name, x1, x2, 1.0, 0.999999, 300, seed=s).inliers for s in (123, 124, 125, 126)]
    assert any(not np.array_equal(masks[0], m) for m in masks[1:]), "the seed has no effect"


# -- registry, availability, sizes ---------------------------------------------------------------
def test_all_names_registered():
    expected = {"pyransac", "degensac", "magsac", "magsac++", "gcransac", "cv-ransac", "cv-usac",
                "cv-magsac", "cv-accurate", "cv-lmeds", "cv-8pt", "poselib", "colmap"}
    assert expected <= set(ESTIMATORS.names())
    for n in expected:
        assert ESTIMATORS.description(n)


def test_unknown_name_raises_imtune_error(scene):
    x1, x2, *_ = scene
    with pytest.raises(ImtuneError, match="no-such-ransac"):
        get_estimator("no-such-ransac")
    with pytest.raises(ImtuneError):
        estimate("no-such-ransac", x1, x2, 1.0, 0.99, 100)


@pytest.mark.parametrize("name", sorted(ESTIMATORS.names()))
def test_missing_package_is_unavailable(name, monkeypatch):
    cls = ESTIMATORS.get(name)
    module = {"opencv-contrib-python-headless": "cv2"}.get(cls.package, cls.package)
    monkeypatch.setitem(sys.modules, module, None)  # makes `import module` raise ImportError
    with pytest.raises(UnavailableError) as ei:
        cls.check_available()
    msg = str(ei.value)
    assert cls.package in msg and "\n" not in msg


def test_get_estimator_returns_an_estimator():
    for n in AVAILABLE:
        est = get_estimator(n)
        assert isinstance(est, Estimator)
        assert est.name == n


def test_sizes_from_points():
    p1 = np.array([[0.0, 0.0], [1023.4, 10.0], [5.0, 767.9]])
    p2 = np.array([[10.0, 20.0], [99.0, 49.5]])
    assert sizes_from_points(p1, p2) == ((1024.0, 768.0), (100.0, 50.0))


@pytest.mark.parametrize("name", [n for n in ("magsac", "magsac++", "gcransac") if n in AVAILABLE])
def test_size_aware_backends_with_and_without_sizes(name, scene):
    x1, x2, gt, *_ = scene
    for sizes in (None, ((W, H), (W, H)), ((2000, 1500), (1200, 900))):
        res = estimate(name, x1, x2, 1.0, 0.999999, 20000, sizes=sizes)
        assert res.F is not None, sizes
        assert (res.inliers & gt).sum() / gt.sum() > 0.9


@pytest.mark.parametrize("name", AVAILABLE)
def test_extreme_budgets_do_not_raise(name, scene):
    x1, x2, *_ = scene
    for it in (1, 10, 10**12):
        res = estimate(name, x1[:200], x2[:200], 1.0, 0.5 if it == 10**12 else 0.999999, it, seed=0)
        _check_result(res, 200)


def test_imc_geom_section_maps_to_estimators():
    from pipeline.geometry.imc import IMC_METHODS, imc_geom_to_config
    g = {"method": "cmp-degensac-f", "threshold": 0.5, "confidence": 0.999999, "max_iter": 100000,
         "error_type": "sampson", "degeneracy_check": True}
    assert imc_geom_to_config(g) == {"ransac": "degensac", "threshold": 0.5, "confidence": 0.999999,
                                     "max_iters": 100000}
    assert imc_geom_to_config({**g, "degeneracy_check": False})["ransac"] == "pyransac"
    assert imc_geom_to_config({"method": "cv2-usacmagsac-f"}) == {"ransac": "cv-magsac"}
    assert set(IMC_METHODS.values()) <= set(ESTIMATORS.names())
    for bad in ({"method": "intel-dfe-f"}, {}, {**g, "error_type": "symm_epipolar"}):
        with pytest.raises(ImtuneError):
            imc_geom_to_config(bad)
