"""COLMAP sparse-model loader: a synthetic model written in COLMAP's text format, then as binary via pycolmap."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from pipeline.data import detect_format, list_scenes, load_colmap, load_scene
from pipeline.errors import ImtuneError

W, H = 120, 90


def _project(K, R, t, X):
    x = (X @ R.T + t) @ K.T
    return x[:, :2] / x[:, 2:]


def write_colmap_text(model: Path, images_dir: Path, n_images: int = 4, n_points: int = 30, seed: int = 0):
    """cameras.txt / images.txt / points3D.txt of a scene of cameras around the origin looking at it."""
    rng = np.random.default_rng(seed)
    model.mkdir(parents=True, exist_ok=True)
    images_dir.mkdir(parents=True, exist_ok=True)
    cams = [("PINHOLE", [100.0, 102.0, 59.5, 44.5]), ("SIMPLE_RADIAL", [95.0, 60.0, 45.0, 0.0])]
    X = rng.uniform(-1, 1, (n_points, 3))
    truth, obs = {}, {}
    img_lines = []
    for k in range(n_images):
        name = f"view_{k}.jpg"
        cv2.imwrite(str(images_dir / name), rng.integers(0, 255, (H, W), dtype=np.uint8))
        R = Rotation.from_euler("y", 20 * k - 30, degrees=True).as_matrix()
        t = np.array([0.1 * k, -0.05, 4.0])
        cam_id = 1 + k % 2
        f, *rest = cams[cam_id - 1][1]
        K = (np.array([[f, 0, rest[1]], [0, rest[0], rest[2]], [0, 0, 1]]) if cam_id == 1
             else np.array([[f, 0, rest[0]], [0, f, rest[1]], [0, 0, 1]]))
        x = _project(K, R, t, X)
        seen = np.flatnonzero(rng.random(n_points) < 0.8)
        q = Rotation.from_matrix(R).as_quat()  # x y z w
        img_lines.append(f"{k + 1} {q[3]:.17g} {q[0]:.17g} {q[1]:.17g} {q[2]:.17g} {t[0]:.17g} {t[1]:.17g} {t[2]:.17g} {cam_id} {name}")
        pts = [f"{x[p, 0]:.17g} {x[p, 1]:.17g} {p + 1}" for p in seen] + ["1.0 2.0 -1"]  # one untriangulated keypoint
        img_lines.append(" ".join(pts))
        truth[name] = (K, R, t)
        obs[name] = (seen, x[seen])
    (model / "cameras.txt").write_text("# Camera list\n" + "".join(
        f"{i + 1} {m} {W} {H} {' '.join(map(repr, p))}\n" for i, (m, p) in enumerate(cams)))
    (model / "images.txt").write_text("# Image list\n" + "\n".join(img_lines) + "\n")
    lines = []
    for p in range(n_points):
        track = [(k + 1, int(np.flatnonzero(obs[f"view_{k}.jpg"][0] == p)[0]))
                 for k in range(n_images) if p in obs[f"view_{k}.jpg"][0]]
        if len(track) < 2:
            continue
        lines.append(f"{p + 1} {X[p, 0]:.17g} {X[p, 1]:.17g} {X[p, 2]:.17g} 128 128 128 0.5 "
                     + " ".join(f"{i} {j}" for i, j in track))
    (model / "points3D.txt").write_text("# 3D points\n" + "\n".join(lines) + "\n")
    kept = sorted(int(ln.split()[0]) - 1 for ln in lines)
    return truth, obs, X, kept


def _centre(K):
    """K written in COLMAP's pixel-corner convention -> imtune's pixel-centre convention (cx, cy - 0.5 px)."""
    return K - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])


def _check(scene, truth, obs, X, kept):
    assert scene.source == "colmap" and len(scene.images) == len(truth)
    n = len(truth)
    assert len(scene.pairs) == n * (n - 1) // 2
    for name, (K, R, t) in truth.items():
        im = scene.images[name]
        np.testing.assert_allclose(im.K, _centre(K), atol=1e-9)
        np.testing.assert_allclose(im.R, R, atol=1e-9)
        np.testing.assert_allclose(im.t, t, atol=1e-9)
        assert im.size == (W, H) and im.path.is_file()
    assert scene.points3d.shape == (len(kept), 3)
    np.testing.assert_allclose(scene.points3d, X[kept], atol=1e-12)
    for name, (idx, xy) in scene.observations.items():
        ids = np.array(kept)[idx]  # back to the synthetic point numbers
        seen, x = obs[name]
        sel = np.isin(seen, kept)
        np.testing.assert_array_equal(np.sort(ids), np.sort(seen[sel]))
        order = np.argsort(ids)
        np.testing.assert_allclose(xy[order], x[sel][np.argsort(seen[sel])] - 0.5, atol=1e-9)
        # observations reproject: the model and the poses agree (both in the pixel-centre convention)
        K, R, t = truth[name]
        np.testing.assert_allclose(_project(_centre(K), R, t, scene.points3d[idx]), xy, atol=1e-6)


def test_colmap_text_model_round_trips(tmp_path):
    truth, obs, X, kept = write_colmap_text(tmp_path / "ds" / "bridge" / "sparse", tmp_path / "ds" / "bridge" / "images")
    assert detect_format(tmp_path / "ds") == "colmap"
    assert list_scenes(tmp_path / "ds") == ["bridge"]
    _check(load_scene(tmp_path / "ds", "bridge"), truth, obs, X, kept)


def test_colmap_binary_model_in_numbered_folder(tmp_path):
    sdir = tmp_path / "bridge"
    truth, obs, X, kept = write_colmap_text(tmp_path / "txt", sdir / "images")
    rec = pycolmap.Reconstruction(str(tmp_path / "txt"))
    (sdir / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(sdir / "sparse" / "0"))
    # a smaller second model: the loader takes the one with the most registered images
    write_colmap_text(tmp_path / "txt_small", tmp_path / "unused", n_images=3, seed=1)
    (sdir / "sparse" / "1").mkdir()
    pycolmap.Reconstruction(str(tmp_path / "txt_small")).write_binary(str(sdir / "sparse" / "1"))
    assert pycolmap.Reconstruction(str(sdir / "sparse" / "1")).num_reg_images() == len(truth) - 1
    _check(load_colmap(sdir), truth, obs, X, kept)


def test_unreadable_model_names_it(tmp_path):
    sdir = tmp_path / "broken"
    write_colmap_text(sdir / "sparse", sdir / "images")
    (sdir / "sparse" / "cameras.txt").write_text("1 NOT_A_MODEL 10 10 1 2 3\n")
    with pytest.raises(ImtuneError, match="unreadable COLMAP model .*broken/sparse"):
        load_colmap(sdir)
    bdir = tmp_path / "bin" / "sparse"
    bdir.mkdir(parents=True)
    for n in ("cameras", "images", "points3D"):
        (bdir / f"{n}.bin").write_bytes(b"")
    (tmp_path / "bin" / "images").mkdir()
    with pytest.raises(ImtuneError, match="unreadable COLMAP model .*bin/sparse"):
        load_colmap(tmp_path / "bin")


def test_missing_image_file(tmp_path):
    sdir = tmp_path / "s"
    write_colmap_text(sdir / "sparse", sdir / "images")
    (sdir / "images" / "view_2.jpg").unlink()
    with pytest.raises(ImtuneError, match="view_2.jpg"):
        load_colmap(sdir)
    assert len(load_colmap(sdir, verify=False).images) == 4


@pytest.mark.parametrize("focal", ["0", "-100"])
def test_a_camera_with_no_focal_length_is_refused(tmp_path, focal):
    """cameras.txt with a focal length of 0 (or < 0), which pycolmap reads without a word, was taken as ground
    truth K; now the Strecha / IMC check of K, one line naming the model, the camera and an image of it."""
    sdir = tmp_path / "bridge"
    write_colmap_text(sdir / "sparse", sdir / "images")
    cams = (sdir / "sparse" / "cameras.txt").read_text().splitlines()
    parts = cams[1].split()
    parts[4] = focal  # camera 1 (PINHOLE): fx
    cams[1] = " ".join(parts)
    (sdir / "sparse" / "cameras.txt").write_text("\n".join(cams) + "\n")
    with pytest.raises(ImtuneError) as e:
        load_colmap(sdir)
    msg = str(e.value)
    assert f"COLMAP model {sdir / 'sparse'}: camera 1 of view_0.jpg: not an intrinsics matrix" in msg, msg
    assert "\n" not in msg


def test_two_images_of_one_name_are_refused(tmp_path):
    """images.txt naming two registered images alike: the later one's pose and observations replaced the earlier's,
    3 images loaded of 4, without a word."""
    sdir = tmp_path / "bridge"
    write_colmap_text(sdir / "sparse", sdir / "images")
    lines = (sdir / "sparse" / "images.txt").read_text().splitlines()
    parts = lines[3].split()  # image 2's header line
    parts[-1] = "view_0.jpg"
    lines[3] = " ".join(parts)
    (sdir / "sparse" / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ImtuneError) as e:
        load_colmap(sdir)
    msg = str(e.value)
    assert f"COLMAP model {sdir / 'sparse'}: images 1 and 2 are both named 'view_0.jpg'" in msg and "\n" not in msg, msg


def test_an_images_txt_of_pose_lines_alone_is_refused(tmp_path):
    """images.txt written with each image's pose line and no 2D-points line after it (a model made by hand from known
    poses): COLMAP reads the line after each pose line as its 2D points, so image 2's pose line became image 1's
    points, and 2 of the 4 images were loaded (1 of their 6 pairs evaluated), without a word. Now one line naming
    images.txt's line and what each image takes."""
    sdir = tmp_path / "bridge"
    write_colmap_text(sdir / "sparse", sdir / "images")
    (sdir / "sparse" / "points3D.txt").write_text("# 3D points\n")
    lines = (sdir / "sparse" / "images.txt").read_text().splitlines()
    (sdir / "sparse" / "images.txt").write_text("\n".join([lines[0]] + lines[1::2]) + "\n")  # the pose lines only
    with pytest.raises(ImtuneError) as e:
        load_colmap(sdir)
    msg = str(e.value)
    assert msg.startswith(f"COLMAP model {sdir / 'sparse'}: images.txt line 3, read as the 2D points of image "
                          "'view_0.jpg'") and "an empty line when it has none" in msg and "\n" not in msg, msg
    # with an empty points line after each pose line, all 4 images and their 6 pairs
    (sdir / "sparse" / "images.txt").write_text("".join(f"{ln}\n\n" for ln in [lines[0]] + lines[1::2]))
    scene = load_colmap(sdir)
    assert sorted(scene.images) == [f"view_{k}.jpg" for k in range(4)] and len(scene.pairs) == 6


