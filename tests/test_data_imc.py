"""IMC-PT 2020 and IMC 2022 loaders on fixtures written in the published layouts."""
from __future__ import annotations

import csv
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.data import default_splits, detect_format, list_scenes, load_imc2022, load_imc_pt2020, load_scene
from pipeline.data.imc2022 import read_scaling_factors
from pipeline.errors import ImtuneError

KEYS = ["01234567_8901234", "11111111_2222222", "33333333_444444", "55555555_66666"]
THRESHOLDS = {  # pair -> co-visibility bucket; keys-th-v lists every pair with bucket >= v
    (0, 1): 0.3, (0, 2): 0.1, (1, 2): 0.0, (2, 3): 0.2, (1, 3): 0.1,
}


def _cameras(n: int, seed: int):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        K = np.array([[300.0 + 10 * k, 0.5, 40.0], [0, 305.0, 30.0], [0, 0, 1]])
        out.append((K, Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 2))
    return out


def _image(path: Path, seed: int, w: int = 80, h: int = 60):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8))


def write_imc_pt2020(root: Path, scene: str = "reichstag", seed: int = 0, with_lists: bool = True):
    """phototourism/<scene>/set_100 exactly as the official benchmark lays it out."""
    sdir = root / scene / "set_100"
    cams = _cameras(len(KEYS), seed)
    for k, (key, (K, R, t)) in enumerate(zip(KEYS, cams)):
        _image(sdir / "images" / f"{key}.jpg", seed + k)
        (sdir / "calibration").mkdir(parents=True, exist_ok=True)
        with h5py.File(sdir / "calibration" / f"calibration_{key}.h5", "w") as f:
            f["K"], f["R"] = K, R
            f["T"] = t.reshape(3, 1) if k % 2 else t  # both shapes occur in the wild
            f["q"] = Rotation.from_matrix(R).as_quat()[[3, 0, 1, 2]]
        (sdir / "depth_maps").mkdir(exist_ok=True)
        if k != 3:
            with h5py.File(sdir / "depth_maps" / f"{key}.h5", "w") as f:
                f["depth"] = np.ones((60, 80), np.float32)
    if with_lists:
        (sdir / "images.txt").write_text("".join(f"images/{k}.jpg\n" for k in KEYS))
        (sdir / "calibration.txt").write_text("".join(f"calibration/calibration_{k}.h5\n" for k in KEYS))
    (sdir / "new-vis-pairs").mkdir()
    for v in np.arange(0, 1, 0.1):
        keys = [f"{KEYS[a]}-{KEYS[b]}" for (a, b), c in THRESHOLDS.items() if c >= v - 1e-9]
        np.save(sdir / "new-vis-pairs" / f"keys-th-{v:0.1f}.npy", np.array(keys))
    (sdir / "sub_set").mkdir()
    for n, bags in {3: [KEYS[:3], KEYS[1:]], 2: [KEYS[:2]]}.items():
        for b, members in enumerate(bags):
            (sdir / "sub_set" / f"{n}bag_{b:03d}.txt").write_text("".join(f"images/{m}.jpg\n" for m in members))
    return cams


def test_imc_pt2020_round_trip(tmp_path):
    cams = write_imc_pt2020(tmp_path / "phototourism")
    assert detect_format(tmp_path / "phototourism") == "imc_pt2020"
    scene = load_scene(tmp_path / "phototourism", "reichstag")
    assert scene.source == "imc_pt2020" and scene.name == "reichstag"
    assert list(scene.images) == [f"{k}.jpg" for k in KEYS]
    for key, (K, R, t) in zip(KEYS, cams):
        im = scene.images[f"{key}.jpg"]
        np.testing.assert_allclose(im.K, K)
        np.testing.assert_allclose(im.R, R)
        np.testing.assert_allclose(im.t, t)
        assert im.size == (80, 60)
    assert scene.images[f"{KEYS[0]}.jpg"].depth_path.name == f"{KEYS[0]}.h5"
    assert scene.images[f"{KEYS[3]}.jpg"].depth_path is None
    got = {(p.i, p.j): p.covisibility for p in scene.pairs}
    assert got == {(f"{KEYS[a]}.jpg", f"{KEYS[b]}.jpg"): pytest.approx(c) for (a, b), c in THRESHOLDS.items()}
    assert {(p.i, p.j) for p in scene.select_pairs(0.1)} == {
        (f"{KEYS[a]}.jpg", f"{KEYS[b]}.jpg") for (a, b), c in THRESHOLDS.items() if c >= 0.1}
    assert scene.bags == {2: [tuple(f"{k}.jpg" for k in KEYS[:2])],
                          3: [tuple(f"{k}.jpg" for k in KEYS[:3]), tuple(f"{k}.jpg" for k in KEYS[1:])]}
    # relative pose from the absolute ones, as the official benchmark computes it
    p = scene.pairs[0]
    (_, R1, t1), (_, R2, t2) = cams[KEYS.index(p.i[:-4])], cams[KEYS.index(p.j[:-4])]
    R, t = scene.relative_pose(p)
    np.testing.assert_allclose(R, R2 @ R1.T, atol=1e-12)
    np.testing.assert_allclose(t, t2 - R2 @ R1.T @ t1, atol=1e-12)


