"""Strecha loader: real data (../shared/data/strecha), pose conventions, and bad-input errors."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.data import load_scene, load_strecha
from pipeline.data.resize import load_image, scaled_K
from pipeline.data.scene import ImageInfo, Pair, Scene
from pipeline.data.strecha import read_camera, write_camera
from pipeline.errors import ImtuneError


def _shared() -> Path:
    env = os.environ.get("IMTUNE_SHARED")
    if env:
        return Path(env) / "data" if (Path(env) / "data").is_dir() else Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


STRECHA = _shared() / "strecha"
needs_strecha = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"shared Strecha data not found at {STRECHA} "
                                                                 "(set IMTUNE_SHARED to the shared folder)")


@pytest.fixture
def strecha_copy(tmp_path):
    if not STRECHA.is_dir():
        pytest.skip(f"shared Strecha data not found at {STRECHA}")
    dst = tmp_path / "strecha"
    shutil.copytree(STRECHA / "fountain-P11", dst / "fountain-P11")
    return dst


# ---------------------------------------------------------------- synthetic: conventions -----------------------

def _random_pose(rng):
    return Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)


def test_relative_pose_composes_with_random_poses():
    rng = np.random.default_rng(0)
    for _ in range(20):
        (Ri, ti), (Rj, tj) = _random_pose(rng), _random_pose(rng)
        scene = Scene("s", Path("."), {"a": ImageInfo("a", Path("a"), R=Ri, t=ti),
                                       "b": ImageInfo("b", Path("b"), R=Rj, t=tj)}, [Pair("a", "b")])
        R, t = scene.relative_pose(scene.pairs[0])
        X = rng.normal(size=(10, 3))
        xi, xj = X @ Ri.T + ti, X @ Rj.T + tj
        np.testing.assert_allclose(xi @ R.T + t, xj, atol=1e-9)


def test_synthetic_strecha_scene_round_trips(tmp_path):
    """Cameras written in the .camera convention (camera-to-world R, centre C) load as world-to-camera poses
    that project world points exactly as K R^T (X - C) does."""
    rng = np.random.default_rng(3)
    sdir = tmp_path / "synthetic-P3"
    (sdir / "images").mkdir(parents=True)
    (sdir / "gt_dense_cameras").mkdir()
    K = np.array([[100.0, 0, 31.5], [0, 101.0, 23.5], [0, 0, 1]])
    truth = {}
    for k in range(3):
        name = f"{k:04d}.jpg"
        cv2.imwrite(str(sdir / "images" / name), rng.integers(0, 255, (48, 64), dtype=np.uint8))
        R_c2w, C = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 5
        write_camera(sdir / "gt_dense_cameras" / f"{name}.camera", K, [0, 0, 0], R_c2w, C, (64, 48))
        truth[name] = (R_c2w, C)
    scene = load_strecha(tmp_path, "synthetic-P3")
    assert scene.source == "strecha" and len(scene.images) == 3 and len(scene.pairs) == 3
    X = rng.normal(size=(20, 3)) * 3
    for name, (R_c2w, C) in truth.items():
        im = scene.images[name]
        assert im.size == (64, 48)
        np.testing.assert_allclose(im.K, K)
        np.testing.assert_allclose(X @ im.R.T + im.t, (X - C) @ R_c2w, atol=1e-8)
    # the scene folder itself is accepted as root
    assert len(load_strecha(sdir).images) == 3


# ---------------------------------------------------------------- real data --------------------------------------

@needs_strecha
@pytest.mark.parametrize("name,n", [("fountain-P11", 11), ("Herz-Jesus-P8", 8), ("entry-P10", 10)])
def test_real_scenes_load(name, n):
    scene = load_scene(STRECHA, name)
    assert scene.name == name and scene.source == "strecha"
    assert len(scene.images) == n and len(scene.pairs) == n * (n - 1) // 2
    assert len({p.key for p in scene.pairs}) == len(scene.pairs)
    for im in scene.images.values():
        assert im.size == (1536, 1024) and im.path.is_file()
        np.testing.assert_allclose(im.R.T @ im.R, np.eye(3), atol=1e-5)
        assert np.linalg.det(im.R) == pytest.approx(1, abs=1e-5)
        cam = read_camera(STRECHA / name / "gt_dense_cameras" / f"{im.name}.camera")
        np.testing.assert_allclose(-im.R.T @ im.t, cam["C"], atol=1e-4)  # centre recovered
        w, h = im.size
        assert abs(im.K[0, 2] - w / 2) < 0.05 * w and abs(im.K[1, 2] - h / 2) < 0.05 * h


@needs_strecha
def test_real_K_matches_working_size():
    scene = load_scene(STRECHA, "fountain-P11")
    im = scene.images["0000.jpg"]
    img, sx, sy = load_image(im.path)
    h2, w2 = img.shape
    assert (w2, h2) == (1024, 683)
    K2 = scaled_K(im.K, sx, sy)
    assert abs(K2[0, 2] - w2 / 2) < 0.05 * w2 and abs(K2[1, 2] - h2 / 2) < 0.05 * h2
    assert K2[0, 0] == pytest.approx(im.K[0, 0] * sx)


def _median_epipolar_px(R, t, K1, K2, x1, x2):
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K2).T @ tx @ R @ np.linalg.inv(K1)
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    l2, l1 = h1 @ F.T, h2 @ F
    d2 = np.abs((h2 * l2).sum(1)) / np.hypot(l2[:, 0], l2[:, 1])
    d1 = np.abs((h1 * l1).sum(1)) / np.hypot(l1[:, 0], l1[:, 1])
    return float(np.median((d1 + d2) / 2))


@needs_strecha
def test_real_ground_truth_agrees_with_sift_matches():
    """The loaded poses (with their R^T convention) explain SIFT matches of fountain 0000/0001 to ~1 px at the
    working resolution; the wrong convention (R read as world-to-camera) does not."""
    scene = load_scene(STRECHA, "fountain-P11")
    pair = next(p for p in scene.pairs if (p.i, p.j) == ("0000.jpg", "0001.jpg"))
    a, b = scene.images[pair.i], scene.images[pair.j]
    (img1, sx1, sy1), (img2, sx2, sy2) = load_image(a.path), load_image(b.path)
    sift = cv2.SIFT_create(2000)
    k1, d1 = sift.detectAndCompute(img1, None)
    k2, d2 = sift.detectAndCompute(img2, None)
    matches = [m for m, n in cv2.BFMatcher().knnMatch(d1, d2, k=2) if m.distance < 0.8 * n.distance]
    assert len(matches) > 200
    x1 = np.float64([k1[m.queryIdx].pt for m in matches])
    x2 = np.float64([k2[m.trainIdx].pt for m in matches])
    K1, K2 = scaled_K(a.K, sx1, sy1), scaled_K(b.K, sx2, sy2)
    R, t = scene.relative_pose(pair)
    assert _median_epipolar_px(R, t, K1, K2, x1, x2) < 1.0
    Rw1, Rw2 = a.R.T, b.R.T  # wrong convention
    C1, C2 = -a.R.T @ a.t, -b.R.T @ b.t
    Rb = Rw2 @ Rw1.T
    tb = -Rw2 @ C2 - Rb @ (-Rw1 @ C1)
    assert _median_epipolar_px(Rb, tb, K1, K2, x1, x2) > 10.0


# ---------------------------------------------------------------- bad input --------------------------------------

def test_camera_with_wrong_number_of_values(strecha_copy):
    cam = strecha_copy / "fountain-P11" / "gt_dense_cameras" / "0003.jpg.camera"
    cam.write_text(" ".join(cam.read_text().split()[:-1]))  # 25 values
    with pytest.raises(ImtuneError, match="0003.jpg.camera") as e:
        load_scene(strecha_copy, "fountain-P11")
    assert "26" in str(e.value) and "\n" not in str(e.value)


def test_camera_with_non_numeric_value(strecha_copy):
    cam = strecha_copy / "fountain-P11" / "gt_dense_cameras" / "0004.jpg.camera"
    cam.write_text(cam.read_text().replace("0 0 0", "0 zero 0", 1))
    with pytest.raises(ImtuneError, match="0004.jpg.camera.*zero"):
        load_scene(strecha_copy, "fountain-P11")


def test_missing_camera_for_image(strecha_copy):
    (strecha_copy / "fountain-P11" / "gt_dense_cameras" / "0005.jpg.camera").unlink()
    with pytest.raises(ImtuneError, match="0005.jpg"):
        load_scene(strecha_copy, "fountain-P11")


def test_missing_image(strecha_copy):
    (strecha_copy / "fountain-P11" / "images" / "0006.jpg").unlink()
    with pytest.raises(ImtuneError, match="0006.jpg"):
        load_scene(strecha_copy, "fountain-P11")


@pytest.mark.parametrize("what", ["image", "camera file"])
@pytest.mark.parametrize("kind", ["a folder", "a FIFO", "a broken link"])
def test_something_else_at_an_image_or_camera_files_name_is_named(strecha_copy, what, kind):
    """A FIFO (or folder, or broken link) at an image's or camera file's name was "image missing for camera file
    ... expected <that very path>" / "missing camera file": the thing there unnamed. Now one line naming it."""
    sdir = strecha_copy / "fountain-P11"
    p = sdir / "images" / "0006.jpg" if what == "image" else sdir / "gt_dense_cameras" / "0006.jpg.camera"
    p.unlink()
    {"a folder": p.mkdir, "a FIFO": lambda: os.mkfifo(p), "a broken link": lambda: p.symlink_to(p.with_name("gone"))}[kind]()
    with pytest.raises(ImtuneError) as e:
        load_scene(strecha_copy, "fountain-P11")
    assert str(e.value) == f"{what} {p} is {kind}, not a file: put the {what} there"


def test_truncated_image(strecha_copy):
    img = strecha_copy / "fountain-P11" / "images" / "0007.jpg"
    data = img.read_bytes()
    img.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImtuneError, match="0007.jpg"):
        load_scene(strecha_copy, "fountain-P11")
    with pytest.raises(ImtuneError, match="0007.jpg"):
        load_image(img)
    # without verification the scene loads; the image fails when it is read
    assert len(load_scene(strecha_copy, "fountain-P11", verify=False).images) == 11


def test_image_size_disagreeing_with_camera(strecha_copy):
    img = strecha_copy / "fountain-P11" / "images" / "0008.jpg"
    cv2.imwrite(str(img), np.zeros((100, 150), np.uint8))
    with pytest.raises(ImtuneError, match="0008.jpg.*150x100"):
        load_scene(strecha_copy, "fountain-P11")


def test_unknown_scene_lists_available(strecha_copy):
    with pytest.raises(ImtuneError, match="castle-P19.*fountain-P11"):
        load_scene(strecha_copy, "castle-P19")
    with pytest.raises(ImtuneError, match="fountain-P11"):
        load_strecha(strecha_copy, "castle-P19")
