"""Pairs-with-GT loader (SuperGlue / LoFTR lists): real ScanNet sample and synthetic lists."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.data import detect_format, load_pairs_with_gt, load_scene
from pipeline.errors import ImtuneError


def _shared() -> Path:
    env = os.environ.get("IMTUNE_SHARED")
    if env:
        return Path(env) / "data" if (Path(env) / "data").is_dir() else Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


SCANNET = _shared() / "scannet_sample"
needs_scannet = pytest.mark.skipif(not SCANNET.is_dir(), reason=f"shared ScanNet sample not found at {SCANNET} "
                                                                 "(set IMTUNE_SHARED to the shared folder)")


def _fmt(a) -> str:
    return " ".join(f"{x:.10g}" for x in np.asarray(a).ravel())


def _write_list(root: Path, n_pairs: int = 3, seed: int = 0, images_dir: str = "images"):
    rng = np.random.default_rng(seed)
    (root / images_dir).mkdir(parents=True, exist_ok=True)
    truth, lines = [], []
    for k in range(n_pairs):
        n0, n1 = f"img{k}a.jpg", f"img{k}b.jpg"
        for n in (n0, n1):
            cv2.imwrite(str(root / images_dir / n), rng.integers(0, 255, (40, 60), dtype=np.uint8))
        K0 = np.array([[50.0 + k, 0, 29.5], [0, 51.0, 19.5], [0, 0, 1]])
        K1 = np.array([[60.0, 0, 30.0], [0, 61.0 + k, 20.0], [0, 0, 1]])
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.normal(size=3)
        truth.append((n0, n1, K0, K1, T))
        lines.append(f"{n0} {n1} 0 0 {_fmt(K0)} {_fmt(K1)} {_fmt(T)}")
    (root / "pairs_with_gt.txt").write_text("\n".join(lines) + "\n")
    return truth


@needs_scannet
def test_real_scannet_sample():
    assert detect_format(SCANNET) == "pairs_with_gt"
    scene = load_scene(SCANNET)
    assert scene.name == "scannet_sample" and scene.source == "pairs_with_gt"
    assert len(scene.pairs) == 15 and len(scene.images) == 30
    for p in scene.pairs:
        R, t = scene.relative_pose(p)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-3)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-3)
        assert np.all(np.isfinite(t)) and np.linalg.norm(t) > 0
        Ki, Kj = scene.intrinsics(p)
        assert Ki.shape == (3, 3) and Ki[0, 0] > 1000
        for n in (p.i, p.j):
            im = scene.images[n]
            assert im.size == (1296, 968) and im.path.is_file()
            assert abs(im.K[0, 2] - 1296 / 2) < 0.05 * 1296


def test_multiview_on_a_pairs_list_says_it_cannot_not_to_build_ground_truth(tmp_path):
    """A pairs list has relative poses only: no bags can be built for it, and the error says so (it said to run
    `tune data build-gt`, which then failed for want of poses)."""
    from pipeline.data.bags import scene_bags
    _write_list(tmp_path / "mylist", 3)
    scene = load_scene(tmp_path / "mylist")
    with pytest.raises(ImtuneError, match=r"no absolute poses .*pairs_with_gt gives a relative pose per pair.*stereo"):
        scene_bags(scene)


def test_synthetic_list_round_trips(tmp_path):
    truth = _write_list(tmp_path / "mylist", 3)
    scene = load_pairs_with_gt(tmp_path / "mylist")
    assert scene.name == "mylist" and len(scene.pairs) == 3 and len(scene.images) == 6
    for (n0, n1, K0, K1, T), p in zip(truth, scene.pairs):
        assert (p.i, p.j) == (n0, n1)
        R, t = scene.relative_pose(p)
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-9)
        np.testing.assert_allclose(t, T[:3, 3], atol=1e-9)
        Ki, Kj = scene.intrinsics(p)
        np.testing.assert_allclose(Ki, K0)
        np.testing.assert_allclose(Kj, K1)
        assert scene.images[n0].size == (60, 40)
    # images relative to the root (no images/ folder) and a folder of lists
    _write_list(tmp_path / "lists" / "flat", 2, images_dir=".")
    _write_list(tmp_path / "lists" / "other", 1)
    assert detect_format(tmp_path / "lists") == "pairs_with_gt"
    assert len(load_scene(tmp_path / "lists", "flat").pairs) == 2


def _corrupt_line(root: Path, lineno: int, fn):
    path = root / "pairs_with_gt.txt"
    lines = path.read_text().splitlines()
    lines[lineno - 1] = fn(lines[lineno - 1])
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("mutate,what", [
    (lambda ln: " ".join(ln.split()[:-1]), "found 37 fields"),
    (lambda ln: ln.replace(" 0 0 ", " 0 oops ", 1), "oops"),
    (lambda ln: ln.replace(" 0 0 ", " 90 0 ", 1), "rotation"),
])
def test_malformed_line_names_file_and_line(tmp_path, mutate, what):
    _write_list(tmp_path / "s", 3)
    _corrupt_line(tmp_path / "s", 2, mutate)
    with pytest.raises(ImtuneError, match=r"pairs_with_gt.txt, line 2") as e:
        load_pairs_with_gt(tmp_path / "s")
    assert what in str(e.value) and "\n" not in str(e.value)


def test_non_rotation_in_list_is_rejected(tmp_path):
    _write_list(tmp_path / "s", 2)
    _corrupt_line(tmp_path / "s", 1, lambda ln: " ".join(ln.split()[:22] + ["5"] + ln.split()[23:]))
    with pytest.raises(ImtuneError, match="line 1.*rotation"):
        load_pairs_with_gt(tmp_path / "s")


def test_missing_image(tmp_path):
    truth = _write_list(tmp_path / "s", 2)
    (tmp_path / "s" / "images" / truth[1][1]).unlink()
    with pytest.raises(ImtuneError, match=truth[1][1]):
        load_pairs_with_gt(tmp_path / "s")


@needs_scannet
def test_real_list_with_a_broken_line(tmp_path):
    dst = tmp_path / "scannet_sample"
    shutil.copytree(SCANNET, dst)
    _corrupt_line(dst, 7, lambda ln: ln + " 1.0")
    with pytest.raises(ImtuneError, match="line 7"):
        load_scene(dst)