@pytest.mark.parametrize("quat", ["0 0 0 0", "0.0 0.0 0.0 0.0", "twice"])
def test_an_image_quaternion_that_is_no_rotation(tmp_path, quat):
    """images.txt with a zero quaternion: pycolmap keeps it and makes it the identity, so the image's ground-truth
    rotation came out of nothing, unsaid; a non-unit one (the true one x 2) gave a matrix that is no rotation. Now zero or
    non-finite is one line naming the image, and a non-unit quaternion is normalised (as COLMAP does)."""
    sdir = tmp_path / "bridge"
    truth, *_ = write_colmap_text(sdir / "sparse", sdir / "images")
    lines = (sdir / "sparse" / "images.txt").read_text().splitlines()
    parts = lines[3].split()  # image 2's header line: id qw qx qy qz ...
    parts[1:5] = [repr(2 * float(v)) for v in parts[1:5]] if quat == "twice" else quat.split()
    lines[3] = " ".join(parts)
    (sdir / "sparse" / "images.txt").write_text("\n".join(lines) + "\n")
    if quat == "twice":
        R = load_colmap(sdir).images["view_1.jpg"].R
        assert np.allclose(R, truth["view_1.jpg"][1], atol=1e-12)  # the rotation written, known
        return
    try:
        load_colmap(sdir)
    except ImtuneError as e:
        msg = str(e)
    else:
        raise AssertionError("loaded")
    assert msg.startswith(f"COLMAP model {sdir / 'sparse'}: image 2 (view_1.jpg): its rotation quaternion"), msg
    assert "\n" not in msg
