"""Ground-truth building with pycolmap: from known poses (Strecha, laser-scan ground truth) and from an
image folder (SfM), storage round trip, corrupt files, and the evaluate path picking it up. Small
settings (few images, 1024 COLMAP SIFT on images resized to 1024 px) keep this under a minute."""
import json

import numpy as np
import pytest

from pipeline.data import load_scene
from pipeline.data.ground_truth import (
    GTConfig,
    attach_ground_truth,
    build_ground_truth,
    find_ground_truth,
    gt_path,
    load_ground_truth,
    reprojection_errors,
)
from pipeline.errors import ImtuneError

SMALL = dict(num_features=1024, max_image_size=1024, bags=((3, 5),), min_points=50)


def subset(scene, names):
    scene.images = {n: scene.images[n] for n in names}
    scene.pairs = [p for p in scene.pairs if p.i in scene.images and p.j in scene.images]
    return scene


@pytest.fixture(scope="module")
def fountain_gt(tmp_path_factory):
    from tests.conftest import DATA
    root = DATA / "strecha"
    if not root.exists():
        pytest.skip(f"real data not found at {root} (expected ../shared beside the project)")
    gt_dir = tmp_path_factory.mktemp("gt")
    scene = subset(load_scene(root, "fountain-P11"), ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"])
    gt, path = build_ground_truth(scene, gt_dir, GTConfig(**SMALL))
    return root, gt_dir, scene, gt, path


def test_known_poses_triangulation_agrees_with_the_laser_scan_poses(fountain_gt):
    root, gt_dir, scene, gt, path = fountain_gt
    assert gt.method == "poses" and gt.names == list(scene.images)
    assert len(gt.points3d) > 300
    rep = gt.meta["reprojection"]
    assert rep["median_px"] < 1.0, rep  # the target
    # independent check through the loader's cameras (not COLMAP's)
    K = {n: scene.images[n].K for n in gt.names}
    R = {n: scene.images[n].R for n in gt.names}
    t = {n: scene.images[n].t for n in gt.names}
    assert np.median(reprojection_errors(gt.points3d, gt.observations, K, R, t)) < 1.0
    # points lie in front of every camera that observes them
    for n, (ids, _) in gt.observations.items():
        z = (scene.images[n].R @ gt.points3d[ids].T).T[:, 2] + scene.images[n].t[2]
        assert (z > 0).mean() > 0.99
    C = gt.covisibility
    assert np.allclose(C, C.T) and (C[np.triu_indices(4, 1)] > 0.1).all()


def test_ground_truth_round_trip_and_attach(fountain_gt):
    root, gt_dir, scene, gt, path = fountain_gt
    assert path == gt_path(scene, gt_dir) and path.is_file()
    assert str(path).startswith(str(gt_dir))  # written into the cache folder, not the data
    again = load_ground_truth(path)
    assert again.names == gt.names and np.allclose(again.points3d, gt.points3d)
    assert all(np.array_equal(again.observations[n][0], gt.observations[n][0]) for n in gt.names)
    assert {k: len(v) for k, v in again.bags.items()} == {k: len(v) for k, v in gt.bags.items()}
    fresh = subset(load_scene(root, "fountain-P11"), gt.names)
    assert all(p.covisibility is None for p in fresh.pairs)
    assert attach_ground_truth(fresh, gt_dir)
    assert fresh.observations is not None and all(p.covisibility is not None for p in fresh.pairs)
    # a scene with other images has another identity: no ground truth found
    other = subset(load_scene(root, "fountain-P11"), gt.names[:3])
    assert find_ground_truth(other, gt_dir) is None and not attach_ground_truth(other, gt_dir)
    with pytest.raises(ImtuneError, match="build-gt"):
        attach_ground_truth(other, gt_dir, required=True)
    # reused, not rebuilt, with the same settings
    gt2, path2 = build_ground_truth(fresh, gt_dir, GTConfig(**SMALL))
    assert path2 == path and gt2.meta["seconds"] == gt.meta["seconds"]


def test_corrupt_ground_truth_is_a_clear_error(fountain_gt, tmp_path):
    *_, path = fountain_gt
    bad = tmp_path / "gt.h5"
    bad.write_bytes(path.read_bytes()[:500])
    with pytest.raises(ImtuneError, match="corrupt ground-truth file"):
        load_ground_truth(bad)


def test_scene_without_poses_cannot_use_the_poses_method(sacre_coeur, tmp_path):
    scene = load_scene(sacre_coeur)
    with pytest.raises(ImtuneError, match="no known pose"):
        build_ground_truth(scene, tmp_path, GTConfig(method="poses", **SMALL))
    one = subset(load_scene(sacre_coeur), list(scene.images)[:1])
    with pytest.raises(ImtuneError, match="at least 2"):
        build_ground_truth(one, tmp_path, GTConfig(method="sfm", **SMALL))


def test_sfm_ground_truth_from_an_image_folder(sacre_coeur, tmp_path):
    scene = load_scene(sacre_coeur)
    names = list(scene.images)
    # wide-baseline phototourism images need more features than SMALL to register (4096: ~15 s)
    gt, path = build_ground_truth(scene, tmp_path, GTConfig(num_features=4096, max_image_size=1100))
    assert gt.method == "sfm" and len(gt.names) >= 8
    assert sorted(gt.names + gt.meta["dropped"]) == sorted(names)
    assert gt.meta["reprojection"]["median_px"] < 1.0
    fresh = load_scene(sacre_coeur)
    assert attach_ground_truth(fresh, tmp_path)
    assert set(fresh.images) == set(gt.names)  # unregistered images dropped
    assert all(i.K is not None and i.R is not None for i in fresh.images.values())
    R = fresh.images[gt.names[0]].R
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-6)
    json.dumps(gt.meta)  # metadata is plain JSON


