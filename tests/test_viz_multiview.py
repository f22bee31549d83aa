"""Multiview figures: keypoint drawing (blue in the model, red not), which keypoints a COLMAP model holds
(synthetic bag: unmatched keypoints can never be in it), a failed bag is a one-line error, the montage PNG."""
import cv2
import numpy as np
import pytest

from pipeline.errors import ImtuneError
from pipeline.tasks.multiview import BagJob, MultiviewConfig
from pipeline.viz.colors import BLUE, RED
from pipeline.viz.multiview import BagReconstruction, draw_bag, draw_keypoints, reconstruct_bag
from tests.conftest import look_at

W, H = 1024, 768
K = np.array([[800.0, 0, 511.5], [0, 800.0, 383.5], [0, 0, 1]])




def synthetic_job(tmp_path, n=4, n_points=1200, n_noise=150, seed=0, no_matches=False):
    """A bag whose keypoints are projections of 3D points (+ noise) followed by ``n_noise`` unmatched
    keypoints per image; matches are the true correspondences."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (n_points, 3))
    names = tuple(f"{i:04d}.png" for i in range(n))
    poses, kpts, ids = {}, {}, {}
    for i, name in enumerate(names):
        a = np.radians(-20 + 40 * i / max(1, n - 1))
        R, t = look_at(np.array([6 * np.sin(a), 0.2 * rng.normal(), -6 * np.cos(a)]))
        poses[name] = (R, t)
        x = (K @ ((R @ X.T).T + t).T).T
        x = x[:, :2] / x[:, 2:]
        vis = np.nonzero((x[:, 0] > 0) & (x[:, 0] < W) & (x[:, 1] > 0) & (x[:, 1] < H))[0]
        noise = np.c_[rng.uniform(0, W, n_noise), rng.uniform(0, H, n_noise)]
        kpts[name] = np.r_[x[vis] + rng.normal(0, 0.3, (len(vis), 2)), noise].astype(np.float32)
        ids[name] = vis
    matches = {}
    if not no_matches:
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                _, ia, ib = np.intersect1d(ids[a], ids[b], return_indices=True)
                matches[(a, b)] = np.c_[ia, ib]
    conf = MultiviewConfig(intrinsics="prior", pair_min_points=0)
    job = BagJob(scene="synthetic", size=n, index=0, names=names, keypoints=kpts,
                 image_sizes={x: (W, H) for x in names}, K={x: K for x in names}, paths={}, poses=poses,
                 matches=matches, conf=conf, workdir=str(tmp_path))
    return job, {nm: len(ids[nm]) for nm in names}


def _rgb_at(img, xy):
    x, y = int(round(xy[0])), int(round(xy[1]))
    return img[y, x, ::-1].astype(int)


def test_draw_keypoints_blue_in_model_red_not():
    img = np.full((400, 600), 120, np.uint8)
    k = np.array([[100.0, 100.0], [300.0, 200.0], [500.0, 300.0], [200.0, 350.0]])
    mask = np.array([True, False, True, False])
    out = draw_keypoints(img, k, mask, width=600, radius=4)
    assert out.shape[1] == 600 and out.shape[0] > 400  # + caption
    for p, m in zip(k, mask):
        got = _rgb_at(out, p)
        assert np.abs(got - np.array(BLUE if m else RED)).max() <= 40, (p, m, got)
    unreg = draw_keypoints(img, k, None, width=300)
    assert unreg.shape[1] == 300
    assert np.abs(_rgb_at(unreg, (k[0] + 0.5) * 0.5 - 0.5) - np.array(RED)).max() <= 60
    with pytest.raises(ValueError):
        draw_keypoints(img, k, mask[:2])


def test_reconstructed_bag_masks_and_montage(tmp_path):
    job, n_true = synthetic_job(tmp_path)
    bag = reconstruct_bag(job)
    assert bag.record["success"] and len(bag.record["registered"]) == len(job.names)
    for name in job.names:
        m = bag.masks[name]
        assert m is not None and len(m) == len(job.keypoints[name])
        true_part, noise_part = m[:n_true[name]], m[n_true[name]:]
        assert not noise_part.any()          # unmatched keypoints cannot be in the model
        assert true_part.mean() > 0.5        # most true correspondences are triangulated
    images = {n: np.full((H, W, 3), 110, np.uint8) for n in job.names}
    img = draw_bag(bag, images=images, panel_width=400, label="synthetic config")
    png = tmp_path / "bag.png"
    cv2.imwrite(str(png), img)
    back = cv2.imread(str(png))
    assert back.shape == img.shape and back.shape[1] >= 2 * 400
    # both colours are present
    flat = back.reshape(-1, 3)[:, ::-1].astype(int)
    assert (np.abs(flat - np.array(BLUE)).max(axis=1) <= 30).sum() > 100
    assert (np.abs(flat - np.array(RED)).max(axis=1) <= 30).sum() > 100


def test_failed_bag_is_a_one_line_error(tmp_path):
    job, _ = synthetic_job(tmp_path, n=3, n_points=300, no_matches=True)
    with pytest.raises(ImtuneError) as e:
        reconstruct_bag(job)
    msg = str(e.value)
    assert "failed" in msg and "synthetic" in msg and "\n" not in msg


def test_unregistered_image_is_drawn_all_red():
    bag = BagReconstruction(record={"scene": "s", "bag_size": 2, "bag": 0, "images": ["a", "b"], "registered": ["a"],
                                    "NL": 10, "TL": 2.0, "errors": [float("inf")], "ATE": None},
                            names=["a", "b"], keypoints={"a": np.array([[50.0, 50.0]]), "b": np.array([[60.0, 60.0]])},
                            masks={"a": np.array([True]), "b": None}, paths={}, image_sizes={"a": (200, 100), "b": (200, 100)})
    img = draw_bag(bag, images={"a": np.zeros((100, 200), np.uint8), "b": np.zeros((100, 200), np.uint8)}, panel_width=200)
    assert img.ndim == 3 and img.shape[1] >= 400


def test_viz_of_a_multiview_study_draws_its_bags_by_default(tmp_path):
    """`tune viz --study NAME` of a multiview study drew stereo pairs (the --task default) with the study's r and an
    eta and Gamma it never tuned. The study's task is now the default; --task stereo still draws pairs. Real
    3-image fountain-P11 subset: build-gt, a 1-trial multiview study, then viz."""
    from tests.conftest import copy_strecha_subset
    from tests.test_bad_input_files import tune
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    env = {"IMTUNE_CACHE": str(tmp_path / "cache"), "IMTUNE_STUDIES": str(tmp_path / "studies")}
    r = tune("data", "build-gt", "--data", data, "--num-features", "1024", "--quiet", env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    r = tune("run", "--task", "multiview", "--data", data, "--num-features", "512", "--n-trials", "1", "--no-test",
             "--bags", "3:1", "--workers", "1", "--quiet", "--study", "mv", env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    common = ["viz", "--study", "mv", "--data", data, "--split", "val", "--quiet"]
    r = tune(*common, "--workers", "1", "--out", tmp_path / "v1", env=env)  # bag processes: multiview only
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.startswith("multiview fountain-P11 bag 3#0") and list((tmp_path / "v1").glob("bag_*.png")), r.stdout
    r = tune(*common, "--task", "stereo", "--out", tmp_path / "v2", env=env)
    assert r.returncode == 0 and r.stdout.startswith("worst ") and list((tmp_path / "v2").glob("fountain-P11_*.png"))
    # the study's report links the gallery `tune viz --study` wrote; `tune plot` redrew it without that link
    report = tmp_path / "studies" / "mv" / "report.html"
    r = tune("plot", "--study", "mv", env=env)
    assert r.returncode == 0 and report.is_file() and "gallery.html" not in report.read_text(), r.stderr[-2000:]
    r = tune(*common, env=env)  # the study's own figures folder and gallery (no --out)
    assert r.returncode == 0 and (report.parent / "gallery.html").is_file(), r.stderr[-2000:]
    assert report.read_text().count("href='gallery.html'") == 1
    r = tune("plot", "--study", "mv", env=env)
    assert r.returncode == 0 and report.read_text().count("href='gallery.html'") == 1, r.stderr[-2000:]
