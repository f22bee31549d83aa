"""Multiview integration on real data (Strecha fountain-P11, 6 of its 11 images, 2048 SIFT, small bags),
through the CLI as a user runs it: build-gt, then evaluate --task multiview / both; a failing bag; the
bag cache. Skips when ../shared/data is absent."""
import json
import os

import pytest

from tests.conftest import DATA, copy_strecha_subset

IMAGES = ["0002.jpg", "0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg", "0007.jpg"]


@pytest.fixture(scope="module")
def small_strecha(tmp_path_factory):
    root = copy_strecha_subset(tmp_path_factory.mktemp("data"), IMAGES)
    cache = tmp_path_factory.mktemp("cache")
    old = os.environ.get("IMTUNE_CACHE")
    old_gt = os.environ.pop("IMTUNE_GT", None)  # ground truth goes to $IMTUNE_CACHE/gt
    os.environ["IMTUNE_CACHE"] = str(cache)
    try:
        from tuner.cli import main
        rc = main(["data", "build-gt", "--data", str(root), "--num-features", "1024", "--max-image-size", "1024",
                   "--quiet"])
        assert rc == 0
        yield root, cache
    finally:
        if old is None:
            os.environ.pop("IMTUNE_CACHE", None)
        else:
            os.environ["IMTUNE_CACHE"] = old
        if old_gt is not None:
            os.environ["IMTUNE_GT"] = old_gt


def run_cli(args, capsys):
    from tuner.cli import main
    capsys.readouterr()
    rc = main(args)
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_build_gt_wrote_into_the_cache_not_the_data(small_strecha):
    root, cache = small_strecha
    assert list((cache / "gt").glob("fountain-P11-*/gt.h5"))
    assert sorted(p.name for p in (root / "fountain-P11").iterdir()) == ["gt_dense_cameras", "images"]


def test_evaluate_both_tasks_json(small_strecha, capsys):
    root, cache = small_strecha
    rc, out, err = run_cli(["evaluate", "--data", str(root), "--task", "both", "--num-features", "2048",
                            "--bags", "5:2,6:1", "--workers", "2", "--ratio", "0.85", "--json",
                            "--bag-records", "--covisibility", "0", "--intermediate"], capsys)
    assert rc == 0, err
    res = json.loads(out)
    st, mv = res["stereo"], res["multiview"]
    assert st["pairs"] == 15 and "covisibility" in st  # co-visibility from the built ground truth
    assert list(st["covisibility"])[:2] == ["0+", "0.1+"]
    assert mv["SR"] == 100.0 and mv["RC"] > 90 and mv["bags"] == 3
    assert mv["mAA10"] > 0.7 and mv["NL"] > 300 and mv["TL"] > 2
    assert mv["ATE"] is not None and mv["ATE"] < 0.5  # metres; the cameras are ~10 m from the fountain
    assert set(mv["by_size"]) == {"5", "6"}
    assert len(mv["bag_records"]) == 3 and all(len(r["errors"]) == 10 for r in mv["bag_records"][:2])
    assert res["multiview_config"]["intrinsics"] == "colmap"
    im = res["intermediate"]  # no depth maps on Strecha: the epipolar matching score only
    assert im["pairs"] == 15 and 0.3 < im["epipolar_matching_score"] <= 1.0 and "repeatability" not in im


def test_failing_bags_are_recorded_and_the_run_goes_on(small_strecha, capsys):
    root, cache = small_strecha
    # r = 0.2 leaves a handful of matches per pair: COLMAP finds no initial pair
    rc, out, err = run_cli(["evaluate", "--data", str(root), "--task", "multiview", "--num-features", "2048",
                            "--bags", "5:2", "--ratio", "0.2", "--workers", "1", "--json", "--bag-records"], capsys)
    assert rc == 0, err
    mv = json.loads(out)["multiview"]
    assert mv["failed"] >= 1 and mv["SR"] < 100
    failed = [r for r in mv["bag_records"] if not r["success"]]
    assert failed and all(r["failure"] for r in failed)
    assert all(e == "inf" for r in failed for e in r["errors"])
    assert mv["mAA10"] < 0.5


