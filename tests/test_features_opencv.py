"""OpenCV feature extractors: registry, contract of Features, options, and geometric sanity.

Real-image tests use ../shared/data/strecha/fountain-P11/images/0000.jpg at the IMC working size
(long side 1024 px, INTER_AREA) and skip when the data folder is absent; synthetic tests always run.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.config import FeatureConfig
from pipeline.errors import ImtuneError, UnavailableError
from pipeline.features import EXTRACTORS, extract, get_extractor
from pipeline.features._opencv import OpenCVExtractor
from pipeline.features.sift import root_sift

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
STRECHA_IMAGE = DATA / "strecha" / "fountain-P11" / "images" / "0000.jpg"

#: registered name -> (descriptor width: floats or bytes, binary)
EXPECTED = {
    "sift": (128, False), "rootsift": (128, False), "orb": (32, True), "akaze": (61, True),
    "kaze": (64, False), "brisk": (64, True), "freak": (64, True), "beblid": (64, True),
    "teblid": (32, True), "surf": (64, False),
}
AVAILABLE = sorted(n for n, (ok, _) in EXTRACTORS.availability().items()
                   if ok and issubclass(EXTRACTORS.get(n), OpenCVExtractor))
UPRIGHT_CAPABLE = [n for n in AVAILABLE if n != "brisk"]


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    if not STRECHA_IMAGE.is_file():
        pytest.skip(f"real data not found: {STRECHA_IMAGE} (see ../shared/data/README.md)")
    img = cv2.imread(str(STRECHA_IMAGE), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f"unreadable: {STRECHA_IMAGE}"
    h, w = img.shape
    s = 1024 / max(h, w)
    return cv2.resize(img, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)


_CACHE: dict = {}


def feats(image: np.ndarray, **kw):
    """Features of the Strecha image for FeatureConfig(**kw), computed once per test session."""
    conf = FeatureConfig(**kw)
    if conf not in _CACHE:
        _CACHE[conf] = extract(conf, image)
    return _CACHE[conf]


def synthetic(h: int = 384, w: int = 512, seed: int = 0) -> np.ndarray:
    """Blurred random discs and polygons on grey: corners and blobs at many scales."""
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 110, np.uint8)
    for _ in range(180):
        c = int(rng.integers(0, 256))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), int(rng.integers(3, 30)), c, -1)
        else:
            pts = (np.array([x, y]) + rng.integers(-35, 35, size=(int(rng.integers(3, 6)), 2))).astype(np.int32)
            cv2.fillPoly(img, [pts], c)
    return cv2.GaussianBlur(img, (0, 0), 1.2)


# -- registry -------------------------------------------------------------------------------------

def test_every_family_is_registered():
    assert set(EXPECTED) <= set(EXTRACTORS.names())
    for name in EXPECTED:
        assert EXTRACTORS.description(name), name
        assert "opencv" in EXTRACTORS.get(name).version


def test_everything_but_surf_is_available_in_the_contrib_wheel():
    assert set(AVAILABLE) >= set(EXPECTED) - {"surf"}


def test_unknown_name_is_an_imtune_error_naming_it():
    with pytest.raises(ImtuneError, match="nosuchfeature"):
        get_extractor(FeatureConfig(name="nosuchfeature"))


def test_surf_is_unavailable_with_a_clear_reason():
    ok, reason = EXTRACTORS.availability()["surf"]
    if ok:
        pytest.skip("this OpenCV was built with OPENCV_ENABLE_NONFREE: surf works here")
    assert "non-free" in reason and "OPENCV_ENABLE_NONFREE" in reason and "opencv-contrib-python-headless" in reason
    with pytest.raises(UnavailableError) as e:
        get_extractor(FeatureConfig(name="surf"))
    assert str(e.value) == reason and "\n" not in reason


@pytest.mark.parametrize("kw, match", [
    (dict(name="sift", options=(("no_such_option", 1),)), "no_such_option"),
    (dict(name="sift", options=(("contrast_threshold", "abc"),)), "contrast_threshold"),
    (dict(name="orb", mr_size=6.0), "mr_size"),
    (dict(name="sift", mr_size=-1.0), "mr_size"),
    (dict(name="brisk", upright=True), "upright"),
    (dict(name="beblid", options=(("detector", "surf"),)), "detector"),
    (dict(name="teblid", options=(("n_bits", 128),)), "n_bits"),
    (dict(name="orb", options=(("n_levels", 0),)), "n_levels"),          # would crash OpenCV
    (dict(name="akaze", options=(("diffusivity", 7),)), "diffusivity"),
    (dict(name="sift", options=(("clahe_tiles", 0),), clahe="both"), "clahe_tiles"),
])
def test_bad_options_are_imtune_errors(kw, match):
    with pytest.raises(ImtuneError, match=match):
        get_extractor(FeatureConfig(**kw))


@pytest.mark.parametrize("bad", [np.zeros((32, 32), np.float32), np.zeros((32, 32, 3), np.uint8),
                                 np.zeros((0, 32), np.uint8), [[0, 1], [1, 0]]])
def test_bad_images_are_imtune_errors(bad):
    with pytest.raises(ImtuneError):
        extract(FeatureConfig(name="orb", num_features=100), bad)


def test_name_and_dict_shortcuts():
    img = synthetic()
    a = extract("orb", img)
    b = extract({"name": "orb"}, img)
    assert len(a) > 0 and np.array_equal(a.descriptors, b.descriptors)


# -- every available extractor on a real image ------------------------------------------------------

@pytest.mark.parametrize("name", AVAILABLE)
def test_extract_real_image_contract(image, name):
    budget = 2048
    f = feats(image, name=name, num_features=budget)
    n = len(f)
    dim, binary = EXPECTED.get(name, (f.descriptors.shape[1], f.binary))
    # low_threshold (the default) reaches the budget on this textured image, and never exceeds it
    assert n == budget, f"{name}: {n} keypoints"
    assert f.keypoints.dtype == np.float32 and f.keypoints.shape == (n, 2)
    h, w = image.shape
    assert np.all((f.keypoints >= -0.5) & (f.keypoints <= [w - 0.5, h - 0.5]))
    assert f.binary is binary
    assert f.descriptors.shape == (n, dim)
    assert f.descriptors.dtype == (np.uint8 if binary else np.float32)
    for arr in (f.scales, f.orientations, f.scores):
        assert arr.shape == (n,) and arr.dtype == np.float32 and np.all(np.isfinite(arr))
    assert np.all(f.scales > 0)
    assert np.all((f.orientations >= 0) & (f.orientations < 360)) and np.ptp(f.orientations) > 90
    assert np.all(np.diff(f.scores) <= 0), "keypoints must come strongest first"
    assert len(np.unique(f.descriptors, axis=0)) > 0.9 * n, "descriptors look degenerate"


@pytest.mark.parametrize("name", AVAILABLE)
def test_blank_or_tiny_image_gives_empty_features(name):
    budget = 512
    noise = np.random.default_rng(0).integers(0, 256, size=(3, 1000), dtype=np.uint8)
    for img in (np.zeros((480, 640), np.uint8), np.full((200, 300, 1), 128, np.uint8),
                noise, noise[:1, :1]):   # too small for any feature (ORB/BRISK pyramids fail on it)
        f = extract(FeatureConfig(name=name, num_features=budget), img)
        dim, binary = EXPECTED[name]
        assert len(f) == 0
        assert f.keypoints.shape == (0, 2) and f.keypoints.dtype == np.float32
        assert f.descriptors.shape == (0, dim)
        assert f.descriptors.dtype == (np.uint8 if binary else np.float32)
        assert f.scales.shape == f.orientations.shape == f.scores.shape == (0,)


def test_low_threshold_is_what_reaches_the_8k_budget(image):
    low = feats(image, name="sift", num_features=8000)
    default = feats(image, name="sift", num_features=8000, low_threshold=False)
    assert len(low) == 8000
    assert len(default) < 0.6 * 8000
    # both keep the strongest: the default-threshold set is (mostly) inside the low-threshold set
    a = {tuple(p) for p in np.round(low.keypoints, 2)}
    assert np.mean([tuple(p) in a for p in np.round(default.keypoints, 2)]) > 0.9


def test_extraction_is_deterministic(image):
    conf = FeatureConfig(name="sift", num_features=2048)
    a = feats(image, name="sift", num_features=2048)
    b = extract(conf, image)
    for x, y in ((a.keypoints, b.keypoints), (a.descriptors, b.descriptors), (a.scores, b.scores)):
        assert np.array_equal(x, y)


def test_rootsift_is_l1_sqrt_of_sift(image):
    s = feats(image, name="sift", num_features=2048)
    r = feats(image, name="rootsift", num_features=2048)
    assert r.descriptors.dtype == np.float32 and np.all(r.descriptors >= 0)
    np.testing.assert_allclose(np.linalg.norm(r.descriptors, axis=1), 1.0, atol=1e-4)
    assert np.array_equal(s.keypoints, r.keypoints)
    expect = np.sqrt(s.descriptors / s.descriptors.sum(axis=1, keepdims=True))
    np.testing.assert_allclose(r.descriptors, expect, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(root_sift(np.ones((2, 8), np.float32)), axis=1), 1.0, rtol=1e-6)


# -- upright / upright++ ----------------------------------------------------------------------------

def _no_duplicates(f) -> bool:
    key = np.column_stack([f.keypoints, f.scales])
    return len(np.unique(key, axis=0)) == len(f)


def test_sift_upright_drops_orientation_duplicates_and_upright_plus_refills(image):
    k = 2048
    oriented = feats(image, name="sift", num_features=k)
    up = feats(image, name="sift", num_features=k, upright=True)
    plus = feats(image, name="sift", num_features=k, upright_plus=True)
    # SIFT assigns several orientations at one location: the oriented set has repeated locations
    assert len(np.unique(oriented.keypoints, axis=0)) < k
    for f in (up, plus):
        assert np.all(f.orientations == 0)
        assert len(np.unique(f.keypoints, axis=0)) == len(f), "duplicate locations"
    assert len(up) == len(np.unique(oriented.keypoints, axis=0)) < k   # upright: top-k, then de-duplicate
    assert len(plus) == k >= len(up)                                   # upright++: refilled
    # upright's keypoints are the oriented top-k's locations
    assert {tuple(p) for p in up.keypoints} == {tuple(p) for p in oriented.keypoints}


@pytest.mark.parametrize("name", [n for n in UPRIGHT_CAPABLE if n not in ("sift", "kaze")])
def test_upright_every_extractor(image, name):
    up = feats(image, name=name, num_features=1024, upright=True)
    plus = feats(image, name=name, num_features=1024, upright_plus=True)
    for f in (up, plus):
        assert len(f) > 0 and np.all(f.orientations == 0) and _no_duplicates(f)
    assert len(up) <= len(plus) <= 1024


def test_kaze_upright_on_a_small_image():  # KAZE is ~1 s per 1024 px image; a small one suffices here
    img = synthetic()
    up = extract(FeatureConfig(name="kaze", num_features=300, upright=True), img)
    orient = extract(FeatureConfig(name="kaze", num_features=300), img)
    assert len(up) > 0 and np.all(up.orientations == 0) and _no_duplicates(up)
    assert np.ptp(orient.orientations) > 90
    assert np.array_equal(up.keypoints, orient.keypoints) and not np.array_equal(up.descriptors, orient.descriptors)


# -- options: CLAHE, mr_size, BEBLID on SIFT keypoints ------------------------------------------------

def test_clahe_reaches_detector_and_descriptor_separately(image):
    base = feats(image, name="orb", num_features=1024)
    det = feats(image, name="orb", num_features=1024, clahe="detector")
    desc = feats(image, name="orb", num_features=1024, clahe="descriptor")
    both = feats(image, name="orb", num_features=1024, clahe="both")
    assert not np.array_equal(det.keypoints, base.keypoints)
    assert np.array_equal(desc.keypoints, base.keypoints) and not np.array_equal(desc.descriptors, base.descriptors)
    assert np.array_equal(both.keypoints, det.keypoints) and not np.array_equal(both.descriptors, det.descriptors)


def test_sift_mr_size_scales_the_descriptor_support(image):
    base = feats(image, name="sift", num_features=1024)
    same = feats(image, name="sift", num_features=1024, mr_size=3.0)        # OpenCV's own factor
    wide = feats(image, name="sift", num_features=1024, mr_size=6.0)
    assert np.array_equal(same.descriptors, base.descriptors)
    assert np.array_equal(wide.keypoints, base.keypoints) and np.array_equal(wide.scales, base.scales)
    changed = np.mean(np.any(wide.descriptors != base.descriptors, axis=1))
    assert changed > 0.95


def test_beblid_on_sift_keypoints(image):
    f = feats(image, name="beblid", num_features=1024, options=(("detector", "sift"),))
    s = feats(image, name="sift", num_features=1024)
    assert f.binary and f.descriptors.shape == (1024, 64)
    assert np.array_equal(f.keypoints, s.keypoints)


def test_freak_descriptor_rows_belong_to_their_keypoints(image):
    """FREAK drops keypoints near the border; check the survivors' rows were not shifted."""
    f = feats(image, name="freak", num_features=2048)
    freak = cv2.xfeatures2d.FREAK_create()
    rows = np.linspace(0, len(f) - 1, 25).astype(int)
    kps = [cv2.KeyPoint(float(f.keypoints[i, 0]), float(f.keypoints[i, 1]), float(f.scales[i])) for i in rows]
    kout, d = freak.compute(image, kps)
    assert len(kout) == len(rows)
    assert np.array_equal(d, f.descriptors[rows])


