"""Stereo figures: the error colour scale, errors against the ground truth (epipolar and depth), the drawing
(PNG size, colours at the drawn endpoints), and one real render on fountain-P11 with 1024 SIFT."""
import math

import cv2
import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.data.scene import ImageInfo, Pair, Scene
from pipeline.viz.colors import BLUE, GREEN, RED, YELLOW, error_colors
from pipeline.viz.gt import depth_reprojection_errors, gt_fundamental, match_errors, symmetric_epipolar_distance
from pipeline.viz.stereo import draw_matches, line_width

K1 = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
K2 = np.array([[760.0, 0, 310.0], [0, 770.0, 245.0], [0, 0, 1]])
W, H = 640, 480


def two_view(n=300, seed=0):
    """Points on the plane Z = 8 of camera 1, seen by both cameras (relative pose R, t)."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(np.radians(12) * np.array([0.1, 1.0, 0.0]) / np.hypot(0.1, 1.0)).as_matrix()
    t = np.array([-1.0, 0.05, 0.1])
    u = rng.integers(40, W - 40, n).astype(float)  # integer pixels of image 1: exact depth look-up
    v = rng.integers(40, H - 40, n).astype(float)
    x1 = np.c_[u, v]
    X = (np.linalg.inv(K1) @ np.c_[x1, np.ones(n)].T).T * 8.0
    X2 = (R @ X.T).T + t
    x2 = (K2 @ X2.T).T
    x2 = x2[:, :2] / x2[:, 2:]
    return R, t, x1, x2


def plane_depths(R, t, z=8.0):
    """Depth maps of both cameras for the plane Z = z of camera 1."""
    d1 = np.full((H, W), z)
    # camera 2 pixel ray r (cam-2 frame) -> cam-1 frame: X1 = R^T (s r - t); plane n.X1 = z with n = (0, 0, 1)
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    rays = (np.linalg.inv(K2) @ np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])).T  # z component 1
    n = R[:, 2]  # third row of R^T
    s = (z + n @ t) / (rays @ n)
    return d1, s.reshape(H, W)  # depth in camera 2 = s (ray z = 1)


def test_error_colours_green_yellow_red_blue():
    c = error_colors([0.0, 5.0, 5.01, 100.0, np.inf, np.nan, 2.5])
    assert tuple(c[0]) == GREEN
    assert tuple(c[1]) == YELLOW
    assert tuple(c[2]) == RED and tuple(c[3]) == RED and tuple(c[4]) == RED
    assert tuple(c[5]) == BLUE
    mid = np.rint((np.array(GREEN) + np.array(YELLOW)) / 2)
    assert np.abs(c[6].astype(int) - mid).max() <= 1
    assert error_colors([]).shape == (0, 3)


def test_epipolar_distance_is_zero_for_true_matches_and_large_for_wrong_ones():
    R, t, x1, x2 = two_view()
    F = gt_fundamental(K1, K2, R, t)
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    assert np.abs(np.sum(h2 * (h1 @ F.T), axis=1)).max() < 1e-9  # x2^T F x1 = 0
    assert symmetric_epipolar_distance(F, x1, x2).max() < 1e-6
    wrong = np.roll(x2, 37, axis=0)
    d = symmetric_epipolar_distance(F, x1, wrong)
    assert np.median(d) > 20 and (d > 5).mean() > 0.9
    # the transpose (wrong convention) does not explain the true matches
    assert np.median(symmetric_epipolar_distance(F.T, x1, x2)) > 5


def test_depth_reprojection_error_zero_for_true_matches_nan_without_depth():
    R, t, x1, x2 = two_view()
    d1, d2 = plane_depths(R, t)
    e = depth_reprojection_errors(x1, x2, K1, K2, R, t, d1, d2)
    assert np.nanmax(e) < 0.5  # camera 2's depth is read at the nearest pixel
    e1 = depth_reprojection_errors(x1, x2, K1, K2, R, t, d1, None)  # one direction only: exact
    assert np.nanmax(e1) < 1e-6
    wrong = depth_reprojection_errors(x1, np.roll(x2, 37, axis=0), K1, K2, R, t, d1, d2)
    assert (wrong > 5).mean() > 0.9
    none = depth_reprojection_errors(x1, x2, K1, K2, R, t, np.zeros_like(d1), np.zeros_like(d2))
    assert np.isnan(none).all()
    # a depth map at half the resolution, scaled back to the keypoints' frame
    half = cv2.resize(d1, (W // 2, H // 2), interpolation=cv2.INTER_NEAREST)
    e_half = depth_reprojection_errors(x1, x2, K1, K2, R, t, half, None, depth_scale1=(2.0, 2.0))
    assert np.nanmax(e_half) < 1e-6


def _scene(tmp_path, with_depth: bool, with_pose: bool = True):
    R, t, x1, x2 = two_view()
    images = {"a.png": ImageInfo("a.png", tmp_path / "a.png", K=K1, size=(W, H)),
              "b.png": ImageInfo("b.png", tmp_path / "b.png", K=K2, size=(W, H))}
    if with_pose:
        images["a.png"].R, images["a.png"].t = np.eye(3), np.zeros(3)
        images["b.png"].R, images["b.png"].t = R, t
    if with_depth:
        for name, d in zip(("a.png", "b.png"), plane_depths(R, t)):
            p = tmp_path / f"{name}.h5"
            with h5py.File(p, "w") as f:
                f["depth"] = d
            images[name].depth_path = p
    sc = Scene("syn", tmp_path, images, pairs=[Pair("a.png", "b.png")])
    return sc, x1, x2


def test_match_errors_picks_depth_epipolar_or_none(tmp_path):
    sc, x1, x2 = _scene(tmp_path, with_depth=True)
    e, kind = match_errors(sc, sc.pairs[0], x1, x2, K1, K2, ((W, H), (W, H)))
    assert kind == "depth" and np.nanmax(e) < 0.5
    e, kind = match_errors(sc, sc.pairs[0], x1, x2, K1, K2, ((W, H), (W, H)), use_depth=False)
    assert kind == "epipolar" and e.max() < 1e-6
    sc2, _, _ = _scene(tmp_path, with_depth=False, with_pose=False)
    e, kind = match_errors(sc2, sc2.pairs[0], x1, x2, K1, K2, ((W, H), (W, H)))
    assert kind == "none" and np.isnan(e).all()


def _close(img, xy, rgb, tol=45):
    x, y = int(round(xy[0])), int(round(xy[1]))
    got = img[y, x, ::-1].astype(int)  # BGR -> RGB
    return np.abs(got - np.asarray(rgb)).max() <= tol, got


@pytest.mark.parametrize("layout", ["horizontal", "vertical"])
def test_draw_matches_png_size_and_endpoint_colours(tmp_path, layout):
    rng = np.random.default_rng(0)
    img1 = (rng.random((480, 640)) * 60 + 90).astype(np.uint8)          # gray
    img2 = (rng.random((400, 600, 3)) * 60 + 90).astype(np.uint8)       # RGB, another size
    pts1 = np.array([[100.0, 100.0], [500.0, 120.0], [120.0, 380.0], [520.0, 400.0]])
    pts2 = np.array([[80.0, 90.0], [480.0, 100.0], [100.0, 330.0], [500.0, 340.0]])
    errors = np.array([0.0, 5.0, 50.0, np.nan])
    fig = draw_matches(img1, img2, pts1, pts2, errors, title=["pair a | b", "config"], width=1000, layout=layout)
    png = fig.save(tmp_path / f"f-{layout}.png")
    back = cv2.imread(str(png), cv2.IMREAD_COLOR)
    assert back is not None and back.shape == fig.image.shape
    if layout == "horizontal":
        assert back.shape[1] == 1000
    else:
        assert back.shape[1] == int(round(640 * fig.scale))
    assert back.shape[0] > (480 * fig.scale if layout == "horizontal" else (480 + 400) * fig.scale)  # + title, legend
    for which, pts in ((1, pts1), (2, pts2)):
        q = fig.to_figure(pts, which)
        for xy, rgb in zip(q, (GREEN, YELLOW, RED, BLUE)):
            ok, got = _close(back, xy, rgb)
            assert ok, (layout, which, xy, rgb, got)
    assert sorted(fig.drawn.tolist()) == [0, 1, 2, 3]
    assert fig.stats["le1"] == 1 and fig.stats["gt_max"] == 1 and fig.stats["unknown"] == 1


def test_draw_matches_caps_the_lines_and_thins_them():
    rng = np.random.default_rng(1)
    img = np.full((300, 400), 128, np.uint8)
    p = rng.uniform(10, 290, (1000, 2))
    fig = draw_matches(img, img, p, p, rng.uniform(0, 8, 1000), max_lines=150, width=800)
    assert len(fig.drawn) == 150 and len(set(fig.drawn.tolist())) == 150
    assert fig.stats["n"] == 1000  # statistics over all matches, not only the drawn ones
    assert line_width(10) > line_width(150) > line_width(1000)
    empty = draw_matches(img, img, np.zeros((0, 2)), np.zeros((0, 2)), None, width=800)
    assert empty.image.shape[1] == 800 and len(empty.drawn) == 0


# ------------------------------------------------------------------------------------------------ real data

def test_real_render_fountain_sift_1024(strecha, cache_dir, tmp_path):
    from pipeline.cache import H5Cache
    from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
    from pipeline.data import load_scene
    from pipeline.geometry import get_estimator
    from pipeline.tasks.prepare import image_features, pair_knn
    from pipeline.tasks.stereo import evaluate_pair
    from pipeline.viz.stereo import render_pair
    scene = load_scene(strecha, "fountain-P11")
    conf = PipelineConfig(FeatureConfig(num_features=1024), MatchConfig(ratio=0.85),
                          GeometryConfig(ransac="degensac", threshold=0.5, max_iters=20000))
    pair = next(p for p in scene.pairs if p.key == "0004.jpg|0005.jpg")
    cache = H5Cache(cache_dir)
    out = render_pair(scene, pair, conf, cache, tmp_path / "fountain.png", width=1200)
    assert out["failure"] is None and out["error_kind"] == "epipolar" and out["what"] == "inliers"
    # the drawn inliers agree with the laser ground truth: the conventions (scaled K, F, pose) line up
    st = out["stats"]
    assert st["n"] == out["NI"] > 100
    assert st["median"] < 1.0 and st["le_max"] >= 0.95 * st["n"]
    assert out["err"] < 5.0
    # the numbers are the stereo task's own for this pair
    fi = image_features(cache, scene.images[pair.i], conf.feature)
    fj = image_features(cache, scene.images[pair.j], conf.feature)
    tab, s = pair_knn(cache, fi, fj, conf.matching)
    rec = evaluate_pair(scene, pair, fi, fj, tab, s, conf, get_estimator("degensac")).record
    assert rec["NI"] == out["NI"] and math.isclose(rec["err"], out["err"])
    img = cv2.imread(out["png"])
    assert img.shape[1] == 1200 and img.shape[0] > 1200 * 683 / 2048


@pytest.mark.parametrize("text", ["η", "Γ", "→"])
def test_figure_text_never_draws_a_missing_glyph_as_a_question_mark(text):
    """Every figure's header reads 'degensac η 0.5 px, Γ 50000': OpenCV's built-in fonts have no Greek letters (nor
    arrows) and drew '?' in their place. Such characters are now spelled out (eta, Gamma, ->)."""
    from pipeline.viz.text import put_text

    def drawn(s):
        img = np.zeros((40, 120, 3), np.uint8)
        put_text(img, s, 5, 30, 20, (255, 255, 255))
        return img
    assert not np.array_equal(drawn(text), drawn("?"))
