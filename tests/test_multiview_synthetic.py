"""The multiview task's machinery on synthetic scenes with known poses: ATE, COLMAP bags from given
keypoints and matches (success, failure, parallel workers, a dying worker), aggregation, bad input."""
import math
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline import colmap_db
from pipeline.errors import ImtuneError
from pipeline.metrics.ate import absolute_trajectory_error, camera_center, umeyama
from pipeline.tasks.multiview import BagJob, MultiviewConfig, run_bag, run_bags, summarize_bags, summarize_scene
from tests.conftest import look_at

W, H = 1024, 768
K = np.array([[800.0, 0, 511.5], [0, 800.0, 383.5], [0, 0, 1]])




def synthetic_bag(n=5, n_points=1500, seed=0, noise=0.5, outliers=0.2, workdir="/tmp", index=0,
                  conf=MultiviewConfig(intrinsics="prior", pair_min_points=0), drop_matches=()):
    """A bag: keypoints = projections + noise, matches = true correspondences + random outliers."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (n_points, 3))
    names = tuple(f"{i:04d}.jpg" for i in range(n))
    poses, kpts, ids = {}, {}, {}
    for i, name in enumerate(names):
        a = np.radians(-25 + 50 * i / max(1, n - 1))
        R, t = look_at(np.array([6 * np.sin(a), 0.3 * rng.normal(), -6 * np.cos(a)]))
        poses[name] = (R, t)
        x = (K @ ((R @ X.T).T + t).T).T
        x = x[:, :2] / x[:, 2:]
        vis = np.nonzero((x[:, 0] > 0) & (x[:, 0] < W) & (x[:, 1] > 0) & (x[:, 1] < H) & (rng.random(n_points) < 0.8))[0]
        kpts[name] = (x[vis] + rng.normal(0, noise, (len(vis), 2))).astype(np.float32)
        ids[name] = vis
    matches = {}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            _, ia, ib = np.intersect1d(ids[a], ids[b], return_indices=True)
            m = np.c_[ia, ib]
            no = int(outliers * len(m))
            m = np.r_[m, np.c_[rng.integers(0, len(kpts[a]), no), rng.integers(0, len(kpts[b]), no)]]
            if drop_matches != "all" and (a, b) not in drop_matches:
                matches[(a, b)] = m
    return BagJob(scene="synthetic", size=n, index=index, names=names, keypoints=kpts,
                  image_sizes={x: (W, H) for x in names}, K={x: K for x in names}, paths={}, poses=poses,
                  matches=matches, conf=conf, workdir=str(workdir))


def test_umeyama_recovers_a_similarity_and_ate_is_zero():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    dst = 2.5 * (R @ src.T).T + np.array([1.0, -2.0, 0.5])
    s, R_est, t = umeyama(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R_est, R) and np.allclose(t, [1.0, -2.0, 0.5])
    assert absolute_trajectory_error(src, dst).ate < 1e-9
    noisy = dst + rng.normal(0, 0.01, dst.shape)
    assert 0.005 < absolute_trajectory_error(src, noisy).ate < 0.03
    assert absolute_trajectory_error(src[:2], dst[:2]) is None  # needs >= 3 cameras
    R0, t0 = look_at(np.array([1.0, 2.0, 3.0]))
    assert np.allclose(camera_center(R0, t0), [1, 2, 3])


def test_a_bag_reconstructs_with_small_errors(tmp_path):
    rec = run_bag(synthetic_bag(workdir=tmp_path))
    assert rec["success"], rec["failure"]
    assert rec["RC"] == 100.0 and len(rec["registered"]) == 5
    assert rec["NL"] > 500 and rec["TL"] > 2
    assert len(rec["errors"]) == 10 and max(rec["errors"]) < 0.5
    assert rec["ATE"] is not None and rec["ATE"] < 0.02  # scene units (~6 m camera distance)
    assert not any(tmp_path.iterdir())  # the bag's database and models are cleaned up


def test_colmap_estimated_intrinsics_also_work(tmp_path):
    rec = run_bag(synthetic_bag(workdir=tmp_path, conf=MultiviewConfig(intrinsics="colmap", pair_min_points=0)))
    assert rec["success"], rec["failure"]
    assert np.median(rec["errors"]) < 2.0


def test_a_bag_without_matches_is_a_recorded_failure(tmp_path):
    rec = run_bag(synthetic_bag(workdir=tmp_path, drop_matches="all"))
    assert not rec["success"] and "no initial pair" in rec["failure"]
    assert rec["RC"] == 0 and all(math.isinf(e) for e in rec["errors"]) and rec["ATE"] is None


def test_unregistered_image_gives_infinite_errors_for_its_pairs(tmp_path):
    names = [f"{i:04d}.jpg" for i in range(5)]
    drop = tuple((a, names[4]) for a in names[:4])  # image 4 has no matches at all
    rec = run_bag(synthetic_bag(workdir=tmp_path, drop_matches=drop))
    assert rec["success"] and rec["RC"] == 80.0 and "0004.jpg" not in rec["registered"]
    errs = dict(zip(rec["pairs"], rec["errors"]))
    assert all(math.isinf(e) for p, e in errs.items() if "0004.jpg" in p)
    assert all(e < 1.0 for p, e in errs.items() if "0004.jpg" not in p)


def test_parallel_bags_match_serial_bags(tmp_path):
    jobs = [synthetic_bag(n=4, seed=s, workdir=tmp_path, index=s) for s in range(4)]
    serial = run_bags(jobs, workers=1)
    parallel = run_bags(jobs, workers=2)
    assert [r["bag"] for r in parallel] == [0, 1, 2, 3]
    for a, b in zip(serial, parallel):
        assert a["success"] and b["success"]
        assert a["registered"] == b["registered"]
        assert np.allclose(a["errors"], b["errors"], atol=1e-3)


def dying_bag(job):
    """A bag function whose worker process dies on bag 1 (as a COLMAP abort would)."""
    if job.index == 1:
        os._exit(3)
    return run_bag(job)


@pytest.mark.timeout(180)
def test_a_worker_that_dies_is_a_failed_bag_and_the_run_goes_on(tmp_path):
    jobs = [synthetic_bag(n=4, seed=s, workdir=tmp_path, index=s) for s in range(3)]
    res = run_bags(jobs, workers=2, fn=dying_bag)
    assert [r["bag"] for r in res] == [0, 1, 2]
    assert res[0]["success"] and res[2]["success"]
    assert not res[1]["success"] and "died" in res[1]["failure"]


def test_aggregation_follows_the_official_benchmark():
    ok = {"scene": "s", "bag_size": 5, "success": True, "NL": 1000, "TL": 4.0, "RC": 100.0, "NM": 500.0,
          "errors": [1.5] * 10, "ATE": 0.1, "seconds": 2.0}
    half = dict(ok, NL=500, TL=3.0, RC=60.0, errors=[1.5] * 3 + [math.inf] * 7, ATE=None)
    fail = dict(ok, success=False, NL=0, TL=0.0, RC=0.0, errors=[math.inf] * 10, ATE=None)
    s = summarize_bags([ok, half, fail])
    assert s["SR"] == pytest.approx(200 / 3) and s["RC"] == pytest.approx(160 / 3)
    assert s["NL"] == 750 and s["TL"] == 3.5          # over successful bags
    assert s["ATE"] == pytest.approx(0.1)             # over bags that have one
    assert s["mAA10"] == pytest.approx((0.9 + 0.27 + 0.0) / 3)
    assert s["failed"] == 1 and s["bags"] == 3
    big = dict(ok, bag_size=10, errors=[0.5] * 45, ATE=0.3)
    sc = summarize_scene([ok, half, fail, big])
    assert set(sc["by_size"]) == {"5", "10"}
    assert sc["mAA10"] == pytest.approx((s["mAA10"] + 1.0) / 2)  # mean over bag sizes
    assert sc["ATE"] == pytest.approx((0.1 + 0.3) / 2)


def test_corrupt_or_foreign_database_is_a_clear_error(tmp_path):
    bad = tmp_path / "database.db"
    bad.write_bytes(b"not a database at all" * 10)
    with pytest.raises(ImtuneError, match="database.db"):
        colmap_db.check_database(bad)
    with pytest.raises(ImtuneError, match="not found"):
        colmap_db.check_database(tmp_path / "missing.db")
    import sqlite3
    other = tmp_path / "other.db"
    sqlite3.connect(other).execute("CREATE TABLE x (a)").connection.commit()
    with pytest.raises(ImtuneError, match="tables missing"):
        colmap_db.open_database(other)
    with pytest.raises(ImtuneError, match="not a COLMAP model"):
        colmap_db.read_model(tmp_path)


def test_bad_multiview_settings_are_rejected():
    with pytest.raises(ImtuneError, match="intrinsics"):
        MultiviewConfig(intrinsics="guess")
    with pytest.raises(ImtuneError):
        MultiviewConfig(min_model_size=1)
    assert MultiviewConfig(bags={5: 3}).bag_spec == {5: 3}


def test_a_bag_size_no_bag_of_which_is_valid_is_said():
    """A requested bag size of which no bag passes the visibility rule (each image sees >= 100 of the bag's points)
    was left out of the scene's multiview means without a word (a 29-image scene of three Strecha scenes: sizes 5 and
    10 averaged, reported as the mean over 5, 10 and 25). Now the task's notes name the size (a warning line and
    `notes` in the JSON)."""
    from pipeline.data.scene import ImageInfo, Scene, all_pairs
    from pipeline.tasks.multiview import MultiviewConfig, MultiviewTask
    names = [f"{k}.jpg" for k in range(10)]
    obs = {n: (np.arange(200), np.zeros((200, 2))) for n in names[:9]}
    obs[names[9]] = (np.arange(50), np.zeros((50, 2)))  # sees too few points: every bag with it is invalid
    scene = Scene("s", Path("."), {n: ImageInfo(n, Path(n), K=np.eye(3), R=np.eye(3), t=np.zeros(3)) for n in names},
                  all_pairs(names), points3d=np.zeros((200, 3)), observations=obs)
    task = MultiviewTask(MultiviewConfig(bags=((5, 3), (10, 1))))
    notes = task.scene_notes(scene)
    assert len(notes) == 1 and "no bag of 10 images" in notes[0] and "scene s" in notes[0], notes
    assert MultiviewTask(MultiviewConfig(bags=((5, 3),))).scene_notes(scene) == []


def test_fewer_distinct_bags_than_asked_are_said():
    """A 10-image scene asked for 3 bags of 10 has one distinct bag of 10: the study recorded 1 and the findings
    report's header said "10:3" without a word. Now the task's notes give the count."""
    from pipeline.data.scene import ImageInfo, Scene, all_pairs
    from pipeline.tasks.multiview import MultiviewConfig, MultiviewTask
    names = [f"{k}.jpg" for k in range(10)]
    obs = {n: (np.arange(200), np.zeros((200, 2))) for n in names}
    scene = Scene("s", Path("."), {n: ImageInfo(n, Path(n), K=np.eye(3), R=np.eye(3), t=np.zeros(3)) for n in names},
                  all_pairs(names), points3d=np.zeros((200, 3)), observations=obs)
    notes = MultiviewTask(MultiviewConfig(bags=((5, 3), (10, 3)))).scene_notes(scene)
    assert notes == ["scene s: 1 bag of 10 images, not 3: its 10 images give only 1 distinct bag passing the "
                     "visibility rule (the protocol takes fewer where a scene has fewer)"], notes
    assert MultiviewTask(MultiviewConfig(bags=((5, 3), (10, 1)))).scene_notes(scene) == []