def test_imc_pt2020_root_variants(tmp_path):
    write_imc_pt2020(tmp_path / "pt", "sacre_coeur", with_lists=False)
    write_imc_pt2020(tmp_path / "pt", "st_peters_square", seed=5)
    assert list_scenes(tmp_path / "pt") == ["sacre_coeur", "st_peters_square"]
    assert default_splits(tmp_path / "pt") == {"val": ["sacre_coeur"], "test": ["st_peters_square"]}
    for root in (tmp_path / "pt" / "sacre_coeur", tmp_path / "pt" / "sacre_coeur" / "set_100"):
        scene = load_imc_pt2020(root)
        assert scene.name == "sacre_coeur" and len(scene.images) == 4 and len(scene.pairs) == 5


def test_imc_pt2020_errors(tmp_path):
    write_imc_pt2020(tmp_path / "pt")
    sdir = tmp_path / "pt" / "reichstag" / "set_100"
    with pytest.raises(ImtuneError, match="unknown scene 'nope'.*reichstag"):
        load_scene(tmp_path / "pt", "nope")
    np.save(sdir / "new-vis-pairs" / "keys-th-0.5.npy", np.array([{"a": 1}], dtype=object))
    with pytest.raises(ImtuneError, match="keys-th-0.5.npy"):
        load_imc_pt2020(tmp_path / "pt")
    (sdir / "new-vis-pairs" / "keys-th-0.5.npy").unlink()
    with h5py.File(sdir / "calibration" / f"calibration_{KEYS[1]}.h5", "w") as f:
        f["K"] = np.eye(3)
    with pytest.raises(ImtuneError, match=f"calibration_{KEYS[1]}.h5.*R, T"):
        load_imc_pt2020(tmp_path / "pt")
    (sdir / "calibration" / f"calibration_{KEYS[1]}.h5").unlink()
    with pytest.raises(ImtuneError, match=f"calibration_{KEYS[1]}.h5"):
        load_imc_pt2020(tmp_path / "pt")



def test_imc_pt2020_non_finite_translation_is_refused(tmp_path):
    """A calibration_<key>.h5 whose T holds a NaN loaded as ground truth (K and R are checked, T was not)."""
    write_imc_pt2020(tmp_path / "pt")
    calib = tmp_path / "pt" / "reichstag" / "set_100" / "calibration" / f"calibration_{KEYS[1]}.h5"
    with h5py.File(calib, "a") as f:
        T = f["T"][()].astype(np.float64)
        T.flat[0] = np.nan
        del f["T"]
        f["T"] = T
    with pytest.raises(ImtuneError) as e:
        load_imc_pt2020(tmp_path / "pt")
    msg = str(e.value)
    assert f"calibration file {calib}: non-finite value in T" in msg and "\n" not in msg, msg

# ---------------------------------------------------------------- IMC 2022 ---------------------------------------

IDS = ["92031733_3992238201", "54163059_5716537618", "64223960_5316591967"]


