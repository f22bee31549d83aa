"""Changing r, eta or Gamma on cached data runs no feature extraction and no neighbour search."""
import dataclasses

from pipeline.cache import H5Cache
from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
from pipeline.data import load_scene
from pipeline.tasks import prepare
from pipeline.tasks.stereo import evaluate_stereo


def test_retuning_hits_the_caches(strecha, tmp_path):
    scene = load_scene(strecha, "fountain-P11")
    scene.pairs = scene.pairs[:6]
    cache = H5Cache(tmp_path / "c")
    conf = PipelineConfig(FeatureConfig("sift", 1024), MatchConfig(ratio=0.9), GeometryConfig("degensac", 1.0, max_iters=2000))
    before = dict(prepare.COUNTERS)
    r1 = evaluate_stereo([scene], conf, cache)
    n_img = len({p.i for p in scene.pairs} | {p.j for p in scene.pairs})
    assert prepare.COUNTERS["extract"] - before.get("extract", 0) == n_img
    assert prepare.COUNTERS["knn"] - before.get("knn", 0) == 6
    mid = dict(prepare.COUNTERS)
    conf2 = dataclasses.replace(conf, matching=MatchConfig(ratio=0.7, strategy="either"),
                                geometry=GeometryConfig("magsac++", 3.0, max_iters=500))
    r2 = evaluate_stereo([scene], conf2, cache)
    assert dict(prepare.COUNTERS) == mid  # nothing recomputed
    assert r2.summary["NM"] != r1.summary["NM"]  # but the new r and strategy did apply
    # a fresh process-level cache object (empty memory) still reads from disk, not recomputes
    r3 = evaluate_stereo([scene], conf, H5Cache(tmp_path / "c"))
    assert dict(prepare.COUNTERS) == mid
    assert r3.summary["NM"] == r1.summary["NM"]


def test_corrupt_cache_entry_is_recomputed(strecha, tmp_path):
    scene = load_scene(strecha, "fountain-P11")
    scene.pairs = scene.pairs[:1]
    cache = H5Cache(tmp_path / "c")
    conf = PipelineConfig(FeatureConfig("sift", 512), MatchConfig(ratio=0.9), GeometryConfig("degensac", 1.0, max_iters=1000))
    r1 = evaluate_stereo([scene], conf, cache)
    files = sorted((tmp_path / "c" / "knn").rglob("*.h5"))
    assert files
    files[0].write_bytes(files[0].read_bytes()[:200])  # truncate the entry
    before = prepare.COUNTERS["knn"]
    r2 = evaluate_stereo([scene], conf, H5Cache(tmp_path / "c"))
    assert prepare.COUNTERS["knn"] == before + 1
    assert r2.summary["NM"] == r1.summary["NM"]
