"""Bring-your-own features and matches (the official IMC import h5 layout): round trip, evaluation through
the real pipeline and the CLI, and every bad input -> one-line error naming the file and the key."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import yaml

from pipeline.cache import H5Cache
from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
from pipeline.data import load_scene
from pipeline.data.resize import scale_points
from pipeline.errors import ImtuneError
from pipeline.tasks.prepare import image_features
from pipeline.tasks.stereo import evaluate_stereo
from tests.conftest import DATA
from tests.test_cli_evaluate import tune

SCENE = "fountain-P11"
IMAGES = ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"]
K = 2048


@pytest.fixture(scope="module")
def mini(tmp_path_factory) -> Path:
    """A 4-image Strecha scene (real fountain-P11 images and cameras)."""
    src = DATA / "strecha" / SCENE
    if not src.exists():
        pytest.skip(f"real data not found at {src}")
    root = tmp_path_factory.mktemp("data")
    for sub, suffix in (("images", ""), ("gt_dense_cameras", ".camera")):
        (root / SCENE / sub).mkdir(parents=True)
        for n in IMAGES:
            shutil.copy(src / sub / (n + suffix), root / SCENE / sub / (n + suffix))
    return root


@pytest.fixture(scope="module")
def good(mini, tmp_path_factory) -> Path:
    """Features (OpenCV SIFT on the images as stored: 1536x1024) and mutual-NN matches, written in the
    benchmark's layout <DIR>/<dataset>/<scene>/*.h5."""
    out = tmp_path_factory.mktemp("byo")
    d = out / "strecha" / SCENE
    d.mkdir(parents=True)
    sift = cv2.SIFT_create(K)
    feats = {}
    for n in IMAGES:
        img = cv2.imread(str(mini / SCENE / "images" / n), cv2.IMREAD_GRAYSCALE)
        kps, desc = sift.detectAndCompute(img, None)
        kps, desc = kps[:K], desc[:K]
        feats[n[:-4]] = (np.array([k.pt for k in kps], np.float32), desc.astype(np.float32),
                         np.array([k.response for k in kps], np.float32), np.array([k.size for k in kps], np.float32),
                         np.array([k.angle for k in kps], np.float32))
    with h5py.File(d / "keypoints.h5", "w") as fk, h5py.File(d / "descriptors.h5", "w") as fd, \
            h5py.File(d / "scores.h5", "w") as fs, h5py.File(d / "scales.h5", "w") as fc, \
            h5py.File(d / "orientations.h5", "w") as fo:
        for key, (kp, desc, sc, size, ang) in feats.items():
            fk[key], fd[key], fs[key], fc[key], fo[key] = kp, desc, sc, size, ang
    with h5py.File(d / "matches.h5", "w") as fm:
        keys = list(feats)
        for a in keys:
            for b in keys:
                if a > b:  # the benchmark's key order: "<larger>-<smaller>", rows index a then b
                    da, db = feats[a][1], feats[b][1]
                    dist = (da ** 2).sum(1)[:, None] + (db ** 2).sum(1)[None] - 2 * da @ db.T
                    nn_ab, nn_ba = dist.argmin(1), dist.argmin(0)
                    srt = np.sort(dist, 1)
                    i = np.flatnonzero((nn_ba[nn_ab] == np.arange(len(da))) & (srt[:, 0] < 0.8 ** 2 * srt[:, 1]))
                    fm[f"{a}-{b}"] = np.stack([i, nn_ab[i]]).astype(np.int32)
    return out


def conf(feature, custom_matches=None, ratio=0.85, k=K):
    return PipelineConfig(FeatureConfig(name=feature, num_features=k),
                          MatchConfig(ratio=ratio, custom_matches=custom_matches),
                          GeometryConfig(ransac="degensac", threshold=0.75, max_iters=5000))


def copy_of(good: Path, tmp_path: Path) -> tuple[Path, Path]:
    d = tmp_path / "byo"
    shutil.copytree(good, d)
    return d, d / "strecha" / SCENE


