"""The IMC 2024/2025 reconstruction task: loader, bad input, `tune data scenes` / `tune data to-imc`, and the task on a
small subset of the real dataset (../shared/data/imc2025) with both mappers, its submission.csv scored by the
independent reference implementation (tests/imc_reference_metric.py)."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import ImtuneError
from tests import imc_reference_metric as ref
from tests.conftest import DATA, require

IMC = DATA / "imc2025"
DATASET = "imc2023_theather_imc2024_church"
HEADER = "dataset,scene,image,rotation_matrix,translation_vector\n"
R_OK = "1;0;0;0;1;0;0;0;1"


def tune(*args, timeout=900):
    return subprocess.run([sys.executable, "-m", "tuner", *args], capture_output=True, text=True, timeout=timeout)


def _jpeg(path: Path, seed: int = 0) -> None:
    import cv2
    img = (np.random.default_rng(seed).random((48, 64)) * 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def _layout(root: Path, rows: list[str], thresholds: list[str] | None = None, images=None) -> Path:
    """A tiny IMC 2025 layout: labels rows (after the header), thresholds rows, image files (default: every image the
    rows name)."""
    (root / "train" / "ds").mkdir(parents=True, exist_ok=True)
    (root / "train_labels.csv").write_text(HEADER + "".join(r + "\n" for r in rows))
    th = thresholds if thresholds is not None else ["ds,A,0.025;0.05;0.1;0.2;0.5;1.0"]
    (root / "train_thresholds.csv").write_text("dataset,scene,thresholds\n" + "".join(r + "\n" for r in th))
    names = images if images is not None else [r.split(",")[2] for r in rows]
    for k, n in enumerate(names):
        _jpeg(root / "train" / "ds" / n, k)
    return root


def _rows(n: int, scene: str = "A") -> list[str]:
    return [f"ds,{scene},im{k}.jpg,{R_OK},{k};0;0" for k in range(n)]


# ------------------------------------------------------------------------------------------------ loader

def test_loads_scenes_outliers_thresholds(tmp_path):
    from pipeline.data import detect_format, load_scene
    rows = _rows(4) + ["ds,outliers,o1.jpg,nan;nan;nan;nan;nan;nan;nan;nan;nan,nan;nan;nan"]
    root = _layout(tmp_path, rows)
    assert detect_format(root) == "imc2025"
    sc = load_scene(root, "ds")
    assert sc.groups == {"im0.jpg": "A", "im1.jpg": "A", "im2.jpg": "A", "im3.jpg": "A", "o1.jpg": "outliers"}
    assert sc.images["o1.jpg"].R is None and sc.thresholds == {"A": (0.025, 0.05, 0.1, 0.2, 0.5, 1.0)}
    assert len(sc.pairs) == 6  # pairs within the scene only


def test_missing_image_is_one_line_error(tmp_path):
    from pipeline.data import load_scene
    root = _layout(tmp_path, _rows(3), images=["im0.jpg", "im1.jpg"])
    with pytest.raises(ImtuneError, match=r"line 4: image file not found: .*im2\.jpg"):
        load_scene(root, "ds")


@pytest.mark.parametrize("rot, what", [("1;0;0;0;1;0;0;0", "expected 9"), ("1;0;0;0;2;0;0;0;1", "not orthonormal"),
                                       ("1;0;0;0;1;0;0;0;x", "not a number")])
def test_bad_rotation_is_one_line_error(tmp_path, rot, what):
    from pipeline.data import load_scene
    rows = _rows(3)
    rows[1] = f"ds,A,im1.jpg,{rot},1;0;0"
    root = _layout(tmp_path, rows)
    with pytest.raises(ImtuneError, match=f"line 3.*{what}"):
        load_scene(root, "ds")


def test_scene_absent_from_thresholds(tmp_path):
    from pipeline.data import load_scene
    root = _layout(tmp_path, _rows(3) + [f"ds,B,b0.jpg,{R_OK},0;1;0"], thresholds=["ds,A,0.025;0.05;0.1;0.2;0.5;1.0"])
    with pytest.raises(ImtuneError, match="scene 'B' of dataset 'ds' has no thresholds"):
        load_scene(root, "ds")


def test_image_in_no_label_row_is_a_counted_exclusion(tmp_path):
    from pipeline.data import load_scene
    from pipeline.tasks import get_task
    root = _layout(tmp_path, _rows(4), images=["im0.jpg", "im1.jpg", "im2.jpg", "im3.jpg", "stray.jpg"])
    sc = load_scene(root, "ds")
    assert sc.excluded == ["stray.jpg"] and "stray.jpg" not in sc.images
    notes = get_task("reconstruction").scene_notes(sc)
    assert any("1 image file(s) in no label row left out" in n for n in notes)


def test_single_image_dataset_is_refused_in_one_line(tmp_path):
    root = _layout(tmp_path, _rows(1))
    r = tune("evaluate", "--task", "reconstruction", "--data", str(root), "--cache", str(tmp_path / "c"), "--json")
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "nothing" in r.stderr and "evaluate" in r.stderr


def test_missing_image_cli_exits_2_without_traceback(tmp_path):
    root = _layout(tmp_path, _rows(3), images=["im0.jpg", "im1.jpg"])
    r = tune("evaluate", "--task", "reconstruction", "--data", str(root), "--cache", str(tmp_path / "c"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "image file not found" in r.stderr and len(r.stderr.strip().splitlines()) == 1


# --------------------------------------------------------------------------------------------- commands

def test_data_scenes_lists_the_real_dataset():
    require(IMC)
    r = tune("data", "scenes", "--data", str(IMC), "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    info = next(s for s in d["scenes"] if s["scene"] == DATASET)["imc"]
    assert info["scenes"] == {"church": 50, "kyiv-puppet-theater": 26}
    assert info["outliers"] == 0 and info["intrinsics"] is False
    r = tune("data", "scenes", "--data", str(IMC))
    assert "  IMC dataset: 76 images; outliers 0; intrinsics unknown\n" in r.stdout
    assert "  scenes: church (50), kyiv-puppet-theater (26)\n" in r.stdout


def test_to_imc_writes_a_strecha_mix_that_loads(tmp_path):
    require(DATA / "strecha")
    from pipeline.data import load_scene
    out = tmp_path / "mix"
    r = tune("data", "to-imc", "--data", str(DATA / "strecha"), "--scenes", "fountain-P11,Herz-Jesus-P8",
             "--outliers", "entry-P10", "--out", str(out), "--dataset", "mix", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["scenes"] == {"fountain-P11": 11, "Herz-Jesus-P8": 8}
    sc = load_scene(out, "mix")
    assert len(sc.images) == 29 and sum(g == "outliers" for g in sc.groups.values()) == 10
    im = sc.images["fountain-P11_0000.jpg"]
    truth = load_scene(DATA / "strecha", "fountain-P11").images["0000.jpg"]
    assert np.allclose(im.R, truth.R) and np.allclose(im.t, truth.t) and np.allclose(im.K, truth.K)
    r = tune("data", "to-imc", "--data", str(DATA / "strecha"), "--scenes", "fountain-P11", "--out",
             str(DATA / "strecha" / "x"), "--dataset", "bad")
    assert r.returncode == 2 and "inside the data folder" in r.stderr and "Traceback" not in r.stderr


# ------------------------------------------------------------------------------------ the task, real data

def _subset(dst: Path, church: int = 10, theater: int = 6) -> Path:
    """A small IMC 2025 layout of the real dataset: the first images of each scene (linked), their label rows."""
    require(IMC)
    with open(IMC / "train_labels.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    keep, n = [], {"church": 0, "kyiv-puppet-theater": 0}
    cap = {"church": church, "kyiv-puppet-theater": theater}
    for r in rows:
        if n[r["scene"]] < cap[r["scene"]]:
            keep.append(r)
            n[r["scene"]] += 1
    (dst / "train" / DATASET).mkdir(parents=True)
    with open(dst / "train_labels.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(keep)
    for r in keep:
        os.symlink((IMC / "train" / DATASET / r["image"]).resolve(), dst / "train" / DATASET / r["image"])
    (dst / "train_thresholds.csv").write_text((IMC / "train_thresholds.csv").read_text())
    return dst


@pytest.fixture(scope="module")
def subset(tmp_path_factory):
    return _subset(tmp_path_factory.mktemp("imc") / "data", church=8, theater=5)


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_task_writes_a_submission_scored_like_the_reference(subset, shared_cache, tmp_path, mapper):
    sub = tmp_path / "submission.csv"
    r = tune("evaluate", "--task", "reconstruction", "--data", str(subset), "--cache", str(shared_cache),
             "--num-features", "1024", "--mapper", mapper, "--submission", str(sub), "--workers", "1", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)["reconstruction"]
    ds = out["scenes"][DATASET]
    assert ds["mapper"] == mapper and ds["submission"] == str(sub)
    with open(sub, newline="") as f:
        rows = list(csv.DictReader(f))
    assert sorted(x["image"] for x in rows) == sorted(os.listdir(subset / "train" / DATASET))  # one row per image
    assert set(ds["ground_truth_scenes"]) == {"church", "kyiv-puppet-theater"}
    for k in ("score", "mAA", "clusterness"):
        assert 0.0 <= out[k] <= 1.0
    theirs = ref.score(subset / "train_labels.csv", sub, subset / "train_thresholds.csv")
    assert abs(theirs["score"] - out["score"]) < 1e-6
    assert abs(theirs["mAA"] - out["mAA"]) < 1e-6
    assert abs(theirs["clusterness"] - out["clusterness"]) < 1e-6


def test_short_study_freezes_and_tests(tmp_path):
    """Validate on a Strecha mix written by `tune data to-imc`, test on the real dataset's subset (whole datasets on
    each side); Gamma fixed so that no budget calibration runs; the mapper options are searched."""
    require(DATA / "strecha")
    both = tmp_path / "both"
    both.mkdir()
    _subset(both / "real", church=6, theater=4)
    from pipeline.data import load_scene
    from pipeline.data.imc_export import export_imc
    src = tmp_path / "strecha"
    for s, keep in (("fountain-P11", 5), ("Herz-Jesus-P8", 5)):
        names = sorted(load_scene(DATA / "strecha", s, verify=False).images)[:keep]
        from tests.conftest import copy_strecha_subset
        copy_strecha_subset(src, names, scene=s)
    export_imc(src, ["fountain-P11", "Herz-Jesus-P8"], both / "mix", "strecha-mix")
    (both / "splits.yaml").write_text(f"val: [strecha-mix]\ntest: [{DATASET}]\n")
    r = tune("--task", "reconstruction", "--data", str(both), "--num-features", "512", "--n-trials", "2",
             "--test-runs", "1", "--fix", "max_iters=2000", "--studies-dir", str(tmp_path / "studies"),
             "--cache", str(tmp_path / "cache"), "--workers", "1", "--seed", "0", "--quiet", "--json",
             timeout=1500)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    text = json.dumps(out)
    assert "min_inliers" in text and "min_model_size" in text  # the mapper options were searched and frozen
    frozen = list((tmp_path / "studies").rglob("frozen.yaml"))
    assert frozen, sorted(p.name for p in (tmp_path / "studies").rglob("*"))
    import yaml
    fz = yaml.safe_load(frozen[0].read_text())
    # the mapper options are frozen parameters (the config's mapper section is left out at its defaults)
    assert fz["task"] == "reconstruction" and {"min_inliers", "min_model_size"} <= set(fz["params"])
    assert fz["feature"] == "colmap-sift"  # the task's default feature (not typed)
    assert fz["selection"]["rule"] == "confirmed"  # the task's default: the best trials confirmed at more seeds
    # the test compares with COLMAP out of the box (the task's default reference), per dataset and overall
    ref = out["test"]["reference"]
    assert ref["label"].startswith("COLMAP out of the box") and ref["spec"] == "colmap"
    cmp = ref["comparison"]
    frozen_score = out["test"]["mean"]["scenes"][DATASET]["score"]
    ref_score = ref["mean"]["scenes"][DATASET]["score"]
    assert cmp["datasets"][DATASET] == pytest.approx(frozen_score - ref_score)
    assert cmp["difference"] == pytest.approx(frozen_score - ref_score) and cmp["pairs"] == 1
    # submission.csv of the frozen settings' first run in the study's folder, scored alike by the independent metric
    sub = Path(out["test"]["submission"])
    assert sub.parent == frozen[0].parent and sub.name == "submission.csv"
    with open(sub, newline="") as f:
        rows = list(csv.DictReader(f))
    assert sorted(x["image"] for x in rows) == sorted(os.listdir(both / "real" / "train" / DATASET))
    from tests import imc_reference_metric as ref_metric  # ``ref`` is the reference's section here
    theirs = ref_metric.score(both / "real" / "train_labels.csv", sub, both / "real" / "train_thresholds.csv")
    assert abs(theirs["score"] - out["test"]["runs"][0]["scenes"][DATASET]["score"]) < 1e-6
    # the study's first trial was the task's defaults (the values docs/reconstruction.md gives; Gamma fixed here)
    import optuna
    st = optuna.load_study(study_name=fz["study"], storage=f"sqlite:///{tmp_path / 'studies' / 'optuna.db'}")
    first = st.trials[0]
    assert first.user_attrs.get("start") == "task defaults"
    assert first.params == pytest.approx({"ratio": 0.85, "threshold": 1.0, "min_inliers": 15, "min_model_size": 3,
                                          "init_min_num_inliers": 25, "abs_pose_min_num_inliers": 12,
                                          "abs_pose_max_error": 12.0, "filter_max_reproj_error": 4.0})


def test_each_image_is_in_one_cluster_only(monkeypatch):
    """COLMAP's incremental mapper may register an image in two models: it stays in the larger one; a model left with
    fewer than min_model_size images is no cluster; every image has one submission row, nan where unregistered."""
    from pipeline import colmap_db
    from pipeline.tasks.reconstruction import clusters_from_models, submission_rows
    monkeypatch.setattr(colmap_db, "model_poses", lambda m: m)
    pose = (np.eye(3), np.zeros(3))
    big = {n: pose for n in "abcdef"}
    second = {n: pose for n in "efgh"}  # e, f already in the first
    third = {n: pose for n in "fgi"}  # only i is new: no cluster
    names = list("abcdefghij")
    clusters = clusters_from_models([big, second, third], names, 2)
    assert {k: sorted(v) for k, v in clusters.items()} == {"cluster0": list("abcdef"), "cluster1": ["g", "h"]}
    rows = submission_rows("ds", names, clusters)
    assert sorted(r[2] for r in rows) == names
    assert [r[1] for r in rows if r[2] in "ij"] == ["outliers", "outliers"]
    assert all("nan" in r[3] for r in rows if r[1] == "outliers")


def test_loads_the_imc2024_layout_with_intrinsics(tmp_path):
    """IMC 2024: labels in train/ with image_name and calibration_matrix columns, images under train/<dataset>/images."""
    from pipeline.data import load_scene
    from pipeline.data.imc2025 import describe
    train = tmp_path / "train"
    K = "500;0;31.5;0;500;23.5;0;0;1"
    rows = [f"im{k}.jpg,{R_OK},{k};0;0,{K},ds,A" for k in range(4)]
    train.mkdir()
    (train / "train_labels.csv").write_text("image_name,rotation_matrix,translation_vector,calibration_matrix,dataset,"
                                            "scene\n" + "".join(r + "\n" for r in rows))
    (train / "train_thresholds.csv").write_text("dataset,scene,thresholds\nds,A,0.025;0.05;0.1;0.2;0.5;1.0\n")
    for k in range(4):
        _jpeg(train / "ds" / "images" / f"im{k}.jpg", k)
    sc = load_scene(tmp_path, "ds")
    assert len(sc.images) == 4 and np.allclose(sc.images["im2.jpg"].K[0, 0], 500)
    assert describe(tmp_path)[0]["intrinsics"] is True


def test_join_submissions_keeps_one_header(tmp_path):
    """The study's submission.csv of several test datasets: one header, every dataset's rows in order."""
    from tuner.freeze import join_submissions
    head = "dataset,scene,image,rotation_matrix,translation_vector"
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    a.write_text(f"{head}\nd1,cluster0,x.png,1;0;0;0;1;0;0;0;1,0;0;0\n")
    b.write_text(f"{head}\nd2,outliers,y.png,nan,nan\nd2,cluster0,z.png,1;0;0;0;1;0;0;0;1,1;2;3\n")
    join_submissions([str(a), str(b)], tmp_path / "submission.csv")
    assert (tmp_path / "submission.csv").read_text() == (
        f"{head}\nd1,cluster0,x.png,1;0;0;0;1;0;0;0;1,0;0;0\nd2,outliers,y.png,nan,nan\n"
        "d2,cluster0,z.png,1;0;0;0;1;0;0;0;1,1;2;3\n")
