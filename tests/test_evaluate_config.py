"""`tune evaluate --config FILE|STUDY` (issue 13 item 8): a frozen.yaml, a configuration YAML / JSON or an IMC
benchmark method JSON; the pipeline options typed on the command line override the file (also when typed with
their default value); extractor options from the command line (``--feature-option KEY=VALUE``) and from a file
(``config: feature: options:``) reach the extractor.

Real `tune evaluate` subprocesses on 3 images of fountain-P11 (3 pairs)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import yaml

from tests.conftest import DATA, ROOT, copy_strecha_subset

STRECHA = DATA / "strecha"
pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return copy_strecha_subset(tmp_path_factory.mktemp("ec-data"), ["0004.jpg", "0005.jpg", "0006.jpg"])


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("ec-cache"))


def evaluate(data, cache, *args, json_out=True):
    env = dict(os.environ, IMTUNE_CACHE=cache)
    env.pop("IMTUNE_DATA", None)
    cmd = [sys.executable, "-m", "tuner", "evaluate", "--data", str(data), "--quiet", *(["--json"] if json_out else []),
           *args]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)


def ok(r) -> dict:
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout)


def one_line_error(r, *needles) -> str:
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("tune: error:"), r.stderr
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


CONFIG = {"config": {"feature": {"name": "sift", "num_features": 512},
                     "matching": {"ratio": 0.8, "strategy": "both"},
                     "geometry": {"ransac": "degensac", "threshold": 1.0, "max_iters": 2000, "seed": 3}}}


@pytest.fixture
def config_file(tmp_path):
    p = tmp_path / "conf.yaml"
    p.write_text(yaml.safe_dump(CONFIG))
    return p


def test_config_file_values_are_used(data, cache, config_file):
    out = ok(evaluate(data, cache, "--config", str(config_file)))
    c = out["config"]
    assert c["feature"]["num_features"] == 512 and c["matching"]["ratio"] == 0.8
    assert c["geometry"]["threshold"] == 1.0 and c["geometry"]["max_iters"] == 2000 and c["geometry"]["seed"] == 3
    assert out["stereo"]["NF"] <= 512
    assert out["config_source"] == {"config": str(config_file), "overridden": []}


def test_typed_options_override_the_file_even_at_their_default(data, cache, config_file):
    """--ratio 0.85 is the option's default, yet typed it wins over the file's 0.8; untyped options (the
    threshold's default 0.5, --max-iters 50000) never do."""
    out = ok(evaluate(data, cache, "--config", str(config_file), "--ratio", "0.85", "--seed", "0"))
    c = out["config"]
    assert c["matching"]["ratio"] == 0.85 and c["geometry"]["seed"] == 0
    assert c["geometry"]["threshold"] == 1.0 and c["geometry"]["max_iters"] == 2000
    assert c["feature"]["num_features"] == 512
    assert out["config_source"]["overridden"] == ["ratio", "seed"]
    # the readable output says where the configuration came from and what was overridden
    r = evaluate(data, cache, "--config", str(config_file), "--threshold", "0.5", json_out=False)
    assert r.returncode == 0, r.stderr
    head = r.stdout.splitlines()
    assert head[0].startswith(f"config {config_file} (") and head[0].endswith("overridden on the command line: --threshold")
    assert "eta=0.5px" in head[1] and "r=0.8 " in head[1] and "Gamma=2000" in head[1]


def test_frozen_yaml_and_study_name(data, cache, tmp_path):
    frozen = {"study": "my-study", "trial": 7, "task": "stereo", "params": {"ratio": 0.9},
              **{"config": {**CONFIG["config"], "matching": {"ratio": 0.9, "strategy": "both"}}}}
    sdir = tmp_path / "studies"
    (sdir / "my-study").mkdir(parents=True)
    path = sdir / "my-study" / "frozen.yaml"
    path.write_text(yaml.safe_dump(frozen))
    by_file = ok(evaluate(data, cache, "--config", str(path), "--max-iters", "3000"))
    assert by_file["config"]["matching"]["ratio"] == 0.9 and by_file["config"]["geometry"]["max_iters"] == 3000
    by_name = ok(evaluate(data, cache, "--config", "my-study", "--studies-dir", str(sdir)))
    assert by_name["config"]["matching"]["ratio"] == 0.9 and by_name["config"]["geometry"]["max_iters"] == 2000
    r = evaluate(data, cache, "--config", "no-such-study", "--studies-dir", str(sdir))
    one_line_error(r, "no-such-study", "neither a config file nor a study")
    one_line_error(evaluate(data, cache, "--config", str(tmp_path / "missing.yaml")), "missing.yaml", "does not exist")


def test_imc_method_json(data, cache, tmp_path):
    imc = tmp_path / "method.json"
    imc.write_text(json.dumps([{"config_common": {"json_label": "sift-imc", "descriptor": "sift", "num_keypoints": 512},
                                "config_phototourism_stereo": {
                                    "matcher": {"method": "nn", "filtering": {"type": "snn_ratio_pairwise",
                                                                              "threshold": 0.75},
                                                "symmetric": {"enabled": True, "reduce": "both"}},
                                    "geom": {"method": "cmp-degensac-f", "threshold": 0.75, "max_iter": 4000}}}]))
    out = ok(evaluate(data, cache, "--config", str(imc), "--num-features", "256"))
    c = out["config"]
    assert c["matching"]["ratio"] == 0.75 and c["geometry"]["threshold"] == 0.75 and c["geometry"]["max_iters"] == 4000
    assert c["feature"]["num_features"] == 256 and out["stereo"]["NF"] <= 256



def test_imc_method_json_reduce_any_is_the_union(data, cache, tmp_path):
    """The benchmark's symmetric matching takes reduce "both" (mutual) or "any" (the union of both directions:
    imtune's either); "any" was refused as "unknown matching strategy 'any'"."""
    imc = tmp_path / "method.json"
    method = {"config_common": {"descriptor": "sift", "num_keypoints": 256},
              "config_phototourism_stereo": {"matcher": {"filtering": {"type": "snn_ratio_pairwise", "threshold": 0.9},
                                                         "symmetric": {"enabled": True, "reduce": "any"}},
                                             "geom": {"method": "cmp-degensac-f", "threshold": 0.75, "max_iter": 1000}}}
    imc.write_text(json.dumps(method))
    union = ok(evaluate(data, cache, "--config", str(imc)))
    assert union["config"]["matching"]["strategy"] == "either"
    method["config_phototourism_stereo"]["matcher"]["symmetric"]["reduce"] = "both"
    imc.write_text(json.dumps(method))
    mutual = ok(evaluate(data, cache, "--config", str(imc)))
    assert mutual["config"]["matching"]["strategy"] == "both" and union["stereo"]["NM"] > mutual["stereo"]["NM"]


def test_imc_method_json_fginn_radius_and_distance_filter_are_used(data, cache, tmp_path):
    """The matcher's filtering.fginn_radius and descriptor_distance_filter.threshold were read as nothing: FGINN at
    10 px and no distance filter, unsaid."""
    imc = tmp_path / "method.json"
    imc.write_text(json.dumps({"config_common": {"descriptor": "sift", "num_keypoints": 256},
                               "config_phototourism_stereo": {
                                   "matcher": {"filtering": {"type": "fginn_ratio_pairwise", "threshold": 0.9,
                                                             "fginn_radius": 15},
                                               "descriptor_distance_filter": {"threshold": 150},
                                               "symmetric": {"enabled": True, "reduce": "both"}},
                                   "geom": {"method": "cmp-degensac-f", "threshold": 0.75, "max_iter": 1000}}}))
    out = ok(evaluate(data, cache, "--config", str(imc)))
    m = out["config"]["matching"]
    assert (m["fginn"], m["fginn_px"], m["distance_threshold"]) == (True, 15.0, 150.0), m

def test_feature_option_changes_the_extracted_features(data, cache, tmp_path):
    """SIFT at the paper's lowered contrast threshold (1e-5) fills the 2048 budget on these 1536 x 1024
    images; at contrast_threshold=0.1 far fewer DoG extrema pass. From the command line and from a file."""
    base = ok(evaluate(data, cache, "--num-features", "2048"))
    high = ok(evaluate(data, cache, "--num-features", "2048", "--feature-option", "contrast_threshold=0.1"))
    assert high["config"]["feature"]["options"] == [["contrast_threshold", 0.1]]
    assert base["stereo"]["NF"] == 2048
    assert high["stereo"]["NF"] < 0.5 * base["stereo"]["NF"], (high["stereo"]["NF"], base["stereo"]["NF"])
    conf = tmp_path / "high.yaml"
    conf.write_text(yaml.safe_dump({"config": {"feature": {"name": "sift", "num_features": 2048,
                                                           "options": {"contrast_threshold": 0.1}}}}))
    from_file = ok(evaluate(data, cache, "--config", str(conf)))
    assert from_file["config"]["feature"]["options"] == [["contrast_threshold", 0.1]]
    assert from_file["stereo"]["NF"] == high["stereo"]["NF"]
    # a typed option is merged over the file's: back to the lowered threshold, and a second option kept
    merged = ok(evaluate(data, cache, "--config", str(conf), "--feature-option", "contrast_threshold=1e-5",
                         "--feature-option", "edge_threshold=10"))
    assert merged["config"]["feature"]["options"] == [["contrast_threshold", 1e-5], ["edge_threshold", 10]]
    assert merged["stereo"]["NF"] == base["stereo"]["NF"]


def test_feature_option_errors_are_one_line(data, cache, tmp_path):
    err = one_line_error(evaluate(data, cache, "--feature-option", "edge_treshold=10"),
                         "--feature-option", "unknown option(s) edge_treshold", "edge_threshold", "contrast_threshold")
    assert "sift" in err
    one_line_error(evaluate(data, cache, "--feature-option", "n_octave_layers=many"), "n_octave_layers", "not a int")
    one_line_error(evaluate(data, cache, "--feature-option", "sigma"), "--feature-option", "KEY=VALUE")
    one_line_error(evaluate(data, cache, "--feature-option", "sigma=nan"), "--feature-option", "finite")
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"config": {"feature": {"name": "sift", "options": {"edgethreshold": 3}}}}))
    one_line_error(evaluate(data, cache, "--config", str(bad)), str(bad), "unknown option(s) edgethreshold",
                   "edge_threshold")
    # the file's options belong to its feature: another --feature drops them rather than failing on them
    out = ok(evaluate(data, cache, "--config", str(bad), "--feature", "orb", "--num-features", "256"))
    assert out["config"]["feature"]["name"] == "orb" and out["config"]["feature"]["options"] == []


