"""The multiview task gets its tentative matches from the one function every task uses
(``pipeline.tasks.prepare.tentative_matches``): the pre-filter applies, and imported multiview matches
(``matches_multiview.h5``) are what COLMAP receives. Real data: 6 fountain-P11 images with built ground truth;
skips when ../shared/data is absent."""
from __future__ import annotations

import json
import os
import shutil

import cv2
import h5py
import numpy as np
import pytest

from tests.conftest import copy_strecha_subset

IMAGES = ["0002.jpg", "0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg", "0007.jpg"]
SCENE = "fountain-P11"


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A 6-image subset with ground truth built by `tune data build-gt` into its own cache."""
    root = copy_strecha_subset(tmp_path_factory.mktemp("data"), IMAGES)
    cache = tmp_path_factory.mktemp("cache")
    old = {k: os.environ.get(k) for k in ("IMTUNE_CACHE", "IMTUNE_GT")}
    os.environ["IMTUNE_CACHE"] = str(cache)
    os.environ.pop("IMTUNE_GT", None)
    try:
        from tuner.cli import main
        assert main(["data", "build-gt", "--data", str(root), "--num-features", "1024", "--quiet"]) == 0
        yield root, cache
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _jobs(root, conf, mv_bags=((5, 1),)):
    from pipeline.cache import H5Cache
    from pipeline.tasks.multiview import MultiviewConfig, scene_jobs
    from tuner.evaluate import load_scenes
    scene = load_scenes(root, [SCENE], split="all")[0]
    mv = MultiviewConfig(bags=mv_bags, pair_min_points=0)
    return scene, scene_jobs(scene, conf, mv, H5Cache(), str(root / "work"))


def test_prefilter_changes_what_colmap_gets(built, capsys):
    from pipeline.cache import H5Cache
    from pipeline.config import FeatureConfig, MatchConfig, PipelineConfig
    from pipeline.tasks.prepare import image_features, pair_knn, tentative_matches
    root, _ = built
    plain = PipelineConfig(FeatureConfig(num_features=1024), MatchConfig(ratio=0.9))
    gms = PipelineConfig(FeatureConfig(num_features=1024), MatchConfig(ratio=0.9, prefilter="gms"))
    scene, jobs_plain = _jobs(root, plain)
    _, jobs_gms = _jobs(root, gms)
    (a, b), m_plain = next(iter(jobs_plain[0].matches.items()))
    m_gms = jobs_gms[0].matches[(a, b)]
    assert len(m_gms) < len(m_plain)  # GMS removed some of the ratio-test matches
    # and they are exactly the stereo task's tentative matches of that pair (the one function)
    cache = H5Cache()
    fa, fb = (image_features(cache, scene.images[n], gms.feature) for n in (a, b))
    tab, _ = pair_knn(cache, fa, fb, gms.matching)
    expect, _ = tentative_matches(tab, gms.matching, fa, fb, task="multiview")
    np.testing.assert_array_equal(m_gms, expect)
    # through the CLI: the bag's tentative-match count (NM, what COLMAP was given) drops with --prefilter gms
    from tuner.cli import main
    nm = {}
    for extra in ([], ["--prefilter", "gms"]):
        capsys.readouterr()
        rc = main(["evaluate", "--data", str(root), "--task", "multiview", "--num-features", "1024", "--ratio", "0.9",
                   "--bags", "5:1", "--workers", "1", "--json", "--quiet", *extra])
        out = capsys.readouterr().out
        assert rc == 0
        nm[bool(extra)] = json.loads(out)["multiview"]["NM"]
    assert 0 < nm[True] < nm[False]


def test_imported_multiview_matches_are_what_colmap_gets(built, tmp_path):
    """A custom folder whose matches_multiview.h5 differs from its matches.h5: the multiview task uses the former."""
    from pipeline.config import FeatureConfig, MatchConfig, PipelineConfig
    root, _ = built
    byo = tmp_path / "byo"
    d = byo / SCENE
    d.mkdir(parents=True)
    sift = cv2.SIFT_create(1024)
    feats = {}
    for n in IMAGES:
        img = cv2.imread(str(root / SCENE / "images" / n), cv2.IMREAD_GRAYSCALE)
        kps, desc = sift.detectAndCompute(img, None)
        feats[n[:-4]] = (np.array([k.pt for k in kps[:1024]], np.float32), desc[:1024].astype(np.float32))
    with h5py.File(d / "keypoints.h5", "w") as fk, h5py.File(d / "descriptors.h5", "w") as fd:
        for key, (kp, desc) in feats.items():
            fk[key], fd[key] = kp, desc
    computed, imported = {}, {}
    with h5py.File(d / "matches.h5", "w") as fs, h5py.File(d / "matches_multiview.h5", "w") as fm:
        for a in feats:
            for b in feats:
                if a > b:
                    da, db = feats[a][1], feats[b][1]
                    dist = (da ** 2).sum(1)[:, None] + (db ** 2).sum(1)[None] - 2 * da @ db.T
                    nn_ab, nn_ba = dist.argmin(1), dist.argmin(0)
                    i = np.flatnonzero(nn_ba[nn_ab] == np.arange(len(da)))
                    full = np.stack([i, nn_ab[i]]).astype(np.int32)
                    fs[f"{a}-{b}"] = full
                    fm[f"{a}-{b}"] = full[:, ::3]  # a different (thinned) set for the multiview task
                    computed[(a, b)], imported[(a, b)] = full, full[:, ::3]
    conf = PipelineConfig(FeatureConfig(name=f"custom:{byo}", num_features=1024),
                          MatchConfig(ratio=1.0, custom_matches=str(byo)))
    _, jobs = _jobs(root, conf)
    assert jobs and jobs[0].matches
    for (a, b), m in jobs[0].matches.items():
        ka, kb = a[:-4], b[:-4]
        want = imported[(kb, ka)][::-1].T if (kb, ka) in imported else imported[(ka, kb)].T
        assert {tuple(x) for x in np.asarray(m).tolist()} == {tuple(x) for x in want.tolist()}
        full = computed[(kb, ka)] if (kb, ka) in computed else computed[(ka, kb)]
        assert len(m) < full.shape[1]  # not the stereo file's matches
    shutil.rmtree(byo)
