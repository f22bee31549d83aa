"""Issue 45, item 4: the IMC 2025 baseline as a named reference pipeline of the reconstruction task
(`--reference imc2025-baseline`, `tune evaluate --recon-pipeline imc2025-baseline`). Its settings are read from the
libraries they come from (pycolmap's option objects, kornia's LightGlue defaults), never typed here; bad input is one
line with exit 2. No network runs here (a few CPU-seconds in all): the pipeline's run on the real datasets is
recorded in benchmarks/results/imc2025-baseline.md."""
from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import DATA
from tests.test_reconstruction_reference import _conf, _flat


def test_baseline_verification_is_pycolmaps_default():
    """The notebook verifies with `pycolmap.match_exhaustive` at its defaults: every option as constructed."""
    pycolmap = pytest.importorskip("pycolmap")
    from pipeline.tasks.reconstruction import baseline_verification_options
    ours, theirs = _flat(baseline_verification_options().todict()), _flat(pycolmap.TwoViewGeometryOptions().todict())
    assert set(ours) == set(theirs)
    assert {k for k in ours if str(ours[k]) != str(theirs[k])} == set()


def test_baseline_mapper_is_the_colmap_references():
    """The baseline's mapper is pycolmap's incremental mapper with min_model_size 3 and max_num_models 25 (those
    two read back from the options object that runs, every other option checked against pycolmap's defaults by
    test_reconstruction_reference.py)."""
    pytest.importorskip("pycolmap")
    from pipeline.tasks.reconstruction import REFERENCE_MIN_MODEL_SIZE, reference_mapper_options
    o = reference_mapper_options(threads=1, seed=0)
    assert (o.min_model_size, o.max_num_models) == (3, 25) and REFERENCE_MIN_MODEL_SIZE == 3


def test_baseline_config_is_aliked_and_lightglue_at_its_defaults():
    kornia_feature = pytest.importorskip("kornia.feature")
    from pipeline.tasks.reconstruction import BASELINE_MIN_CONFIDENCE, baseline_config
    # LightGlue's own filter threshold, as the notebook's KF.LightGlueMatcher leaves it
    assert BASELINE_MIN_CONFIDENCE == kornia_feature.LightGlue.default_conf["filter_threshold"]
    conf = _conf()  # sift, 512 features, r 0.9: the baseline replaces the feature and the matcher, keeps the count
    b = baseline_config(conf)
    assert (b.feature.name, b.feature.num_features, b.feature.max_side) == ("aliked", 512, conf.feature.max_side)
    assert dict(b.feature.options) == {"detection_threshold": 0.01}
    assert b.matching.method == "lightglue" and b.matching.min_confidence == BASELINE_MIN_CONFIDENCE
    assert dict(b.matching.matcher_options) == {"depth_confidence": -1.0, "width_confidence": -1.0}
    assert b.mapper == conf.mapper and b.geometry == conf.geometry
    assert baseline_config(b) == b  # idempotent: a frozen reference config runs as recorded


def test_reference_imc2025_baseline_is_the_reconstruction_tasks_named_reference():
    from pipeline.errors import ImtuneError
    from pipeline.tasks import TASKS
    from tuner.select import reference_config, reference_task_of
    recon = TASKS.get("reconstruction")()
    frozen = {"task": "reconstruction", "config": _conf().to_dict()}
    conf, label = reference_config(frozen, "imc2025-baseline", recon)
    assert conf.feature.name == "aliked" and conf.matching.method == "lightglue" and conf.feature.num_features == 512
    assert label.startswith("IMC 2025 baseline (ALIKED at 512 keypoints + LightGlue")
    rt = reference_task_of("imc2025-baseline", recon)
    assert rt.rc.pipeline == "imc2025-baseline" and rt.rc.mapper == "incremental" and recon.rc.pipeline == "imtune"
    assert reference_task_of("colmap", recon).rc.pipeline == "colmap"  # the existing reference is unchanged
    with pytest.raises(ImtuneError) as e:
        reference_config({"task": "stereo", "config": _conf().to_dict()}, "IMC2025-Baseline", TASKS.get("stereo")())
    assert "--reference imc2025-baseline: the IMC 2025 baseline is the reconstruction task's reference" in str(e.value)
    assert "\n" not in str(e.value)


