"""Issue 44: the COLMAP reference's options are pycolmap's own defaults; MapperConfig's defaults are pycolmap's; a
change of mapper options alone reuses the verified pairs (a counter); per-dataset pruning by a real Optuna pruner;
`--reference colmap` on a task without one is a one-line error. Real data: two small datasets cut from
../shared/data/imc2023_heritage, 512 features."""
from __future__ import annotations

import csv
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import DATA, require

HERITAGE = DATA / "imc2023_heritage"
DS = "imc2023_heritage"


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def test_reference_mapper_options_are_pycolmaps_defaults():
    pycolmap = pytest.importorskip("pycolmap")
    from pipeline.tasks.reconstruction import REFERENCE_SET, reference_mapper_options
    ours = _flat(reference_mapper_options(threads=2, seed=7).todict())
    theirs = _flat(pycolmap.IncrementalPipelineOptions().todict())
    assert set(ours) == set(theirs)
    differ = {k for k in ours if str(ours[k]) != str(theirs[k])}
    assert differ <= set(REFERENCE_SET), differ - set(REFERENCE_SET)
    assert ours["min_model_size"] == 3 and ours["max_num_models"] == 25  # the IMC 2025 baseline's
    assert ours["num_threads"] == 2 and ours["random_seed"] == 7 and ours["mapper.random_seed"] == 7


def test_reference_stage_options_are_pycolmaps_defaults():
    pycolmap = pytest.importorskip("pycolmap")
    from pipeline.tasks.reconstruction import REFERENCE_STAGE_SET, reference_stage_options
    built = reference_stage_options(num_features=1536, threads=2)
    fresh = (pycolmap.FeatureExtractionOptions(), pycolmap.FeatureMatchingOptions(), pycolmap.TwoViewGeometryOptions())
    for ours, theirs, allowed in zip(built, fresh, REFERENCE_STAGE_SET):
        a, b = _flat(ours.todict()), _flat(theirs.todict())
        differ = {k for k in a if str(a[k]) != str(b[k])}
        assert differ <= set(allowed), differ
    assert built[0].sift.max_num_features == 1536


def test_mapper_config_defaults_are_pycolmaps():
    """MapperConfig's defaults are pycolmap's, read from its option objects, except the documented deviations."""
    pycolmap = pytest.importorskip("pycolmap")
    from pipeline.config import MAPPER_DEVIATIONS, MapperConfig
    inc, glo = pycolmap.IncrementalPipelineOptions(), pycolmap.GlobalPipelineOptions()
    m = MapperConfig()
    theirs = {"min_inliers": inc.min_num_matches, "min_model_size": inc.min_model_size,
              "max_num_models": inc.max_num_models, "init_min_num_inliers": inc.mapper.init_min_num_inliers,
              "abs_pose_min_num_inliers": inc.mapper.abs_pose_min_num_inliers,
              "abs_pose_max_error": inc.mapper.abs_pose_max_error,
              "filter_max_reproj_error": inc.mapper.filter_max_reproj_error,
              "global_max_rotation_error": glo.mapper.rotation_averaging.max_rotation_error_deg,
              "global_max_angular_error": glo.mapper.max_angular_reproj_error_deg}
    assert set(theirs) == {f.name for f in dataclasses.fields(MapperConfig)}
    for name, value in theirs.items():
        if name in MAPPER_DEVIATIONS:
            assert getattr(m, name) != value, name  # a deviation that is none would be a stale claim
        else:
            assert getattr(m, name) == value, name
    assert m.min_model_size == 3 and m.max_num_models == 25  # the IMC 2025 baseline's


@pytest.mark.parametrize("field, value", [("abs_pose_max_error", 0), ("init_min_num_inliers", 0),
                                          ("max_num_models", 1.5), ("filter_max_reproj_error", "x")])
def test_bad_mapper_option_is_one_line(field, value):
    from pipeline.config import MapperConfig
    from pipeline.errors import ImtuneError
    with pytest.raises(ImtuneError, match=field) as e:
        MapperConfig(**{field: value})
    assert "\n" not in str(e.value)


def test_bad_reconstruction_options_are_one_line():
    from pipeline.errors import ImtuneError
    from pipeline.tasks.reconstruction import ReconstructionConfig, ReconstructionTask
    for kw, what in (({"verifier": "magsac"}, "verifier"), ({"two_view": "E"}, "two_view"),
                     ({"pipeline": "hloc"}, "pipeline")):
        with pytest.raises(ImtuneError, match=what):
            ReconstructionConfig(**kw)
    with pytest.raises(ImtuneError, match="unknown reconstruction option"):
        ReconstructionTask({"mappr": "global"})