def test_typed_options_are_tracked_by_the_real_parser():
    """Which options count as typed: argparse calls an action only for what is on the command line."""
    from tuner.cli import build_parser
    from tuner.options import explicit_options
    ap = build_parser()
    assert explicit_options(ap.parse_args(["evaluate"])) == frozenset()
    a = ap.parse_args(["evaluate", "--ratio", "0.85", "--fginn", "--feature-option", "sigma=1.6", "--feature-option",
                       "edge_threshold=10"])
    assert {"ratio", "fginn", "feature_option"} <= explicit_options(a)
    assert "threshold" not in explicit_options(a) and a.threshold == 0.5
    assert a.feature_option == [("sigma", 1.6), ("edge_threshold", 10)]
    b = ap.parse_args(["evaluate", "--feature-option", "upright=true", "--feature-option", "x=text"])
    assert b.feature_option == [("upright", True), ("x", "text")]


def test_feature_options_name_the_study():
    """`tune --feature-option ...` is another configuration: its default study name says so (no clash with the
    study without options, which resuming would refuse)."""
    from tuner.cli import build_parser
    from tuner.options import build_config
    from tuner.study import default_study_name
    args = build_parser().parse_args(["run", "--feature-option", "edge_threshold=5", "--feature-option",
                                      "contrast_threshold=0.01"])
    conf = build_config(args, ratio=1.0, threshold=0.5, max_iters=1000, seed=0)
    assert default_study_name(conf) == "sift+contrast_threshold0.01+edge_threshold5-8000-degensac-stereo"
    plain = build_config(build_parser().parse_args(["run"]), ratio=1.0, threshold=0.5, max_iters=1000, seed=0)
    assert default_study_name(plain) == "sift-8000-degensac-stereo"