def test_round_trip(mini, good, cache_dir):
    sc = load_scene(mini, SCENE)
    info = sc.images["0004.jpg"]
    f = image_features(H5Cache(cache_dir), info, FeatureConfig(name=f"custom:{good}", num_features=K))
    with h5py.File(good / "strecha" / SCENE / "keypoints.h5") as fk, \
            h5py.File(good / "strecha" / SCENE / "descriptors.h5") as fd:
        kp, desc = fk["0004"][()], fd["0004"][()]
    assert (f.width, f.height) == (1024, 683)
    np.testing.assert_allclose(f.keypoints, scale_points(kp, f.sx, f.sy), atol=1e-3)
    np.testing.assert_array_equal(f.descriptors, desc)
    assert not f.binary and f.scores is not None and f.scales is not None and f.orientations is not None
    # budget: the strongest by scores.h5
    g = image_features(H5Cache(cache_dir), info, FeatureConfig(name=f"custom:{good}", num_features=500))
    with h5py.File(good / "strecha" / SCENE / "scores.h5") as fs:
        sc_all = fs["0004"][()]
    assert len(g.keypoints) == 500 and np.isclose(g.scores.min(), np.sort(sc_all)[-500])


def test_stereo_with_custom_features_and_matcher(mini, good, cache_dir):
    sc = load_scene(mini, SCENE)
    res = evaluate_stereo([sc], conf(f"custom:{good}"), H5Cache(cache_dir), min_covisibility=None)
    assert res.summary["pairs"] == 6 and res.summary["NF"] == K
    assert res.summary["mAA10"] > 0.6, res.records


def test_stereo_with_custom_matches(mini, good, cache_dir):
    sc = load_scene(mini, SCENE)
    res = evaluate_stereo([sc], conf(f"custom:{good}", custom_matches=str(good), ratio=0.5),
                          H5Cache(cache_dir), min_covisibility=None)
    with h5py.File(good / "strecha" / SCENE / "matches.h5") as fm:
        counts = {k: fm[k].shape[1] for k in fm}
    by_pair = {r["pair"]: r["NM"] for r in res.records}
    assert by_pair["0003.jpg|0004.jpg"] == counts["0004-0003"]  # the file's matches, unfiltered (r ignored)
    assert res.summary["mAA10"] > 0.6, res.records


def test_cli_custom_features_and_matches(mini, good, tmp_path):
    r = tune("evaluate", "--feature", f"custom:{good}", "--matches", f"custom:{good}", "--num-features", str(K),
             "--ransac", "degensac", "--threshold", "0.75", "--max-iters", "5000", "--data", str(mini),
             "--scenes", SCENE, "--json", "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "c")})
    assert r.returncode == 0, r.stderr
    st = json.loads(r.stdout)["stereo"]
    assert st["pairs"] == 6 and st["mAA10"] > 0.6
    r = tune("evaluate", "--feature", "sift", "--matches", f"custom:{good}", "--data", str(mini),
             env={"IMTUNE_CACHE": str(tmp_path / "c")})
    assert r.returncode != 0 and "needs --feature custom:DIR" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_cli_custom_matches_say_no_ratio_test_and_refuse_matcher_options(mini, good, tmp_path):
    """Imported matches skip the matcher, yet the run was labelled (and recorded) with the default r 0.85, and a
    typed --ratio / --fginn / --strategy / --matcher was accepted and ignored."""
    base = ["evaluate", "--feature", f"custom:{good}", "--matches", f"custom:{good}", "--num-features", str(K),
            "--max-iters", "2000", "--data", str(mini), "--scenes", SCENE, "--quiet", "--ci", "none"]
    env = {"IMTUNE_CACHE": str(tmp_path / "c")}
    r = tune(*base, "--json", env=env)
    assert r.returncode == 0, r.stderr
    m = json.loads(r.stdout)["config"]["matching"]
    assert (m["ratio"], m["strategy"], m["fginn"], m["distance_threshold"]) == (1.0, "both", False, None), m
    for opt in (["--ratio", "0.8"], ["--fginn"], ["--strategy", "uni"], ["--matcher", "flann"]):
        r = tune(*base, *opt, env=env)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, r.stderr
        assert f"{opt[0]} does not apply with --matches custom:DIR" in lines[0] and "drop it" in lines[0], lines

@pytest.mark.parametrize("field,value", [("ratio", 0.8), ("strategy", "uni"), ("fginn", True), (None, None)])
def test_a_config_file_with_custom_matches_and_a_ratio_is_said(field, value, mini, good, tmp_path):
    """A config file with matching.custom_matches and ratio 0.8 ran without that ratio test (imported matches skip
    the matcher) and was recorded and labelled r 0.8. Now one line naming the file and the field; without one
    (the defaults: r 1, both) it runs."""
    f = tmp_path / "cm.yaml"
    matching = {"custom_matches": str(good), **({field: value} if field else {})}
    f.write_text(yaml.safe_dump({"config": {"feature": {"name": f"custom:{good}", "num_features": K},
                                            "matching": matching,
                                            "geometry": {"ransac": "degensac", "max_iters": 2000}}}))
    r = tune("evaluate", "--config", str(f), "--data", str(mini), "--scenes", SCENE, "--quiet", "--ci", "none",
             "--json", env={"IMTUNE_CACHE": str(tmp_path / "c")})
    if field is None:
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout)["config"]["matching"]["ratio"] == 1.0
        return
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"tune: error: {f}: matching.{field} {value!r} with custom_matches: imported matches "
                               "skip the matcher"), lines