def write_imc2022(root: Path, scene: str = "british_museum", seed: int = 1):
    """train/<scene>/{images, calibration.csv, pair_covisibility.csv} + train/scaling_factors.csv (Kaggle layout)."""
    sdir = root / "train" / scene
    cams = _cameras(len(IDS), seed)
    with open(sdir.parent.joinpath("scaling_factors.csv") if sdir.parent.is_dir() else _mk(sdir.parent) /
              "scaling_factors.csv", "a", newline="") as f:
        w = csv.writer(f)
        if f.tell() == 0:
            w.writerow(["scene", "scaling_factor"])
        w.writerow([scene, 2.5])
    sdir.mkdir(parents=True, exist_ok=True)
    with open(sdir / "calibration.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image_id", "camera_intrinsics", "rotation_matrix", "translation_vector"])
        for k, (i, (K, R, t)) in enumerate(zip(IDS, cams)):
            _image(sdir / "images" / f"{i}.jpg", seed + k)
            w.writerow([i, _nums(K), _nums(R), _nums(t)])
    covis = {(0, 1): 0.42, (0, 2): 0.05, (1, 2): 0.9}
    with open(sdir / "pair_covisibility.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["pair", "covisibility", "fundamental_matrix"])
        for (a, b), c in covis.items():
            w.writerow([f"{IDS[a]}-{IDS[b]}", c, " ".join(["0.1"] * 9)])
    return cams, covis


def _nums(a) -> str:
    return " ".join(f"{x:.17g}" for x in np.asarray(a).ravel())


def _mk(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


def test_imc2022_round_trip(tmp_path):
    cams, covis = write_imc2022(tmp_path / "imc")
    write_imc2022(tmp_path / "imc", "taj_mahal", seed=7)
    assert detect_format(tmp_path / "imc") == "imc2022"
    assert list_scenes(tmp_path / "imc") == ["british_museum", "taj_mahal"]
    assert read_scaling_factors(tmp_path / "imc") == {"british_museum": 2.5, "taj_mahal": 2.5}
    for root in (tmp_path / "imc", tmp_path / "imc" / "train"):
        scene = load_scene(root, "british_museum")
        assert scene.source == "imc2022" and len(scene.images) == 3
        for i, (K, R, t) in zip(IDS, cams):
            im = scene.images[f"{i}.jpg"]
            np.testing.assert_allclose(im.K, K)
            np.testing.assert_allclose(im.R, R)
            np.testing.assert_allclose(im.t, t)
            assert im.size == (80, 60)
        assert {(p.i, p.j): p.covisibility for p in scene.pairs} == {
            (f"{IDS[a]}.jpg", f"{IDS[b]}.jpg"): c for (a, b), c in covis.items()}
        assert len(scene.select_pairs(0.1)) == 2
    assert load_imc2022(tmp_path / "imc" / "train" / "taj_mahal").name == "taj_mahal"


def _imc2022_error(root: Path) -> str:
    """The one-line error load_imc2022(root) raises."""
    with pytest.raises(ImtuneError) as e:
        load_imc2022(root)
    msg = str(e.value)
    assert "\n" not in msg, msg
    return msg


def test_imc2022_errors(tmp_path):
    write_imc2022(tmp_path / "imc")
    sdir = tmp_path / "imc" / "train" / "british_museum"
    calib = sdir / "calibration.csv"
    text = calib.read_text()
    calib.write_text(text.replace("translation_vector", "translation"))
    with pytest.raises(ImtuneError, match="calibration.csv.*translation_vector"):
        load_imc2022(tmp_path / "imc")
    lines = text.splitlines()
    lines[2] = lines[2].rsplit(",", 1)[0] + ",1.0 2.0"
    calib.write_text("\n".join(lines) + "\n")
    with pytest.raises(ImtuneError, match="calibration.csv, line 3.*expected 3 numbers"):
        load_imc2022(tmp_path / "imc")
    calib.write_text(text)
    covis = sdir / "pair_covisibility.csv"
    covis.write_text(covis.read_text() + f"{IDS[0]}-99999999_1,0.5,\n")
    with pytest.raises(ImtuneError, match="pair_covisibility.csv, line 5.*99999999_1"):
        load_imc2022(tmp_path / "imc")


@pytest.mark.parametrize("extra,needle", [
    (lambda: f"{IDS[1]}-{IDS[0]},0.42,", "lines 2 and 5: the pair"),  # listed again, the other way round
    (lambda: f"{IDS[0]}-{IDS[1]},0.42,", "lines 2 and 5: the pair"),  # listed again as it was
    (lambda: f"{IDS[2]}-{IDS[2]},1.0,", "line 5: pair"),  # an image with itself
])
def test_imc2022_pair_listed_twice_or_with_itself_is_refused(tmp_path, extra, needle):
    """pair_covisibility.csv listing a pair twice (either order) evaluated it twice: it counted twice in every mAA
    (5 pairs evaluated for 3 images); an image paired with itself has no relative pose to estimate."""
    write_imc2022(tmp_path / "imc")
    covis = tmp_path / "imc" / "train" / "british_museum" / "pair_covisibility.csv"
    covis.write_text(covis.read_text() + extra() + "\n")
    msg = _imc2022_error(tmp_path / "imc")
    assert str(covis) in msg and needle in msg and "\n" not in msg, msg


def test_imc2022_image_listed_twice_in_calibration_is_refused(tmp_path):
    """A second calibration.csv row for an image_id replaced the first one's K, R, t without a word."""
    write_imc2022(tmp_path / "imc")
    calib = tmp_path / "imc" / "train" / "british_museum" / "calibration.csv"
    lines = calib.read_text().splitlines()
    calib.write_text("\n".join(lines + [lines[1]]) + "\n")
    msg = _imc2022_error(tmp_path / "imc")
    assert f"{calib}, lines 2 and 5: image_id {IDS[0]!r} is listed twice" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_imc2022_covisibility_file_that_is_no_file_is_named(tmp_path, kind):
    """A folder (or a FIFO) at pair_covisibility.csv was read as "no co-visibility file": every pair of the scene
    evaluated, co-visibility unknown, without a word (a FIFO would have blocked the reader). Now one line naming it."""
    import os
    write_imc2022(tmp_path / "imc")
    covis = tmp_path / "imc" / "train" / "british_museum" / "pair_covisibility.csv"
    covis.unlink()
    covis.mkdir() if kind == "folder" else os.mkfifo(covis)
    msg = _imc2022_error(tmp_path / "imc")
    assert msg.startswith(f"IMC 2022 file {covis} is ") and "\n" not in msg, msg


@pytest.mark.parametrize("value", ["5", "-0.2"])
def test_imc2022_covisibility_outside_0_1_is_refused(tmp_path, value):
    """A co-visibility is a fraction: 5 passed every --covisibility threshold and -0.2 none, without a word."""
    write_imc2022(tmp_path / "imc")
    covis = tmp_path / "imc" / "train" / "british_museum" / "pair_covisibility.csv"
    covis.write_text(covis.read_text().replace(",0.42,", f",{value},"))
    msg = _imc2022_error(tmp_path / "imc")
    assert f"{covis}, line 2: covisibility must be in [0, 1], got {value}" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("how", ["reversed", "self"])
def test_imc_pt2020_pair_listed_in_both_orders_or_with_itself_is_refused(tmp_path, how):
    """new-vis-pairs lists that also held a pair as keyB-keyA (after keyA-keyB) evaluated it twice: 6 pairs for the
    5 listed, one counting twice in every mAA; keyA-keyA has no relative pose to estimate."""
    write_imc_pt2020(tmp_path / "pt")
    vis = tmp_path / "pt" / "reichstag" / "set_100" / "new-vis-pairs"
    a, b = next(iter(THRESHOLDS))
    keys = list(np.load(vis / "keys-th-0.0.npy"))
    keys.append(f"{KEYS[b]}-{KEYS[a]}" if how == "reversed" else f"{KEYS[a]}-{KEYS[a]}")
    np.save(vis / "keys-th-0.0.npy", np.array(keys))
    with pytest.raises(ImtuneError) as e:
        load_imc_pt2020(tmp_path / "pt")
    msg = str(e.value)
    needle = f"lists the pair {KEYS[a]}-{KEYS[b]} again as {KEYS[b]}-{KEYS[a]}" if how == "reversed" else \
        f"pairs image {KEYS[a]} with itself"
    assert f"pair list in {vis}: {needle}" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("how", ["image-twice", "cut-short"])
def test_imc_pt2020_bag_file_with_an_image_twice_or_too_few_is_refused(tmp_path, how):
    """sub_set/3bag_000.txt listing an image twice (or only 2 images) was a bag of 3 holding 2 distinct images,
    read as a bag of size 3 without a word."""
    write_imc_pt2020(tmp_path / "pt")
    bag = tmp_path / "pt" / "reichstag" / "set_100" / "sub_set" / "3bag_000.txt"
    lines = bag.read_text().splitlines()
    lines = lines[:2] + [lines[0]] if how == "image-twice" else lines[:2]
    bag.write_text("\n".join(lines) + "\n")
    with pytest.raises(ImtuneError) as e:
        load_imc_pt2020(tmp_path / "pt")
    msg = str(e.value)
    needle = f"image {lines[0]!r} is listed twice" if how == "image-twice" else "2 images in a bag of 3"
    assert f"bag file {bag}: {needle}" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("where,kind,needle", [
    ("new-vis-pairs", "file", "pair list folder {p} is a file, not a folder"),
    ("sub_set", "file", "bag folder {p} is a file, not a folder"),
    (f"depth_maps/{KEYS[0]}.h5", "folder", "depth map {p} is a folder, not a file"),
    ("new-vis-pairs", "broken link", "pair list folder {p} is a broken link"),
])
def test_imc_pt2020_something_else_at_an_optional_name_is_said(tmp_path, where, kind, needle):
    """A file at new-vis-pairs/ (an archive not unpacked) was read as no pair list: every pair evaluated, co-visibility
    unknown, unsaid; a file at sub_set/: no bags; a folder at a depth map: no depth. Now one line naming it."""
    import shutil
    write_imc_pt2020(tmp_path / "pt")
    p = tmp_path / "pt" / "reichstag" / "set_100" / where
    shutil.rmtree(p) if p.is_dir() else p.unlink()
    if kind == "file":
        p.write_bytes(b"PK\x03\x04")
    elif kind == "folder":
        p.mkdir()
    else:
        p.symlink_to(tmp_path / "nowhere")
    with pytest.raises(ImtuneError) as e:
        load_scene(tmp_path / "pt", "reichstag")
    assert needle.format(p=p) in str(e.value) and "\n" not in str(e.value)