def test_table_output_and_bag_cache(small_strecha, capsys):
    root, cache = small_strecha
    args = ["evaluate", "--data", str(root), "--task", "multiview", "--num-features", "2048", "--bags", "5:2",
            "--workers", "2", "--mv-intrinsics", "prior"]
    rc, out, err = run_cli(args, capsys)
    assert rc == 0, err
    assert "| scene" in out and "SR" in out and "ATE" in out and "fountain-P11" in out
    n_entries = len(list((cache / "bags").rglob("*.h5")))
    assert n_entries >= 2
    rc, out2, err = run_cli(args, capsys)  # same inputs: bag records come from the cache
    assert rc == 0 and out2 == out
    assert len(list((cache / "bags").rglob("*.h5"))) == n_entries


def test_keep_models_keeps_models_of_cached_bags(small_strecha, tmp_path, capsys):
    """--keep-models after a run of the same bags read them from the cache: no model kept, not even the folder,
    without a word. Now those bags are reconstructed, and their database and model kept."""
    root, cache = small_strecha
    args = ["evaluate", "--data", str(root), "--task", "multiview", "--num-features", "1024", "--bags", "5:1",
            "--workers", "1", "--json", "--quiet"]
    rc, out, err = run_cli(args, capsys)
    assert rc == 0, err
    kept = tmp_path / "models"
    rc, out2, err = run_cli(args + ["--keep-models", str(kept)], capsys)
    assert rc == 0, err
    assert json.loads(out2)["multiview"]["bags"] == 1
    (bag,) = [p for p in kept.iterdir() if p.is_dir()]
    assert (bag / "database.db").is_file() and list(bag.glob("sparse/*/images.bin")), sorted(kept.rglob("*"))

def test_multiview_without_ground_truth_points_is_a_clear_error(tmp_path, capsys, monkeypatch):
    src = DATA / "strecha" / "fountain-P11"
    if not src.exists():
        pytest.skip("real data not found")
    monkeypatch.setenv("IMTUNE_CACHE", str(tmp_path / "empty-cache"))
    monkeypatch.delenv("IMTUNE_GT", raising=False)
    rc, out, err = run_cli(["evaluate", "--data", str(DATA / "strecha"), "--scenes", "fountain-P11", "--task",
                            "multiview", "--num-features", "512", "--bags", "5:1"], capsys)
    assert rc == 2 and "build-gt" in err and "Traceback" not in err


def test_bag_sizes_above_the_scenes_images_are_said_and_kept(small_strecha, capsys):
    """--bags 5:1,8:1,10:1 on a 6-image scene: sizes 8 and 10 become one bag of all 6 images. The numbers are listed
    under size 6 (not 8 or 10), a warning line says so and the JSON keeps it: a user comparing with the paper's
    25-image bags on 11-image Strecha scenes must not read them as the protocol's."""
    root, cache = small_strecha
    rc, out, err = run_cli(["evaluate", "--data", str(root), "--task", "multiview", "--num-features", "1024",
                            "--bags", "5:1,8:1,10:1", "--workers", "2", "--json", "--quiet"], capsys)
    assert rc == 0, err
    mv = json.loads(out)["multiview"]
    assert set(mv["by_size"]) == {"5", "6"} and mv["bags"] == 2
    note = ("scene fountain-P11 has 6 images: bag sizes 8, 10 evaluated as bags of all 6 (listed under size 6, at "
            "most one bag); its multiview numbers at those sizes are not the protocol's")
    assert mv["notes"] == [note]
    assert [ln for ln in err.splitlines() if ln.strip()] == [f"warning: {note}"]
    rc, out, err = run_cli(["evaluate", "--data", str(root), "--task", "multiview", "--num-features", "1024",
                            "--bags", "5:1", "--workers", "2", "--json", "--quiet"], capsys)
    assert rc == 0 and "notes" not in json.loads(out)["multiview"] and "warning" not in err, err
