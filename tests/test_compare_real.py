"""`tune compare` on real Strecha images: a small subset of entry-P10 (images 0000-0006, 21 pairs, 2k SIFT).

On this subset (and on all 45 pairs of entry-P10) DEGENSAC at r 0.85, eta 0.5 px, Gamma 10k beats OpenCV's
RANSAC at its defaults (eta 3 px, confidence 0.99, 1000 iterations) by about 0.36 mAA(10) with p ~ 0.004;
a configuration compared with itself must give difference 0 and p = 1 exactly."""
import json

import pytest
import yaml

from tests.conftest import copy_strecha_subset
from tuner.cli import main

IMAGES = [f"{i:04d}.jpg" for i in range(7)]
SIFT = {"name": "sift", "num_features": 2048}
DEGENSAC = {"feature": SIFT, "matching": {"ratio": 0.85},
            "geometry": {"ransac": "degensac", "threshold": 0.5, "max_iters": 10000}}
OPENCV = {"feature": SIFT, "matching": {"ratio": 0.85},
          "geometry": {"ransac": "cv-ransac", "threshold": 3.0, "confidence": 0.99, "max_iters": 1000}}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("compare")
    data = copy_strecha_subset(root / "data", IMAGES, scene="entry-P10")
    files = {}
    for name, conf in (("degensac", DEGENSAC), ("opencv", OPENCV)):
        files[name] = root / f"{name}.yaml"
        files[name].write_text(yaml.safe_dump({"config": conf}))
    studies = root / "studies"
    (studies / "sift-degensac").mkdir(parents=True)  # a study's frozen settings, as `tune` writes them
    (studies / "sift-degensac" / "frozen.yaml").write_text(yaml.safe_dump({"study": "sift-degensac", "trial": 7,
                                                                          "config": DEGENSAC}))
    common = ["--data", str(data), "--scenes", "entry-P10", "--cache", str(root / "cache"),
              "--studies-dir", str(studies), "--quiet"]
    return {"files": files, "common": common, "data": data, "root": root}


def run(capsys, *argv):
    code = main(["compare", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_tuned_degensac_is_significantly_better_than_opencv_defaults(setup, capsys):
    f = setup["files"]
    code, out, err = run(capsys, f["opencv"], f["degensac"], *setup["common"], "--json")
    assert code == 0, err
    res = json.loads(out)
    o = res["overall"]
    assert set(o) >= {"mAA10_a", "mAA10_b", "difference", "ci", "p_value"}
    assert o["pairs"] == 21 and o["dropped_a"] == 0 and o["dropped_b"] == 0
    assert o["difference"] == pytest.approx(o["mAA10_b"] - o["mAA10_a"])
    assert o["difference"] > 0.15 and o["ci"][0] > 0 and o["p_value"] < 0.05, o
    assert list(res["scenes"]) == ["entry-P10"]
    assert res["scenes"]["entry-P10"]["difference"] == pytest.approx(o["difference"])  # one scene
    # the mAA it compares is the one `tune evaluate` reports for the same configuration
    from tuner.evaluate import evaluate_config
    from tuner.freeze import pipeline_from_dict
    ev = evaluate_config(pipeline_from_dict(DEGENSAC), setup["data"], ["entry-P10"],
                         cache_dir=str(setup["root"] / "cache"))
    assert o["mAA10_b"] == pytest.approx(ev["stereo"]["mAA10"], abs=1e-12)


def test_a_configuration_compared_with_itself(setup, capsys):
    f = setup["files"]
    code, out, err = run(capsys, f["degensac"], "sift-degensac", *setup["common"], "--json")  # file vs study
    assert code == 0, err
    o = json.loads(out)["overall"]
    assert o["difference"] == 0.0 and o["ci"] == [0.0, 0.0] and o["p_value"] == 1.0
    # said, not left to be read as a finding (a study and a file of its own settings look different)
    said = [ln for ln in err.splitlines() if "same configuration" in ln]
    assert len(said) == 1 and "sift-degensac and " in said[0] and "difference is 0 by construction" in said[0], err
    code, out, err = run(capsys, f["degensac"], f["degensac"], *setup["common"])
    assert code == 0, err
    assert err.count("same configuration") == 1
    assert "no significant difference" in out and "| A better" not in out and "| B better" not in out


def test_three_configurations_give_a_list_and_a_readable_table(setup, capsys):
    f = setup["files"]
    code, out, err = run(capsys, f["degensac"], f["opencv"], f["degensac"], *setup["common"], "--json")
    assert code == 0, err
    res = json.loads(out)
    assert isinstance(res, list) and len(res) == 2
    assert res[0]["overall"]["difference"] < 0 and res[0]["overall"]["ci"][1] < 0
    assert res[1]["overall"]["p_value"] == 1.0
    code, out, err = run(capsys, f["degensac"], f["opencv"], *setup["common"])
    assert code == 0, err
    assert "| A better" in out and "95% CI" in out and "entry-P10" in out


@pytest.mark.parametrize("argv, culprit", [
    (["no-such-study", "degensac"], "no-such-study"),
    (["missing.yaml", "degensac"], "missing.yaml"),
    (["degensac"], "at least two"),
])
def test_bad_input_is_one_line_and_exit_2(setup, capsys, tmp_path, argv, culprit):
    f = setup["files"]
    argv = [str(f[a]) if a in f else (str(tmp_path / a) if a.endswith(".yaml") else a) for a in argv]
    code, out, err = run(capsys, *argv, *setup["common"])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tune: error:") and culprit in lines[0], err


def test_a_scene_a_study_was_tuned_on_is_named_in_a_warning(setup, capsys):
    """`tune compare` evaluates on every scene of the data by default, the validation scenes included: a tuned study
    was compared on the very pairs it was tuned on (favoured there), and nothing said so. Now one warning per study
    names the scenes that are its validation scenes."""
    studies = setup["root"] / "studies"
    (studies / "tuned-on-entry").mkdir(parents=True, exist_ok=True)
    (studies / "tuned-on-entry" / "frozen.yaml").write_text(yaml.safe_dump(
        {"study": "tuned-on-entry", "trial": 3, "config": DEGENSAC,
         "data": {"val_scenes": ["entry-P10"], "test_scenes": ["Herz-Jesus-P8"]}}))
    code, out, err = run(capsys, setup["files"]["opencv"], "tuned-on-entry", *setup["common"])
    assert code == 0, err
    warn = [ln for ln in err.splitlines() if "validation scene" in ln]
    assert len(warn) == 1 and "tuned-on-entry" in warn[0] and "entry-P10" in warn[0], err
    code, out, err = run(capsys, setup["files"]["opencv"], "sift-degensac", *setup["common"])  # no val scenes known
    assert code == 0 and "validation scene" not in err, err