def test_orb_descriptor_rows_belong_to_their_keypoints(image):
    """ORB's compute() returns the keypoints it was given grouped by pyramid level, not in the order given; the
    extractor hands them over strongest first (levels mixed) and took a same-length answer as the same order:
    rows of descriptors belonged to other keypoints, and ORB solved no Strecha pair (mAA(10) 0.000 on
    fountain-P11, 41 of 796 cross-checked matches inliers on 0000/0001 against OpenCV ORB's 528). Each row is
    now OpenCV's own descriptor of its keypoint (the same detector: nfeatures 2048, fastThreshold 0)."""
    f = feats(image, name="orb", num_features=2048)
    kps, d = cv2.ORB_create(2048, fastThreshold=0).detectAndCompute(image, None)
    from pipeline.features.orb import orb_pixel_centre  # positions reported in the pixel-centre convention
    pts = orb_pixel_centre(np.array([k.pt for k in kps]), np.array([k.octave for k in kps]), image.shape, 1.2)
    ref = {}  # keyed by position (x, y): a few keypoints share one, on several pyramid levels
    for (x, y), row in zip(pts.astype(float), d):
        ref.setdefault((round(x, 2), round(y, 2)), []).append(row)
    same = [any(np.array_equal(r, f.descriptors[i]) for r in ref[key])
            for i, key in enumerate(zip(np.round(f.keypoints[:, 0].astype(float), 2),
                                        np.round(f.keypoints[:, 1].astype(float), 2))) if key in ref]
    assert len(same) > 0.9 * len(f) and all(same), (len(same), sum(same))
    assert np.all(np.diff(f.scores) <= 0)  # still strongest first


