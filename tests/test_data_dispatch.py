"""Format detection, scene listing, the load_scene dispatcher and validation / test splits."""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

import pipeline
from pipeline.data import FORMATS, default_max_pairs, default_splits, detect_format, list_scenes, load_scene
from pipeline.data.strecha import write_camera
from pipeline.errors import ImtuneError


def _shared() -> Path:
    env = os.environ.get("IMTUNE_SHARED")
    if env:
        return Path(env) / "data" if (Path(env) / "data").is_dir() else Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


SHARED = _shared()
needs_shared = pytest.mark.skipif(not (SHARED / "strecha").is_dir(),
                                  reason=f"shared data not found at {SHARED} (set IMTUNE_SHARED)")


def _strecha_scene(root: Path, name: str, n: int = 2):
    for k in range(n):
        f = f"{k:04d}.jpg"
        (root / name / "images").mkdir(parents=True, exist_ok=True)
        (root / name / "gt_dense_cameras").mkdir(exist_ok=True)
        cv2.imwrite(str(root / name / "images" / f), np.full((20, 30), 100 + k, np.uint8))
        write_camera(root / name / "gt_dense_cameras" / f"{f}.camera", np.array([[40, 0, 14.5], [0, 40, 9.5], [0, 0, 1]]),
                     [0, 0, 0], np.eye(3), [k, 0, 0], (30, 20))


def _folder_scene(root: Path, name: str):
    (root / name / "images").mkdir(parents=True)
    for k in range(3):
        cv2.imwrite(str(root / name / "images" / f"{k}.png"), np.zeros((10, 12), np.uint8))


@needs_shared
def test_real_shared_folders():
    assert detect_format(SHARED / "strecha") == "strecha"
    # all six Strecha scenes since December 2026 (../shared/data/README.md), listed in sorted order
    six = ["Herz-Jesus-P25", "Herz-Jesus-P8", "castle-P19", "castle-P30", "entry-P10", "fountain-P11"]
    assert list_scenes(SHARED / "strecha") == six
    # the measured default split (benchmarks/results/default-split-and-freeze-rules.md): the fountain and Herz-Jesus (P8, P25) families
    # validate, entry and castle (P19, P30) test; written out, not read from STRECHA_VAL
    assert default_splits(SHARED / "strecha") == {"val": ["fountain-P11", "Herz-Jesus-P8", "Herz-Jesus-P25"],
                                                  "test": ["castle-P19", "castle-P30", "entry-P10"]}
    # ... each family on one side: castle-P19 / P30 share 11 byte-identical images, Herz-Jesus-P8 / P25 a facade
    split = default_splits(SHARED / "strecha")
    for family in (("castle-P19", "castle-P30"), ("Herz-Jesus-P8", "Herz-Jesus-P25")):
        assert len({"val" if s in split["val"] else "test" for s in family}) == 1, family
    assert default_max_pairs(SHARED / "strecha") == 20  # the main job's pairs per scene on this split
    assert default_max_pairs(SHARED / "scannet_sample") is None and default_max_pairs(SHARED / "sacre_coeur") is None
    assert detect_format(SHARED / "sacre_coeur") == "images"
    sc = load_scene(SHARED / "sacre_coeur")
    assert len(sc.images) == 10 and len(sc.pairs) == 45 and all(im.K is None for im in sc.images.values())
    assert detect_format(SHARED / "scannet_sample") == "pairs_with_gt"
    assert default_splits(SHARED / "scannet_sample") == {"val": ["scannet_sample"], "test": []}
    # the shared root holds scenes of several formats side by side
    assert detect_format(SHARED) == "mixed"
    assert set(list_scenes(SHARED)) >= {"sacre_coeur", "scannet_sample"}
    assert load_scene(SHARED, "scannet_sample").source == "pairs_with_gt"


def test_lazy_top_level_import():
    assert pipeline.load_scene is load_scene