# ------------------------------------------------------------------------------------------- real data

def _cut(dst: Path, parts: dict[str, tuple[int, int]]) -> Path:
    """IMC datasets named by ``parts`` (name -> (first, last) index of the dioscuri images), plus one outlier each."""
    require(HERITAGE)
    with open(HERITAGE / "train_labels.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    th = list(csv.DictReader(open(HERITAGE / "train_thresholds.csv", newline="")))
    scene = [r for r in rows if r["scene"] != "outliers"]
    outl = [r for r in rows if r["scene"] == "outliers"]
    keep, ths = [], []
    for k, (name, (a, b)) in enumerate(parts.items()):
        (dst / "train" / name).mkdir(parents=True)
        for r in scene[a:b] + outl[k:k + 1]:
            keep.append({**r, "dataset": name})
            os.symlink((HERITAGE / "train" / DS / r["image"]).resolve(), dst / "train" / name / r["image"])
        ths.extend({**t, "dataset": name} for t in th)
    for path, items in ((dst / "train_labels.csv", keep), (dst / "train_thresholds.csv", ths)):
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(items[0]))
            w.writeheader()
            w.writerows(items)
    return dst


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    return _cut(tmp_path_factory.mktemp("recon44") / "data", {"hA": (0, 5), "hB": (5, 10)})


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    from pipeline.cache import H5Cache
    return H5Cache(tmp_path_factory.mktemp("recon44-cache"))


def _conf(**mapper):
    from pipeline.config import FeatureConfig, GeometryConfig, MapperConfig, MatchConfig, PipelineConfig
    return PipelineConfig(feature=FeatureConfig(name="sift", num_features=512), matching=MatchConfig(ratio=0.9),
                          geometry=GeometryConfig(threshold=1.0, max_iters=2000), mapper=MapperConfig(**mapper))


def test_mapper_only_change_reuses_the_verified_pairs(two, cache):
    from pipeline.data import load_scene
    from pipeline.tasks.reconstruction import COUNTERS, ReconstructionTask
    sc = load_scene(two, "hA")
    task = ReconstructionTask(workers=1)
    n0 = COUNTERS["verify"]
    a = task.evaluate([sc], _conf(), cache)
    assert COUNTERS["verify"] == n0 + 1
    b = task.evaluate([sc], _conf(init_min_num_inliers=40, abs_pose_min_num_inliers=12, max_num_models=5), cache)
    assert COUNTERS["verify"] == n0 + 1  # mapper options only: the verified pairs of the first evaluation
    assert b.scenes["hA"]["pairs"] == a.scenes["hA"]["pairs"]
    c = dataclasses.replace(_conf(), geometry=dataclasses.replace(_conf().geometry, threshold=2.0))
    task.evaluate([sc], c, cache)
    assert COUNTERS["verify"] == n0 + 2  # eta changed: verified again
    task.evaluate([sc], _conf(min_inliers=40), cache)
    assert COUNTERS["verify"] == n0 + 3  # min_inliers decides which pairs are verified at all


def test_pruned_after_the_first_dataset(two, cache, tmp_path, monkeypatch):
    """A real Optuna pruner (ThresholdPruner, lower 1.5: every score is below it) stops the trial after the first of
    its two validation datasets: one intermediate value, the second dataset never verified."""
    import optuna
    from optuna.trial import TrialState

    from pipeline.config import FeatureConfig, PipelineConfig
    from pipeline.tasks.reconstruction import COUNTERS
    from tuner.study import TuneSettings, setup_study
    monkeypatch.setenv("IMTUNE_CACHE", str(cache.root))
    s = TuneSettings(base=PipelineConfig(feature=FeatureConfig(name="sift", num_features=512)), data_root=two,
                     task="reconstruction", storage=f"sqlite:///{tmp_path}/o.db", studies_dir=tmp_path,
                     val_scenes=["hA", "hB"], fixes=["max_iters=2000", "ratio=0.9", "threshold=1.0",
                                                    "min_model_size=3"],
                     n_trials=1, sampler="random", seed=0, progress=False, test=False, workers=1)
    ctx = setup_study(s)
    study = optuna.create_study(direction="maximize", pruner=optuna.pruners.ThresholdPruner(lower=1.5))
    n0 = COUNTERS["verify"]
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    study.optimize(ctx.objective, n_trials=1)
    t = study.trials[0]
    assert t.state == TrialState.PRUNED
    assert sorted(t.intermediate_values) == [0]
    assert COUNTERS["verify"] == n0 + 1  # hB was never verified
    # no pruner: both datasets, two intermediate values
    study2 = optuna.create_study(direction="maximize", pruner=optuna.pruners.NopPruner())
    study2.optimize(ctx.objective, n_trials=1)
    assert study2.trials[0].state == TrialState.COMPLETE and sorted(study2.trials[0].intermediate_values) == [0, 1]