# -- geometry: 90-degree rotation ---------------------------------------------------------------------

def _repeatability(a: np.ndarray, b: np.ndarray, tol: float = 1.5) -> float:
    """Fraction of points of ``a`` with a point of ``b`` within ``tol`` px."""
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    return float(np.mean(d.min(axis=1) <= tol))


def _correct_mutual_nn(fa, fb, a_in_b: np.ndarray, tol: float = 2.0) -> float:
    d = np.linalg.norm(fa.descriptors[:, None, :] - fb.descriptors[None, :, :], axis=2)
    ab, ba = d.argmin(1), d.argmin(0)
    mutual = ba[ab] == np.arange(len(ab))
    err = np.linalg.norm(a_in_b[mutual] - fb.keypoints[ab[mutual]], axis=1)
    return float(np.mean(err <= tol))


def test_sift_keypoints_survive_a_90_degree_rotation():
    img = synthetic()
    h, w = img.shape
    rot = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)           # (x, y) -> (h - 1 - y, x)
    conf = FeatureConfig(name="sift", num_features=1000)
    fa, fb = extract(conf, img), extract(conf, rot)
    assert len(fa) > 300 and len(fb) > 300
    a_in_b = np.column_stack([h - 1 - fa.keypoints[:, 1], fa.keypoints[:, 0]])
    rep = _repeatability(a_in_b, fb.keypoints)
    rng = np.random.default_rng(0)
    chance = _repeatability(rng.uniform([0, 0], [h, w], size=(len(fa), 2)), fb.keypoints)
    wrong = _repeatability(np.column_stack([fa.keypoints[:, 1], w - 1 - fa.keypoints[:, 0]]), fb.keypoints)
    assert rep > 0.8, rep
    assert chance < 0.1 and wrong < 0.1 and rep > 5 * max(chance, wrong)
    # rotation-invariant descriptors: mutual nearest neighbours land on the right point
    assert _correct_mutual_nn(fa, fb, a_in_b) > 0.9
    # ... while upright descriptors (orientation fixed to 0) do not survive 90 degrees
    up = FeatureConfig(name="sift", num_features=1000, upright=True)
    ua, ub = extract(up, img), extract(up, rot)
    ua_in_b = np.column_stack([h - 1 - ua.keypoints[:, 1], ua.keypoints[:, 0]])
    assert _correct_mutual_nn(ua, ub, ua_in_b) < 0.2