def test_detect_and_list_synthetic(tmp_path):
    _strecha_scene(tmp_path / "st", "fountain-P11")
    _strecha_scene(tmp_path / "st", "castle-P19")
    _strecha_scene(tmp_path / "st", "entry-P10")
    assert detect_format(tmp_path / "st") == "strecha"
    assert list_scenes(tmp_path / "st") == ["castle-P19", "entry-P10", "fountain-P11"]
    assert default_splits(tmp_path / "st") == {"val": ["fountain-P11"], "test": ["castle-P19", "entry-P10"]}
    assert default_max_pairs(tmp_path / "st") is None  # 1 pair per scene: a small subset keeps every pair
    _strecha_scene(tmp_path / "st", "castle-P30", n=8)  # 28 pairs > 20: the cap applies to the whole split
    assert default_max_pairs(tmp_path / "st") == 20
    (tmp_path / "st" / "splits.yaml").write_text("val: [castle-P19]\ntest: [entry-P10]\n")
    assert default_max_pairs(tmp_path / "st") is None  # the user's own split: every pair unless --max-pairs
    (tmp_path / "st" / "splits.yaml").unlink()
    import shutil
    shutil.rmtree(tmp_path / "st" / "castle-P30")
    assert detect_format(tmp_path / "st" / "entry-P10") == "strecha"
    assert load_scene(tmp_path / "st" / "entry-P10").name == "entry-P10"
    _folder_scene(tmp_path / "imgs", "b_scene")
    _folder_scene(tmp_path / "imgs", "a_scene")
    assert detect_format(tmp_path / "imgs") == "images"
    assert default_splits(tmp_path / "imgs") == {"val": ["a_scene"], "test": ["b_scene"]}
    assert set(FORMATS) == {"strecha", "imc_pt2020", "imc2022", "imc2025", "colmap", "pairs_with_gt", "images"}


def test_unknown_scene_and_bad_roots(tmp_path):
    _strecha_scene(tmp_path / "st", "fountain-P11")
    _strecha_scene(tmp_path / "st", "entry-P10")
    with pytest.raises(ImtuneError, match=r"unknown scene 'nope'.*entry-P10, fountain-P11"):
        load_scene(tmp_path / "st", "nope")
    with pytest.raises(ImtuneError, match="several scenes.*entry-P10"):
        load_scene(tmp_path / "st")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImtuneError, match="no dataset recognised"):
        detect_format(tmp_path / "empty")
    with pytest.raises(ImtuneError, match="no dataset recognised"):
        load_scene(tmp_path / "empty", "x")
    with pytest.raises(ImtuneError, match="not found"):
        list_scenes(tmp_path / "missing")


def test_splits_yaml(tmp_path):
    root = tmp_path / "imgs"
    for s in ("s1", "s2", "s3"):
        _folder_scene(root, s)
    (root / "splits.yaml").write_text("val: [s2]\ntest:\n  - s1\n  - s3\n")
    assert default_splits(root) == {"val": ["s2"], "test": ["s1", "s3"]}
    (root / "splits.yaml").write_text("validation: s3\n")
    assert default_splits(root) == {"val": ["s3"], "test": []}
    for bad, msg in [("val: [s9]\n", "unknown scene 's9'"), ("- s1\n", "mapping"), ("val: [s1\n", "cannot read"),
                     ("val: [s1]\ntrain: [s2]\n", "unexpected key 'train'"), ("test: [s1]\n", "no validation"),
                     ("val: {a: 1}\n", "list of scene names"), ("!!python/object:os.system {}\n", "cannot read")]:
        (root / "splits.yaml").write_text(bad)
        with pytest.raises(ImtuneError, match=msg) as e:
            default_splits(root)
        assert "splits.yaml" in str(e.value) and "\n" not in str(e.value)


@needs_shared
def test_main_job_caps_pairs_on_the_default_strecha_split(tmp_path):
    """`tune run` on the built-in Strecha split (six scenes, 1,034 pairs) uses at most 20 pairs per scene unless told
    otherwise; before, every pair (a main job of hours). The user's own scenes, --max-pairs or a multiview run keep
    their pairs. The parser and settings only: nothing is tuned."""
    from tuner.cli import build_parser
    from tuner.commands.study import settings_from_args
    parser = build_parser()

    def max_pairs(*extra):
        args = parser.parse_args(["run", "--data", str(SHARED / "strecha"), "--studies-dir", str(tmp_path), *extra])
        return settings_from_args(args).max_pairs

    assert max_pairs() == 20
    assert max_pairs("--max-pairs", "5") == 5
    assert max_pairs("--test-scenes", "entry-P10") is None and max_pairs("--scenes", "fountain-P11") is None
    assert max_pairs("--task", "multiview") is None