def test_misspelt_reference_names_the_choices(tmp_path):
    from pipeline.errors import ImtuneError
    from tuner.commands.study import resolve_reference
    assert resolve_reference("imc2025-baseline", tmp_path) == "imc2025-baseline"
    with pytest.raises(ImtuneError) as e:
        resolve_reference("imc2025-basline", tmp_path)
    msg = str(e.value)
    assert "\n" not in msg and "'imc2025-basline'" in msg and "imc2025-baseline" in msg.split("or give")[1]


def test_cli_bad_recon_pipeline_is_one_line_exit_2():
    data = DATA / "imc2023_heritage"
    r = subprocess.run([sys.executable, "-m", "tuner", "evaluate", "--task", "reconstruction", "--data", str(data),
                        "--recon-pipeline", "imc2025"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "--recon-pipeline" in r.stderr, r.stderr


def test_baseline_runs_lightglue_and_colmap_on_real_images(tmp_path):
    """Two dioscuri views and an outlier, 128 ALIKED keypoints at 320 px (a few CPU-seconds): LightGlue runs
    once per pair (a counter), with the baseline's options whatever the configuration said; the pairs below the
    notebook's 15 matches are not imported; the submission names every image once. Whole datasets:
    benchmarks/results/imc2025-baseline.md."""
    import csv
    import dataclasses

    from pipeline.cache import H5Cache
    from pipeline.data import load_scene
    from pipeline.tasks import prepare
    from pipeline.tasks.reconstruction import ReconstructionTask
    from tests.test_reconstruction_reference import _cut
    data = _cut(tmp_path / "data", {"h3": (0, 2)})  # two dioscuri views and a Sacre Coeur outlier
    sc = load_scene(data, "h3")
    conf = _conf()
    conf = dataclasses.replace(conf, feature=dataclasses.replace(conf.feature, num_features=128, max_side=320))
    before = prepare.COUNTERS["learned"]
    task = ReconstructionTask({"pipeline": "imc2025-baseline"}, workers=1, submission=tmp_path / "sub.csv")
    res = task.evaluate([sc], conf, H5Cache(tmp_path / "c"))
    assert prepare.COUNTERS["learned"] - before == 3  # every pair of three images, once
    (pairs, verified, imported), = task._kept.values()
    # the notebook's min_matches: exactly the pairs with at least 15 LightGlue matches are imported, the others say why
    assert sorted(imported) == sorted(r["pair"] for r in verified if r["NM"] >= 15)
    assert all((r["failure"] is not None) == (r["NM"] < 15) for r in verified) and len(verified) == 3
    assert 0 < len(imported) < 3, [r["NM"] for r in verified]  # both sides of the rule seen
    s = res.scenes["h3"]
    assert s["pairs"] == 3 and s["mapper"] == "incremental"
    ran = res.summary["baseline_config"]
    assert ran["feature"]["name"] == "aliked" and ran["feature"]["num_features"] == 128
    assert ran["matching"]["method"] == "lightglue"
    rows = list(csv.DictReader(open(tmp_path / "sub.csv", newline="")))
    assert sorted(r["image"] for r in rows) == sorted(sc.images)


def test_replicate_lines_name_lightglues_threshold():
    """A LightGlue study's replicates froze c (min_confidence), not r: the replicate lines and the spread name it."""
    from tuner.replicates import _param_text, param_spread
    params = [{"min_confidence": 0.495, "threshold": 0.115, "max_iters": 110027},
              {"min_confidence": 0.831, "threshold": 0.212, "max_iters": 45095}]
    assert _param_text(params[0]) == "c 0.495, eta 0.115, Gamma 110027"
    assert param_spread(params)["min_confidence"] == (0.495, 0.831) and "ratio" not in param_spread(params)
    assert _param_text({"ratio": 0.85, "threshold": 0.5, "max_iters": 1000}) == "r 0.85, eta 0.5, Gamma 1000"