# -- geometry: the pixel-centre convention --------------------------------------------------------------

def _centre_bias(name: str, img: np.ndarray, **kw) -> np.ndarray:
    """Median keypoint offset (px, x and y) from the pixel-centre convention, measured on a 180-degree rotation
    (exact: (x, y) -> (w - 1 - x, h - 1 - y)). A keypoint reported at true + b lands at w - 1 - x + b in the
    rotated image and w - 1 - x - b is predicted from the original: the residual of a repeated point is 2 b."""
    h, w = img.shape
    conf = FeatureConfig(name=name, num_features=1000, **kw)
    fa, fb = extract(conf, img), extract(conf, cv2.rotate(img, cv2.ROTATE_180))
    pred = np.column_stack([w - 1 - fa.keypoints[:, 0], h - 1 - fa.keypoints[:, 1]]).astype(np.float64)
    d = np.linalg.norm(pred[:, None, :] - fb.keypoints[None, :, :], axis=2)
    j = d.argmin(1)
    near = d[np.arange(len(j)), j] < 1.0
    assert near.sum() > 200, near.sum()
    return np.median(fb.keypoints[j[near]] - pred[near], axis=0) / 2


@pytest.mark.parametrize("name", ["sift", "rootsift"])
def test_sift_keypoints_follow_the_pixel_centre_convention(image, name):
    """OpenCV's SIFT detects on the image doubled (pixel-centre resize: x -> 2 x + 0.5) and halves the positions
    without undoing the half pixel: every keypoint came out 0.25 px right of and below the point it describes
    (measured on the Strecha image under a 180-degree rotation: a median bias of (+0.250, +0.250) px at every
    scale), against the documented convention (centre of the top-left pixel = (0, 0)). Now within 0.02 px."""
    b = _centre_bias(name, image[::2, ::2].copy())
    assert np.all(np.abs(b) < 0.05), b