@pytest.mark.parametrize("kw,said", [
    ({"conf": {"feature": {"num_features": 512}}}, "conf must be a PipelineConfig"),  # AttributeError
    ({"conf": None}, "conf must be a PipelineConfig"),
    ({"max_pairs": -1}, "max_pairs must be None or 0 (every pair) or an integer >= 1, got -1"),  # numpy ValueError
    ({"max_pairs": 1.5}, "max_pairs must be None"),  # numpy TypeError
    ({"ci_resamples": -1}, "ci_resamples must be None (the default, 2000), 0 (no interval) or an integer from 100"),
    ({"ci_resamples": 1}, "got 1"),  # mAA10 0.633 [0.333, 0.333]: an interval missing its estimate
    ({"ci_resamples": 2.5}, "got 2.5"),
    ({"workers": 0}, "workers must be None (every usable CPU) or an integer >= 1, got 0"),
])
def test_evaluate_config_checks_its_arguments_first(kw, said, data, cache):
    """The documented Python call (tuner.evaluate.evaluate_config) with a wrong argument value: one ImtuneError
    naming it, before any scene is read, instead of an AttributeError / numpy / scipy error."""
    from pipeline.config import FeatureConfig, PipelineConfig
    from pipeline.errors import ImtuneError
    from tuner.evaluate import evaluate_config
    args = {"conf": PipelineConfig(feature=FeatureConfig(num_features=512)), "data_root": data,
            "scenes": ["fountain-P11"], "cache_dir": cache, "jobs": 1, **kw}
    with pytest.raises(ImtuneError) as e:
        evaluate_config(**args)
    assert said in str(e.value) and "\n" not in str(e.value), str(e.value)