def test_reference_colmap_on_the_stereo_task_is_one_line():
    from pipeline.errors import ImtuneError
    from pipeline.tasks import TASKS
    from tuner.select import reference_config
    frozen = {"task": "stereo", "config": _conf().to_dict()}
    with pytest.raises(ImtuneError, match="--reference colmap: COLMAP's own pipeline is the reconstruction task's"):
        reference_config(frozen, "colmap", TASKS.get("stereo")())
    rc = reference_config({"task": "reconstruction", "config": _conf().to_dict()}, None,
                          TASKS.get("reconstruction")())
    assert rc is not None and rc[1].startswith("COLMAP out of the box")


def test_compare_runs_per_dataset_and_overall():
    from pipeline.tasks.reconstruction import ReconstructionTask
    ref = [{"scenes": {"a": {"score": 0.5}, "b": {"score": 0.2}}}, {"scenes": {"a": {"score": 0.4}, "b": {"score": 0.2}}}]
    new = [{"scenes": {"a": {"score": 0.6}, "b": {"score": 0.1}}}, {"scenes": {"a": {"score": 0.6}, "b": {"score": 0.3}}}]
    c = ReconstructionTask.compare_runs(ref, new)
    # differences: a 0.1, 0.2; b -0.1, 0.1 -> mean 0.075; sd of [0.1, 0.2, -0.1, 0.1] = 0.12583; t(0.975, 3) = 3.1824
    assert c["difference"] == pytest.approx(0.075)
    assert c["datasets"] == pytest.approx({"a": 0.15, "b": 0.0})
    half = 3.182446305284263 * 0.12583057392117916 / 2
    assert c["ci"] == pytest.approx([0.075 - half, 0.075 + half])
    assert c["pairs"] == 4


def test_evaluate_defaults_to_colmap_sift_and_bad_choice_exits_2(two, tmp_path):
    r = subprocess.run([sys.executable, "-m", "tuner", "evaluate", "--task", "reconstruction", "--data", str(two),
                        "--scenes", "hA", "--num-features", "512", "--max-iters", "2000", "--cache",
                        str(tmp_path / "c"), "--workers", "1", "--json"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    import json
    out = json.loads(r.stdout)
    assert out["config"]["feature"]["name"] == "colmap-sift" and out["config"]["geometry"]["threshold"] == 1.0
    r = subprocess.run([sys.executable, "-m", "tuner", "evaluate", "--task", "reconstruction", "--data", str(two),
                        "--verifier", "magsac"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "--verifier" in r.stderr


def test_to_imc_sparse_subset_and_outlier_cap(tmp_path):
    """`tune data to-imc --every 3 --max-outliers 2`: every third image of each scene (name order), two outliers spread
    over the outlier scene; bad values are one line, exit 2."""
    require(DATA / "strecha")
    from pipeline.data import load_scene
    out = tmp_path / "imc"
    r = subprocess.run([sys.executable, "-m", "tuner", "data", "to-imc", "--data", str(DATA / "strecha"), "--scenes",
                        "fountain-P11", "--outliers", "entry-P10", "--every", "3", "--max-outliers", "2", "--out",
                        str(out), "--dataset", "sparse", "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    sc = load_scene(out, "sparse")
    fountain = sorted(load_scene(DATA / "strecha", "fountain-P11", verify=False).images)
    entry = sorted(load_scene(DATA / "strecha", "entry-P10", verify=False).images)
    scene = sorted(n for n, g in sc.groups.items() if g != "outliers")
    assert scene == [f"fountain-P11_{n}" for n in fountain[::3]]  # 0000, 0003, 0006, 0009 of 11
    assert sorted(n for n, g in sc.groups.items() if g == "outliers") == [f"entry-P10_{entry[0]}",
                                                                           f"entry-P10_{entry[-1]}"]
    for bad, what in ((["--every", "0"], "--every"), (["--max-outliers", "-1"], "--max-outliers")):
        r = subprocess.run([sys.executable, "-m", "tuner", "data", "to-imc", "--data", str(DATA / "strecha"),
                            "--scenes", "fountain-P11", "--out", str(tmp_path / "x"), "--dataset", "d", *bad],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
        assert what in r.stderr