@pytest.mark.parametrize("fix", ["ratio=0.7", "strategy=either"])
def test_run_with_custom_matches_refuses_a_matcher_fix(fix, mini, good, tmp_path):
    """--fix ratio=0.7 with --matches said "--fix ratio is given twice (ratio=0.7 and ratio=1.0)": given once by the
    user, the other pin was the one --matches makes. Now the cause, before any work (no storage made)."""
    st = tmp_path / "st"
    r = tune("run", "--feature", f"custom:{good}", "--matches", f"custom:{good}", "--num-features", str(K),
             "--data", str(mini), "--studies-dir", str(st), "--fix", fix, "--fix", "max_iters=1000", "--n-trials", "1",
             "--no-test", "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "c")})
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert f"--fix {fix} does not apply with --matches custom:DIR" in lines[0] and "drop it" in lines[0], lines
    assert not (st / "optuna.db").exists()

def _corrupt(path: Path, key: str, fn):
    with h5py.File(path, "a") as f:
        a = f[key][()]
        del f[key]
        new = fn(a)
        if new is not None:
            f[key] = new


@pytest.mark.parametrize("file,key,fn,needle", [
    ("descriptors.h5", "0004", lambda a: np.where(np.arange(len(a))[:, None] == 3, np.nan, a), "NaN"),
    ("descriptors.h5", "0005", lambda a: a[:, :64], "dimension"),
    ("descriptors.h5", "0005", lambda a: a[:-1], "match"),
    ("keypoints.h5", "0003", lambda a: np.vstack([a[:-1], [[5000.0, 10.0]]]).astype(np.float32), "outside"),
    ("keypoints.h5", "0003", lambda a: np.vstack([a[:-1], [[np.nan, 10.0]]]).astype(np.float32), "NaN"),
    ("keypoints.h5", "0006", lambda a: None, "no key"),
])
def test_bad_features(mini, good, tmp_path, cache_dir, file, key, fn, needle):
    byo, scene_dir = copy_of(good, tmp_path)
    _corrupt(scene_dir / file, key, fn)
    sc = load_scene(mini, SCENE)
    with pytest.raises(ImtuneError) as e:
        evaluate_stereo([sc], conf(f"custom:{byo}"), H5Cache(cache_dir), min_covisibility=None)
    msg = str(e.value)
    assert str(scene_dir / file) in msg and f"'{key}'" in msg, msg
    assert needle in msg and "\n" not in msg, msg


@pytest.mark.parametrize("mutate,needle", [
    (lambda a: np.where(np.arange(a.shape[1]) == 2, 99999, a), "out of range"),
    (lambda a: None, "no key"),
    (lambda a: a[:1], "(2, M)"),
    (lambda a: a.astype(np.float32) + 0.5, "integers"),
    # a match given twice counted twice in NM and NI (and weighed twice by the estimator), unsaid
    (lambda a: np.hstack([a, a[:, 2:5]]), "3 duplicate matches"),
])
def test_bad_matches(mini, good, tmp_path, cache_dir, mutate, needle):
    byo, scene_dir = copy_of(good, tmp_path)
    _corrupt(scene_dir / "matches.h5", "0005-0004", mutate)
    sc = load_scene(mini, SCENE)
    with pytest.raises(ImtuneError) as e:
        evaluate_stereo([sc], conf(f"custom:{byo}", custom_matches=str(byo)), H5Cache(cache_dir), min_covisibility=None)
    msg = str(e.value)
    assert str(scene_dir / "matches.h5") in msg and "0005" in msg and "0004" in msg, msg
    assert needle in msg and "\n" not in msg, msg


def test_budget_and_alignment_errors(mini, good, tmp_path, cache_dir):
    byo, scene_dir = copy_of(good, tmp_path)
    (scene_dir / "scores.h5").unlink()
    sc = load_scene(mini, SCENE)
    with pytest.raises(ImtuneError, match="no scores.h5") as e:
        evaluate_stereo([sc], conf(f"custom:{byo}", k=1000), H5Cache(cache_dir), min_covisibility=None)
    assert "keypoints.h5" in str(e.value)
    # custom matches index all keypoints: a smaller budget would misalign them -> error, not garbage
    with pytest.raises(ImtuneError, match="index the"):
        evaluate_stereo([sc], conf(f"custom:{good}", custom_matches=str(good), k=1000), H5Cache(cache_dir),
                        min_covisibility=None)


@pytest.mark.parametrize("file,kind", [("scales.h5", "folder"), ("orientations.h5", "folder"),
                                       ("descriptors.h5", "folder"), ("keypoints.h5", "FIFO")])
def test_something_else_at_an_h5_name_is_named_not_read_as_absent(mini, good, tmp_path, cache_dir, file, kind):
    """A folder at scales.h5 / orientations.h5 was read as no file: AdaLAM ran without scales (or orientations),
    unsaid; at descriptors.h5 it was "without descriptors.h5"; a FIFO at keypoints.h5 was "file not found". Now one
    line naming it."""
    import os
    byo, scene_dir = copy_of(good, tmp_path)
    (scene_dir / file).unlink()
    os.mkfifo(scene_dir / file) if kind == "FIFO" else (scene_dir / file).mkdir()
    sc = load_scene(mini, SCENE)
    c = conf(f"custom:{byo}")
    c = PipelineConfig(c.feature, MatchConfig(ratio=0.85, prefilter="adalam"), c.geometry)
    with pytest.raises(ImtuneError) as e:
        evaluate_stereo([sc], c, H5Cache(cache_dir), min_covisibility=None)
    assert str(e.value) == f"{scene_dir / file} is a {kind}, not an h5 file: move it away, or put the file there"


def test_cli_bad_input_one_line(mini, good, tmp_path):
    byo, scene_dir = copy_of(good, tmp_path)
    _corrupt(scene_dir / "keypoints.h5", "0006", lambda a: None)
    r = tune("evaluate", "--feature", f"custom:{byo}", "--num-features", str(K), "--data", str(mini),
             "--scenes", SCENE, "--quiet", env={"IMTUNE_CACHE": str(tmp_path / "c")})
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "keypoints.h5" in lines[0] and "0006" in lines[0], r.stderr
    r = tune("evaluate", "--feature", f"custom:{tmp_path / 'nowhere'}", "--data", str(mini))
    assert r.returncode != 0 and "does not exist" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_match_file_per_task(mini, good, tmp_path, cache_dir):
    """matches_stereo_0.h5 for stereo and matches_multiview.h5 for multiview win over matches.h5."""
    from pipeline.tasks.prepare import pair_knn, tentative_matches
    byo, scene_dir = copy_of(good, tmp_path)
    with h5py.File(scene_dir / "matches.h5") as f:
        full = f["0004-0003"][()]
    for name, n in (("matches_stereo_0.h5", 10), ("matches_multiview.h5", 20)):
        with h5py.File(scene_dir / name, "w") as f:
            f["0004-0003"] = full[:, :n]
    sc = load_scene(mini, SCENE)
    cache = H5Cache(cache_dir)
    fc = FeatureConfig(name=f"custom:{byo}", num_features=K)
    fi, fj = image_features(cache, sc.images["0003.jpg"], fc), image_features(cache, sc.images["0004.jpg"], fc)
    mc = MatchConfig(custom_matches=str(byo))
    tab, secs = pair_knn(cache, fi, fj, mc)
    assert secs == 0.0
    stereo, _ = tentative_matches(tab, mc, fi, fj)
    multi, _ = tentative_matches(tab, mc, fi, fj, task="multiview")
    assert len(stereo) == 10 and len(multi) == 20
    np.testing.assert_array_equal(stereo, full[:, :10][::-1].T)  # key "0004-0003": rows swapped to (0003, 0004)


@pytest.mark.parametrize("name,task", [("matches_multiview.h5", "multiview"), ("matches_stereo_0.h5", "stereo")])
def test_a_folder_at_a_task_match_file_is_named_not_passed_over(name, task, mini, good, tmp_path, cache_dir):
    """A folder at matches_multiview.h5 (or matches_stereo_0.h5) was passed over for matches.h5: the task got the
    other file's matches, unsaid. Now one line naming it."""
    from pipeline.tasks.prepare import pair_knn, tentative_matches
    byo, scene_dir = copy_of(good, tmp_path)
    (scene_dir / name).mkdir()
    sc = load_scene(mini, SCENE)
    cache = H5Cache(cache_dir)
    fc = FeatureConfig(name=f"custom:{byo}", num_features=K)
    fi, fj = image_features(cache, sc.images["0003.jpg"], fc), image_features(cache, sc.images["0004.jpg"], fc)
    mc = MatchConfig(custom_matches=str(byo))
    with pytest.raises(ImtuneError) as e:
        tentative_matches(pair_knn(cache, fi, fj, mc)[0], mc, fi, fj, task=task)
    assert str(e.value) == f"{scene_dir / name} is a folder, not an h5 file: move it away, or put the file there"


def test_one_scene_folder_is_not_read_for_another_scene(mini, good, tmp_path, cache_dir):
    """An import folder holding fountain-P11/ only, evaluated on every scene of the data (`tune evaluate
    --feature custom:DIR` without --scenes): Herz-Jesus-P8's 0003.jpg ... were given fountain-P11's 0003 ...
    keypoints (the lone scene folder served every scene), and its pairs scored mAA 0 with 900 "inliers", unsaid.
    Now the lone folder serves the scene it is named after (or DIR itself is the scene folder); another scene is
    a one-line error naming the folder and the image."""
    other = "Herz-Jesus-P8"
    src = DATA / "strecha" / other
    if not src.exists():
        pytest.skip(f"real data not found at {src}")
    data = tmp_path / "data"
    shutil.copytree(mini / SCENE, data / SCENE)
    for sub, suffix in (("images", ""), ("gt_dense_cameras", ".camera")):
        (data / other / sub).mkdir(parents=True)
        for n in IMAGES:
            shutil.copy(src / sub / (n + suffix), data / other / sub / (n + suffix))
    fc = FeatureConfig(name=f"custom:{good}", num_features=K)
    assert len(image_features(H5Cache(cache_dir), load_scene(data, SCENE).images["0004.jpg"], fc).keypoints) == K
    with pytest.raises(ImtuneError, match=f"{other}.*0004.jpg|0004.jpg.*{other}") as e:
        image_features(H5Cache(cache_dir), load_scene(data, other).images["0004.jpg"], fc)
    assert "\n" not in str(e.value) and SCENE in str(e.value)
    # DIR = the scene folder itself: still one scene, whatever its name
    one = image_features(H5Cache(cache_dir), load_scene(data, SCENE).images["0004.jpg"],
                         FeatureConfig(name=f"custom:{good / 'strecha' / SCENE}", num_features=K))
    assert len(one.keypoints) == K
