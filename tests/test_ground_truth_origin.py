"""Reports say where a scene's ground truth comes from: the scene's own poses (the camera files of its Strecha-layout folder) or a
reconstruction imtune built by SfM (`tune data build-gt` on an image folder). One real short study: validation on
4 fountain-P11 images (own poses), test on 4 Herz-Jesus-P8 images given as a plain
image folder (SfM poses); the study's attributes, frozen settings, test.json, `tune test`'s table, the HTML report
and the findings header each name both."""
import json
import os
import shutil
import subprocess
import sys

import pytest

from tests.conftest import DATA, ROOT, copy_strecha_subset

STRECHA = DATA / "strecha"
pytestmark = pytest.mark.skipif(not STRECHA.is_dir(), reason=f"real data not found at {STRECHA}")
OWN = "the scene's own poses (the camera files of its Strecha-layout folder)"
SFM = "imtune's SfM reconstruction (tune data build-gt, pycolmap; 4 of 4 images registered)"


def tune(*args, env):
    r = subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], capture_output=True, text=True, cwd=ROOT,
                       env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


@pytest.fixture(scope="module")
def tested(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("origin")
    data = copy_strecha_subset(tmp / "data", ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"])
    herz = data / "herz" / "images"  # no camera files: a plain image folder, its poses by SfM
    herz.mkdir(parents=True)
    for n in ["0002.jpg", "0003.jpg", "0004.jpg", "0005.jpg"]:
        shutil.copy(STRECHA / "Herz-Jesus-P8" / "images" / n, herz / n)
    env = dict(os.environ, IMTUNE_CACHE=str(tmp / "cache"), IMTUNE_GT=str(tmp / "gt"))
    built = json.loads(tune("data", "build-gt", "--data", data, "--scenes", "herz", "--json", "--num-features", "1024",
                            "--max-image-size", "1024", env=env).stdout)
    assert built["herz"]["method"] == "sfm", built
    assert built["herz"]["registered"] == 4, built  # SFM's count below
    studies = tmp / "studies"
    run = tune("--data", data, "--feature", "sift", "--num-features", "1024", "--ransac", "cv-ransac",
               "--scenes", "fountain-P11", "--test-scenes", "herz", "--n-trials", "1", "--test-runs", "1",
               "--budget", "5", "--fix", "max_iters=2000", "--calibration-pairs", "2", "--studies-dir", studies,
               "--jobs", "1", "--quiet",
               env=env)
    test = tune("test", "--study", "sift-1024-cv-ransac-stereo", "--studies-dir", studies, "--runs", "1", "--jobs",
                "1", "--quiet", env=env)
    return dict(tmp=tmp, data=data, env=env, studies=studies, run=run, test=test,
                name="sift-1024-cv-ransac-stereo")


def test_test_json_and_tune_test_name_the_test_scenes_ground_truth(tested):
    t = json.loads((tested["studies"] / tested["name"] / "test.json").read_text())
    assert t["data"]["ground_truth"] == {"herz": SFM}
    assert f"ground truth: herz: {SFM}" in tested["test"].stdout.splitlines(), tested["test"].stdout


def test_the_study_and_its_frozen_settings_name_the_validation_ground_truth(tested):
    import yaml
    frozen = yaml.safe_load((tested["studies"] / tested["name"] / "frozen.yaml").read_text())
    assert frozen["data"]["ground_truth"] == {"fountain-P11": OWN}
    out = tested["run"].stdout.splitlines()
    assert f"validation ground truth: fountain-P11: {OWN}" in out, tested["run"].stdout
    assert f"ground truth: herz: {SFM}" in out, tested["run"].stdout


def test_the_html_report_names_both(tested):
    import html
    report = tested["studies"] / tested["name"] / "report.html"
    tune("plot", "--study", tested["name"], "--studies-dir", tested["studies"], "--out", report, env=tested["env"])
    text = report.read_text()
    assert html.escape(f"validation ground truth: fountain-P11: {OWN}") in text
    assert html.escape(f"test ground truth: herz: {SFM}") in text


def test_the_findings_header_names_both(tested, monkeypatch):
    from tuner.findings import FindingsSettings
    from tuner.findings.report import settings_lines
    monkeypatch.setenv("IMTUNE_GT", tested["env"]["IMTUNE_GT"])
    lines = settings_lines(FindingsSettings(data_root=tested["data"], studies_dir=tested["studies"], quick=True,
                                            val_scenes=["fountain-P11"], test_scenes=["herz"]))
    assert f"ground truth: fountain-P11: {OWN}; herz: {SFM}" in lines, lines


def test_tune_results_and_table_name_the_ground_truth_in_their_caption(tested):
    """`tune results` and `tune table` did not say where the scenes' poses come from, which a reader comparing the
    figures with the paper's needs beside them: results (test numbers) the test scenes', table (validation optima)
    the validation scenes'. One origin for every row: a caption line."""
    env, studies = tested["env"], tested["studies"]
    results = tune("results", "--studies-dir", studies, env=env).stdout
    caption = [ln for ln in results.splitlines() if ln.startswith("Table: ")]
    assert len(caption) == 1 and caption[0].endswith(f" Test ground truth: herz: {SFM}."), results
    assert "| ground truth" not in results  # one origin: no column
    table = tune("table", "--studies-dir", studies, env=env).stdout
    caption = [ln for ln in table.splitlines() if ln.startswith("Table: ")]
    assert len(caption) == 1 and caption[0].endswith(f" Validation ground truth: fountain-P11: {OWN}."), table
    latex = tune("table", "--studies-dir", studies, "--format", "latex", env=env).stdout
    assert "Validation ground truth: fountain-P11: the scene's own poses (the camera files of its Strecha-layout folder)." in latex
    rows = json.loads(tune("results", "--studies-dir", studies, "--format", "json", env=env).stdout)
    assert [r["ground truth"] for r in rows] == [f"herz: {SFM}"], rows
    rows = json.loads(tune("table", "--studies-dir", studies, "--format", "json", env=env).stdout)
    assert [r["val ground truth"] for r in rows] == [f"fountain-P11: {OWN}"], rows


def test_an_older_study_beside_a_new_one_reads_not_recorded_in_a_column(tested, tmp_path):
    """A storage holding a study recorded before imtune recorded the ground truth (no 'ground_truth' in its data or
    test summary) beside one that has it: the origins differ, so each row says its own in a 'ground truth' column
    (results) or 'val ground truth' column (table), the older one 'not recorded'. The older study here is a copy of
    the tested one, as another feature, with those records removed, in a copy of the real storage."""
    import optuna

    from tests.conftest import copy_studies
    studies = copy_studies(tested["studies"], tmp_path / "studies")
    url = f"sqlite:///{studies / 'optuna.db'}"
    optuna.copy_study(from_study_name=tested["name"], from_storage=url, to_storage=url,
                      to_study_name="old-rootsift-1024-cv-ransac-stereo")
    old = optuna.load_study(study_name="old-rootsift-1024-cv-ransac-stereo", storage=url)
    data = {k: v for k, v in old.user_attrs["data"].items() if k != "ground_truth"}
    test = {k: v for k, v in old.user_attrs["test"].items() if k != "ground_truth"}
    old.set_user_attr("data", data)
    old.set_user_attr("test", test)
    old.set_user_attr("feature", "rootsift")
    env = tested["env"]
    rows = json.loads(tune("results", "--studies-dir", studies, "--format", "json", env=env).stdout)
    got = {r["feature"]: r["ground truth"] for r in rows}
    # (the fixture fixes Gamma at 2000, which the feature label says)
    assert got == {"sift+Gamma2000": f"herz: {SFM}",
                   "rootsift+Gamma2000": "not recorded (written before imtune recorded it)"}, rows
    results = tune("results", "--studies-dir", studies, env=env).stdout
    assert "| ground truth" in results.splitlines()[0], results
    assert results.splitlines()[-1].endswith(" Test ground truth of each row's best study: column 'ground truth'.")
    table = tune("table", "--studies-dir", studies, env=env).stdout
    head = table.splitlines()[0]
    assert "| val ground truth" in head, table
    assert any("not recorded (written before imtune recorded it)" in ln for ln in table.splitlines()[2:4]), table
    assert table.splitlines()[-1].endswith(" Validation ground truth of each row's study: column 'val ground truth'.")
    # `tune studies` says it per study too: a short cell in the table, the whole phrases in --json
    listed = tune("studies", "--studies-dir", studies, env=env).stdout
    assert max(len(ln) for ln in listed.splitlines()) <= 100, listed  # split by columns, the study in each part
    lines = listed.splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("|") and ln.split("|")[-2].strip() == "ground truth")
    body = [ln for ln in lines[head + 2:] if ln.startswith("|")]
    body = body[:next((k for k, ln in enumerate(body) if ln.startswith("| study")), len(body))]
    cells = {ln.split("|")[1].strip(): ln.split("|")[-2].strip() for ln in body}
    assert cells == {tested["name"]: "val own poses; test SfM (build-gt)",
                     "old-rootsift-1024-cv-ransac-stereo": "val not recorded; test not recorded"}, listed
    rows = {r["study"]: r["ground_truth"] for r in json.loads(tune("studies", "--studies-dir", studies, "--json",
                                                                     env=env).stdout)}
    assert rows == {tested["name"]: {"validation": {"fountain-P11": OWN}, "test": {"herz": SFM}},
                    "old-rootsift-1024-cv-ransac-stereo": {"validation": None, "test": None}}, rows


def test_ground_truth_short_names_each_origin_truth_origin_gives():
    """The table cell of `tune studies` for every phrase :meth:`Scene.truth_origin` writes (its own poses, SfM in
    their place, SfM co-visibility of listed pairs, co-visibility from 3D points, none), scenes named when they
    differ; a phrase it does not know is shown whole."""
    from pathlib import Path

    import numpy as np

    from pipeline.data.scene import Pair, Scene
    from tuner.formatting import ground_truth_short
    sfm_built = {"method": "sfm", "registered": 4, "images": 5}
    own = Scene(name="a", root=Path("."), images={}, source="strecha")
    sfm = Scene(name="b", root=Path("."), images={}, source="folder", built=sfm_built)
    listed = Scene(name="c", root=Path("."), images={}, source="pairs_with_gt", built=sfm_built,
                   pairs=[Pair("x", "y", R=np.eye(3), t=np.array([1.0, 0, 0]))])
    tri = Scene(name="d", root=Path("."), images={}, source="strecha", built={"method": "poses"})
    bare = Scene(name="e", root=Path("."), images={}, source="folder")
    o = {s.name: s.truth_origin() for s in (own, sfm, listed, tri, bare)}
    assert [ground_truth_short({k: v}) for k, v in o.items()] == [
        "own poses", "SfM (build-gt)", "own poses, SfM co-visibility", "own poses, co-visibility from 3D points",
        "none"], o
    assert ground_truth_short({"a": o["a"], "b": o["b"], "d": o["a"]}) == "a, d: own poses; b: SfM (build-gt)"
    assert ground_truth_short({"a": "somebody's poses"}) == "somebody's poses"
    assert ground_truth_short(None) == ground_truth_short({}) == "not recorded"