def test_a_failed_sfm_is_one_line_and_leaves_no_colmap_logs(tmp_path):
    """Two images of different scenes cannot be reconstructed: `tune data build-gt` says so in one line of its own,
    with none of COLMAP's glog lines on stderr and none of glog's log files in the temporary folder."""
    import os
    import shutil
    import subprocess
    import sys
    import tempfile

    from tests.conftest import DATA, ROOT
    if not (DATA / "strecha").exists():
        pytest.skip(f"real data not found at {DATA / 'strecha'} (expected ../shared beside the project)")
    folder = tmp_path / "mixed" / "images"
    folder.mkdir(parents=True)
    shutil.copy(DATA / "strecha" / "fountain-P11" / "images" / "0000.jpg", folder / "a.jpg")
    shutil.copy(DATA / "strecha" / "entry-P10" / "images" / "0009.jpg", folder / "b.jpg")

    def glog_files():  # glog's <host>.<user>.log.<LEVEL>.<time>.<pid>, hidden when the host name starts with "."
        return {n for n in os.listdir(tempfile.gettempdir()) if ".log.INFO." in n or ".log.ERROR." in n}
    logs = glog_files()
    env = dict(os.environ, IMTUNE_CACHE=str(tmp_path / "cache"), IMTUNE_GT=str(tmp_path / "gt"))
    env.pop("IMTUNE_DEBUG", None)
    r = subprocess.run([sys.executable, "-m", "tuner", "data", "build-gt", "--data", str(tmp_path / "mixed"),
                        "--num-features", "512"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("tune: error: ")]
    assert len(errors) == 1 and "SfM registered fewer than 2 images" in errors[0], r.stderr
    assert not [ln for ln in r.stderr.splitlines() if ".cc:" in ln or ln[:1] in "EWF" and ln[1:9].isdigit()], r.stderr
    assert glog_files() <= logs


def _evaluate_and_build_gt_errors(data, gt_dir, tmp_path, capsys) -> list[str]:
    """The one error line of `tune evaluate` and of `tune data build-gt` with this --gt-dir (each must exit 2)."""
    from tuner.cli import main
    out = []
    for argv in (["evaluate", "--data", str(data), "--num-features", "512", "--jobs", "1", "--gt-dir", str(gt_dir),
                  "--cache", str(tmp_path / "cache"), "--quiet"],
                 ["data", "build-gt", "--data", str(data), "--gt-dir", str(gt_dir), "--quiet"]):
        capsys.readouterr()
        rc = main(argv)
        err = capsys.readouterr().err.strip()
        assert rc == 2 and "\n" not in err, (argv[0], err)
        out.append(err)
    return out


def test_a_file_where_the_ground_truth_folder_goes_is_one_line(tmp_path, capsys):
    """--gt-dir (or $IMTUNE_CACHE/gt) a file: every scene's ground truth read as "not built" -- `tune evaluate`
    went on without it, without a word -- and `tune data build-gt` built it only to fail writing it ("cannot write
    ...: Not a directory"). Now one line naming the file in the way, from both, before work."""
    from tests.conftest import copy_strecha_subset
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    gt_dir = tmp_path / "gt"
    gt_dir.write_text("mine")
    for err in _evaluate_and_build_gt_errors(data, gt_dir, tmp_path, capsys):
        assert f": {gt_dir} is a file where a folder should be: move it away" in err, err
        assert gt_dir.read_text() == "mine"


@pytest.mark.parametrize("cache", ["/dev/null", "file"])
def test_a_cache_that_is_no_folder_is_blamed_not_the_ground_truth(tmp_path, capsys, monkeypatch, cache):
    """IMTUNE_CACHE=/dev/null (or a file): the ground truth's default place is inside the cache, and the line said
    "ground truth /dev/null/gt/...: /dev/null is a file where a folder should be: move it away, or give another
    folder with --gt-dir": the wrong setting, and /dev/null to move away. Now it names the cache setting."""
    from tests.conftest import copy_strecha_subset
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    if cache == "file":
        cache = tmp_path / "cachefile"
        cache.write_text("mine")
    monkeypatch.setenv("IMTUNE_CACHE", str(cache))
    monkeypatch.delenv("IMTUNE_GT", raising=False)
    from tuner.cli import main
    for argv in (["evaluate", "--data", str(data), "--num-features", "512", "--jobs", "1", "--quiet"],
                 ["data", "build-gt", "--data", str(data), "--quiet"]):
        capsys.readouterr()
        rc = main(argv)
        err = capsys.readouterr().err.strip()
        assert rc == 2 and "\n" not in err, (argv[0], err)
        assert err.startswith(f"tune: error: cache folder {cache} is not a folder, and the ground truth goes in "
                              f"{cache}/gt: give a folder with --cache DIR or $IMTUNE_CACHE"), err


def test_a_camera_model_the_build_does_not_use_is_said(tmp_path, capsys):
    """`tune data build-gt --camera-model PINHOLE` on posed images (--method poses, or auto on Strecha) was accepted
    and unused, unsaid. Now --method poses refuses it in one line; auto warns naming the scenes it does not apply to."""
    from tests.conftest import copy_strecha_subset
    from tuner.cli import main
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    common = ["data", "build-gt", "--data", str(data), "--gt-dir", str(tmp_path / "gt"), "--quiet",
              "--num-features", "1024", "--camera-model", "PINHOLE"]
    capsys.readouterr()
    rc = main([*common, "--method", "poses"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err == ("tune: error: --camera-model is for --method sfm only (poses triangulates with each "
                               "image's known K): drop it, or use --method sfm"), err
    assert not (tmp_path / "gt").exists()
    rc = main(common)
    err = capsys.readouterr().err.strip()
    assert rc == 0 and err.startswith("warning: --camera-model PINHOLE is not used for fountain-P11: "), err


def test_checking_a_camera_model_keeps_sigterm_for_tune():
    """GTConfig checks its camera model against pycolmap's list: loading pycolmap there must not hand SIGTERM to
    glog's failure handler (a stack trace and death by signal instead of tune's one line and exit 143; a bare
    `import pycolmap` did that to every multiview study, whose ground truth makes a GTConfig)."""
    import subprocess
    import sys

    from tests.conftest import ROOT
    code = ("import os, signal, sys, time\n"
            "signal.signal(signal.SIGTERM, lambda *a: (print('tune handler', flush=True), os._exit(143)))\n"
            "from pipeline.data.ground_truth import GTConfig\n"
            "GTConfig(camera_model='SIMPLE_RADIAL')\n"
            "os.kill(os.getpid(), signal.SIGTERM)\n"
            "time.sleep(5)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 143 and r.stdout.strip() == "tune handler", (r.returncode, r.stdout, r.stderr[-800:])
    assert "Aborted at" not in r.stderr


def test_a_folder_where_the_ground_truth_goes_is_one_line(tmp_path, capsys):
    """A folder in the place of a scene's gt.h5 read as "no ground truth built": `tune evaluate` went on without the
    scene's co-visibility (other pairs, other numbers) without a word, and `tune data build-gt` built it (SfM: hours)
    only to fail writing it ("cannot write ...: Is a directory"). Now one line naming it from both, before work."""
    from tests.conftest import copy_strecha_subset
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    gt_dir = tmp_path / "gt"
    where = gt_path(load_scene(data, "fountain-P11"), gt_dir)
    (where / "inside").mkdir(parents=True)
    for err in _evaluate_and_build_gt_errors(data, gt_dir, tmp_path, capsys):
        assert err.startswith(f"tune: error: ground truth {where} is a folder") and "move it away" in err, err
        assert (where / "inside").is_dir() and sorted(p.name for p in where.parent.iterdir()) == ["gt.h5"]


def test_ground_truth_from_poses_of_two_images_is_refused_not_written_empty(tmp_path, capsys):
    """`tune data build-gt` on a scene of 2 posed images wrote a ground truth of 0 points (COLMAP triangulates no point
    seen in only two images): its one pair then had co-visibility 0, and `tune evaluate` found "nothing to evaluate"
    (in a data set of several scenes, that scene's pairs were left out without a word). Now one line naming the scene,
    nothing written, and the pair is still evaluated (the other scenes of a data folder are still built:
    test_a_posed_scene_of_two_images_is_one_failed_scene_the_others_built)."""
    from tests.conftest import copy_strecha_subset
    from tuner.cli import main
    data = copy_strecha_subset(tmp_path / "data", ["0004.jpg", "0005.jpg"])
    gt_dir = tmp_path / "gt"
    capsys.readouterr()
    rc = main(["data", "build-gt", "--data", str(data), "--gt-dir", str(gt_dir), "--quiet", "--num-features", "1024"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err, err
    assert err.startswith("tune: error: scene fountain-P11: ground truth from known poses needs at least 3 images, "
                          "it has 2"), err
    assert not list(gt_dir.rglob("gt.h5"))
    rc = main(["evaluate", "--data", str(data), "--gt-dir", str(gt_dir), "--num-features", "256", "--jobs", "1",
               "--cache", str(tmp_path / "cache"), "--quiet", "--json"])
    assert rc == 0 and json.loads(capsys.readouterr().out)["stereo"]["pairs"] == 1


def test_sfm_ground_truth_on_a_posed_scene_says_it_replaces_the_scenes_poses(tmp_path, capsys):
    """`tune data build-gt --method sfm` on Strecha (laser-scan poses and K) built an SfM reconstruction whose poses
    every later command then evaluated against, in place of the scene's own, unsaid. One warning, before the
    build; --method auto says nothing."""
    from tests.conftest import copy_strecha_subset
    from tuner.cli import main
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"])
    common = ["data", "build-gt", "--data", str(data), "--quiet", "--num-features", "1024", "--max-image-size", "1024"]
    capsys.readouterr()
    rc = main([*common, "--gt-dir", str(tmp_path / "gt-sfm"), "--method", "sfm"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 0 and len(err) == 1, err
    assert err[0].startswith("warning: --method sfm on fountain-P11, whose images have known poses and K"), err
    assert "in place of them" in err[0] and "--method auto keeps them" in err[0]
    rc = main([*common, "--gt-dir", str(tmp_path / "gt-auto")])
    assert rc == 0 and capsys.readouterr().err.strip() == ""
    # what the reports then name as the scene's ground truth (Scene.truth_origin)
    scene = load_scene(data, "fountain-P11")
    assert attach_ground_truth(scene, tmp_path / "gt-sfm")
    assert scene.truth_origin() == ("imtune's SfM reconstruction (tune data build-gt, pycolmap; 4 of 4 images "
                                    "registered), in place of the scene's own poses (the camera files of its Strecha-layout folder)")
    scene = load_scene(data, "fountain-P11")
    assert scene.truth_origin() == "the scene's own poses (the camera files of its Strecha-layout folder)"  # nothing built attached
    assert attach_ground_truth(scene, tmp_path / "gt-auto")
    assert scene.truth_origin() == ("the scene's own poses (the camera files of its Strecha-layout folder); co-visibility from 3D "
                                    "points triangulated with them (tune data build-gt)")


def test_a_scene_whose_sfm_fails_does_not_stop_the_others(tmp_path, capsys):
    """`tune data build-gt` on a data folder of several scenes stopped at the first scene whose SfM failed: the
    scenes after it were left unbuilt (their pairs then evaluated without co-visibility). Now every scene that can
    be built is built, each failed one is one line naming it and what to do, and the exit code is 2."""
    import shutil

    from tests.conftest import DATA, copy_strecha_subset
    from tuner.cli import main
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    bad = data / "unrelated" / "images"  # three images of three different scenes: nothing to reconstruct
    bad.mkdir(parents=True)
    for k, (scene, image) in enumerate([("fountain-P11", "0000.jpg"), ("entry-P10", "0009.jpg"),
                                        ("Herz-Jesus-P8", "0007.jpg")]):
        shutil.copy(DATA / "strecha" / scene / "images" / image, bad / f"{k}.jpg")
    gt_dir = tmp_path / "gt"
    capsys.readouterr()
    rc = main(["data", "build-gt", "--data", str(data), "--scenes", "unrelated,fountain-P11", "--gt-dir", str(gt_dir),
               "--quiet", "--num-features", "1024", "--max-image-size", "1024"])
    out, err = capsys.readouterr()
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("tune: error: scene unrelated: SfM registered fewer than 2 images"), err
    assert "leave it out with --scenes" in lines[0], err
    assert out.startswith("fountain-P11: poses: 3/3 images registered"), out  # the scene after it was built
    built = find_ground_truth(load_scene(data, "fountain-P11"), gt_dir)
    assert built is not None and load_ground_truth(built).names == ["0003.jpg", "0004.jpg", "0005.jpg"]
    assert find_ground_truth(load_scene(data, "unrelated"), gt_dir) is None
    rc = main(["data", "build-gt", "--data", str(data), "--scenes", "unrelated,fountain-P11", "--gt-dir", str(gt_dir),
               "--quiet", "--num-features", "1024", "--max-image-size", "1024", "--json"])
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert rc == 2 and report["unrelated"]["error"].startswith("scene unrelated: SfM registered fewer than 2 images")
    assert report["fountain-P11"]["registered"] == 3  # kept (reused), not rebuilt nor dropped
    assert len(err.strip().splitlines()) == 1, err


def _strecha_pairs_list(dst, names, stranger=("entry-P10", "0009.jpg")):
    """A pairs-with-GT list scene (``pairs_with_gt.txt``) of real Strecha fountain-P11 images with their laser-scan
    relative poses, plus one image of another scene paired with each of them (a plausible pose: SfM cannot register
    it). Returns the scene folder."""
    import shutil

    from pipeline.data.scene import Pair
    from tests.conftest import DATA
    root = DATA / "strecha"
    if not root.exists():
        pytest.skip(f"real data not found at {root} (expected ../shared beside the project)")
    src = load_scene(root, "fountain-P11")
    (dst / "images").mkdir(parents=True)
    lines = []

    def line(a, b, Ka, Kb, R, t):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        return " ".join([a, b, "0", "0"] + [repr(float(v)) for v in (*Ka.ravel(), *Kb.ravel(), *T.ravel())])
    for k, a in enumerate(names):
        shutil.copy(src.images[a].path, dst / "images" / a)
        for b in names[k + 1:]:
            R, t = src.relative_pose(Pair(a, b))
            lines.append(line(a, b, src.images[a].K, src.images[b].K, R, t))
    other = load_scene(root, stranger[0]).images[stranger[1]]
    shutil.copy(other.path, dst / "images" / "stranger.jpg")
    for a in names:
        lines.append(line(a, "stranger.jpg", src.images[a].K, other.K, np.eye(3), np.array([1.0, 0.0, 0.0])))
    (dst / "pairs_with_gt.txt").write_text("\n".join(lines) + "\n")
    return dst


def test_pairs_of_an_image_the_sfm_did_not_register_keep_their_listed_poses(tmp_path, capsys):
    """A pairs list whose SfM ground truth (`tune data build-gt`, no absolute poses: SfM) left an image unregistered
    had every pair with that image dropped, whatever --covisibility said, though the list gives each pair its pose
    and the SfM only the co-visibility. Now they stay on the list's poses at co-visibility 0 (the image sees none of
    the SfM's points): the default filter (0.1) leaves them out, --covisibility 0 evaluates them; one warning names the
    scene, the pairs evaluated of those listed and the image, and the JSON result keeps it in the task's notes."""
    from tuner.cli import main
    names = ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"]
    data = _strecha_pairs_list(tmp_path / "listed", names)
    gt_dir = tmp_path / "gt"
    capsys.readouterr()
    rc = main(["data", "build-gt", "--data", str(data), "--gt-dir", str(gt_dir), "--quiet", "--json",
               "--num-features", "1024", "--max-image-size", "1024"])
    out, err = capsys.readouterr()
    built = json.loads(out)["listed"]
    assert rc == 0 and built["method"] == "sfm" and built["dropped"] == ["stranger.jpg"], (out, err)
    common = ["evaluate", "--data", str(data), "--gt-dir", str(gt_dir), "--num-features", "512", "--jobs", "1",
              "--cache", str(tmp_path / "cache"), "--quiet"]
    rc = main([*common, "--json", "--pairs", "--covisibility", "0"])
    out, err = capsys.readouterr()
    res = json.loads(out)["stereo"]
    note = ("scene listed: 10 of 10 listed pairs evaluated (4 hold an image the SfM ground truth (tune data build-gt) "
            "did not register (stranger.jpg): co-visibility 0)")
    assert rc == 0 and res["pairs"] == 10, (res["pairs"], err)  # 6 before: the 4 dropped whatever --covisibility
    assert res["notes"] == [note], res.get("notes")
    assert err.strip().splitlines() == [f"warning: {note}"], err
    assert {f"{a}|stranger.jpg" for a in names} <= {r["pair"] for r in res["pair_records"]}
    origin = ("the scene's own poses (its pairs list); co-visibility from imtune's SfM (tune data build-gt, 4 of 5 "
              "images registered)")
    assert json.loads(out)["ground_truth"] == {"listed": origin}
    rc = main([*common, "--json"])  # the default co-visibility filter, 0.1
    out, err = capsys.readouterr()
    res = json.loads(out)["stereo"]
    assert rc == 0 and res["pairs"] <= 6, (res["pairs"], err)
    assert res["notes"][0].startswith(f"scene listed: {res['pairs']} of 10 listed pairs evaluated (4 hold an image "
                                      "the SfM ground truth (tune data build-gt) did not register (stranger.jpg): "
                                      "co-visibility 0; "), res["notes"]
    # the pairs' relative poses evaluated are still the list's own: SfM gave the co-visibility and the pairs kept
    rc = main(["evaluate", "--data", str(data), "--gt-dir", str(gt_dir), "--num-features", "512", "--jobs", "1",
               "--cache", str(tmp_path / "cache"), "--quiet", "--covisibility", "0"])
    out, err = capsys.readouterr()
    assert rc == 0 and f"ground truth: listed: {origin}" in out.splitlines(), out


def test_a_posed_scene_of_two_images_is_one_failed_scene_the_others_built(tmp_path, capsys):
    """`tune data build-gt` on a data folder where one posed scene has 2 images refused the whole run before building
    anything (the other scenes left without co-visibility). Now that scene is one more failed scene (its line at the
    end, exit 2) and the others are built."""
    from tests.conftest import copy_strecha_subset
    from tuner.cli import main
    data = copy_strecha_subset(tmp_path / "data", ["0004.jpg", "0005.jpg"])
    copy_strecha_subset(data, ["0000.jpg", "0001.jpg", "0002.jpg"], scene="Herz-Jesus-P8")
    gt_dir = tmp_path / "gt"
    capsys.readouterr()
    rc = main(["data", "build-gt", "--data", str(data), "--scenes", "fountain-P11,Herz-Jesus-P8", "--gt-dir",
               str(gt_dir), "--quiet", "--num-features", "1024", "--max-image-size", "1024"])
    out, err = capsys.readouterr()
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tune: error: scene fountain-P11: ground truth from known poses "
                                                   "needs at least 3 images, it has 2"), err
    assert out.startswith("Herz-Jesus-P8: poses: 3/3 images registered"), out
    built = find_ground_truth(load_scene(data, "Herz-Jesus-P8"), gt_dir)
    assert built is not None and load_ground_truth(built).names == ["0000.jpg", "0001.jpg", "0002.jpg"]
    assert find_ground_truth(load_scene(data, "fountain-P11"), gt_dir) is None


def test_an_exception_from_colmap_is_the_scenes_one_line_not_a_traceback(tmp_path):
    """An exception from pycolmap inside `tune data build-gt` (here its database cannot be written: a process whose
    files may not grow, as on a full disk; COLMAP raises "RuntimeError: No registered database factory succeeded")
    went up as a traceback that stopped the loop over scenes. Now each scene is its own one-line failure naming the
    scene, the COLMAP step and the cause; every scene is tried; exit 2."""
    import os
    import resource
    import signal
    import subprocess
    import sys

    from tests.conftest import ROOT, copy_strecha_subset
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    copy_strecha_subset(data, ["0000.jpg", "0001.jpg", "0002.jpg"], scene="Herz-Jesus-P8")
    env = dict(os.environ, IMTUNE_CACHE=str(tmp_path / "cache"), IMTUNE_GT=str(tmp_path / "gt"))
    env.pop("IMTUNE_DEBUG", None)

    def no_room():  # writes fail with EFBIG ("File too large") in place of killing the process
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1024, 1024))  # room for tempfile's probe, not a database page
    r = subprocess.run([sys.executable, "-m", "tuner", "data", "build-gt", "--data", str(data), "--scenes",
                        "fountain-P11,Herz-Jesus-P8", "--num-features", "512", "--max-image-size", "1024", "--quiet"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300, preexec_fn=no_room)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2, r.stderr
    for line, scene in zip(lines, ["fountain-P11", "Herz-Jesus-P8"]):
        assert line.startswith(f"tune: error: scene {scene}: COLMAP feature extraction failed (RuntimeError: "), line
        assert "has free space" in line, line


@pytest.mark.parametrize("kind", ["zeros", "truncated-eoi"])
def test_a_corrupt_jpeg_is_refused_before_colmap_reads_it(tmp_path, capsys, kind):
    """A JPEG whose middle is overwritten (end marker intact), or cut short with an end marker appended, passes the
    scene's marker walk; COLMAP's extraction decoded it into a damaged image without a word and `build-gt` built on
    it (the pair evaluation itself refuses such a file: test_bad_input_pipeline). `build-gt` now checks every image
    as the pair path does, before COLMAP: one line naming the file, nothing built."""
    from pipeline.data.imagefile import jpeg_end
    from tests.conftest import copy_strecha_subset
    from tuner.cli import main
    data = copy_strecha_subset(tmp_path / "data", ["0003.jpg", "0004.jpg", "0005.jpg"])
    p = data / "fountain-P11" / "images" / "0004.jpg"
    b = bytearray(p.read_bytes())
    n = len(b)
    if kind == "zeros":
        b[n // 2: n // 2 + 8192] = bytes(8192)
    else:
        b = b[: n // 2] + b"\xff\xd9"
    assert jpeg_end(bytes(b)) is not None  # the scene's own check (the end marker walk) passes
    p.write_bytes(bytes(b))
    gt_dir = tmp_path / "gt"
    capsys.readouterr()
    rc = main(["data", "build-gt", "--data", str(data), "--gt-dir", str(gt_dir), "--quiet", "--num-features", "1024",
               "--max-image-size", "1024"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err, err
    assert err.startswith(f"tune: error: scene fountain-P11: corrupt JPEG {p}: libjpeg reports"), err
    assert "replace the file or remove it from the scene" in err, err
    assert not list(gt_dir.rglob("gt.h5"))