@pytest.mark.parametrize("name", ["orb", "beblid"])
def test_orb_keypoints_follow_the_pixel_centre_convention_on_every_level(image, name):
    """ORB detects FAST corners at integer pixels u of pyramid level l (the image resized to round(W / s), s =
    1.2^l, by a pixel-centre resize) and reports u * s, where the pixel-centre position is
    (u + 0.5) * W / round(W / s) - 0.5: a bias of about -(s - 1) / 2 px plus the level's rounding, up to -1.3 px at
    level 7, that differs between two images. Measured on the Strecha image (640 px) under a 180-degree rotation:
    levels 3, 5, 6, 7 had no keypoint repeated within 1 + 0.3 s px at all, level 2 a bias of (-0.54, +0.12) px.
    Now every level repeats, with a bias below 0.05 px. beblid (ORB keypoints) likewise."""
    img = cv2.resize(image, (640, round(640 * image.shape[0] / image.shape[1])), interpolation=cv2.INTER_AREA)
    h, w = img.shape
    conf = FeatureConfig(name=name, num_features=3000)
    fa, fb = extract(conf, img), extract(conf, cv2.rotate(img, cv2.ROTATE_180))

    def level(f):  # ORB size = 31 * 1.2^l
        return np.round(np.log(f.scales / 31.0) / np.log(1.2)).astype(int)

    la, lb = level(fa), level(fb)
    pred = np.column_stack([w - 1 - fa.keypoints[:, 0], h - 1 - fa.keypoints[:, 1]]).astype(np.float64)
    for lv in range(8):
        a, b = pred[la == lv], fb.keypoints[lb == lv]
        assert len(a) > 50 and len(b) > 50, (lv, len(a), len(b))
        d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
        j = d.argmin(1)
        near = d[np.arange(len(j)), j] < 1.0 + 0.3 * 1.2 ** lv
        assert near.sum() > 0.2 * len(a), (lv, near.sum(), len(a))
        bias = np.mean(b[j[near]] - a[near], axis=0) / 2
        assert np.all(np.abs(bias) < 0.05), (lv, bias)
