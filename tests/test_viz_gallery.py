"""`tune viz`: gallery updates, pair selection, config files, and the command end to end on fountain-P11
(1024 SIFT; skipped without ../shared/data) — a study's gallery linked from its report, a comparison, and
bad input as one line."""
import json
import math

import numpy as np
import pytest
import yaml

from pipeline.data.scene import ImageInfo, Pair, Scene
from pipeline.errors import ImtuneError
from pipeline.viz.gallery import GalleryEntry, link_gallery, read_manifest, write_gallery
from pipeline.viz.select import disagreements, find_pair, select_records
from tuner.cli import main


def _png(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n")  # the gallery only checks that the file exists
    return path


def test_gallery_is_updated_not_overwritten(tmp_path):
    html = tmp_path / "gallery.html"
    for n in ("a", "b", "c", "d"):
        _png(tmp_path / "viz" / f"{n}.png")
    write_gallery(html, [GalleryEntry("viz/a.png", "worst", "A", scope="c1"),
                         GalleryEntry("viz/b.png", "compare", "B", scope="c1|c2")], title="t")
    write_gallery(html, [GalleryEntry("viz/c.png", "worst", "C", scope="c2")], replace_sections=("worst",), scope="c2")
    names = {e.png for e in read_manifest(html)}
    assert names == {"viz/a.png", "viz/b.png", "viz/c.png"}  # another configuration's worst pairs stay
    write_gallery(html, [GalleryEntry("viz/d.png", "worst", "D", scope="c1")], replace_sections=("worst",), scope="c1")
    names = {e.png for e in read_manifest(html)}
    assert names == {"viz/b.png", "viz/c.png", "viz/d.png"}  # c1's previous selection replaced
    (tmp_path / "viz" / "b.png").unlink()
    write_gallery(html, [GalleryEntry("viz/d.png", "worst", "D again", scope="c1")])
    ents = read_manifest(html)
    assert {e.png for e in ents} == {"viz/c.png", "viz/d.png"}  # missing file dropped, same PNG replaced
    text = html.read_text()
    assert "viz/d.png" in text and "D again" in text and "viz/b.png" not in text
    assert "<h2>" in text and "green" in text  # sections and the colour explanation


def test_link_gallery_is_idempotent(tmp_path):
    rep = tmp_path / "report.html"
    assert not link_gallery(rep)
    rep.write_text("<html><body><h1>r</h1></body></html>")
    assert link_gallery(rep) and link_gallery(rep)
    assert rep.read_text().count("gallery.html") == 1


def _scene():
    imgs = {n: ImageInfo(n, None, K=np.eye(3), R=np.eye(3), t=np.zeros(3)) for n in ("a", "b", "c")}
    return Scene("s1", None, imgs, pairs=[Pair("a", "b", R=np.eye(3), t=np.array([1.0, 0, 0])), Pair("a", "c")])


def test_find_pair_and_bad_pairs():
    sc = _scene()
    other = Scene("s2", None, {n: ImageInfo(n, None) for n in ("a", "b")}, pairs=[Pair("a", "b")])
    assert find_pair([sc], "a|b")[1] is sc.pairs[0]
    s, p = find_pair([sc], "b|a")  # reversed: the ground truth is reversed too
    assert (p.i, p.j) == ("b", "a") and np.allclose(p.t, [-1.0, 0, 0])
    assert find_pair([sc], "b|c")[1].key == "b|c"  # not listed, but both images have poses
    assert find_pair([sc, other], "s1:a|b")[0] is sc
    for bad, words in (("a|z", "not in s1"), ("a-b", "expected"), ("x:a|b", "not loaded"), ("a|a", "two different")):
        with pytest.raises(ImtuneError, match=words):
            find_pair([sc], bad)
    with pytest.raises(ImtuneError, match="several scenes"):
        find_pair([sc, other], "a|b")


def test_select_worst_best_random_without_repeats():
    recs = [{"scene": "s", "pair": f"p{k}", "err": e, "NI": k} for k, e in
            enumerate([0.5, math.inf, 3.0, 0.1, 12.0, math.inf, 1.0, 2.0])]
    sel = select_records(recs, worst=2, best=2, random=3, seed=0)
    reasons = [r for _, r in sel]
    assert reasons == ["worst", "worst", "best", "best", "random", "random", "random"]
    assert [r["pair"] for r, _ in sel[:4]] == ["p1", "p5", "p3", "p0"]  # inf first (fewest inliers first)
    assert len({r["pair"] for r, _ in sel}) == 7
    a = [{"scene": "s", "pair": "x", "err": 1.0, "NI": 50}, {"scene": "s", "pair": "y", "err": 2.0, "NI": 50}]
    b = [{"scene": "s", "pair": "x", "err": math.inf, "NI": 3}, {"scene": "s", "pair": "y", "err": 2.5, "NI": 40}]
    assert disagreements(a, b, 1) == [("s", "x")]


def test_config_files(tmp_path):
    from pipeline.config_files import load_config_file
    flat = tmp_path / "flat.yaml"
    flat.write_text("feature: sift\nnum_features: 1024\nratio: 0.8\nransac: cv-ransac\nthreshold: 2\n")
    c = load_config_file(flat).conf
    assert (c.feature.num_features, c.matching.ratio, c.geometry.ransac, c.geometry.threshold) == (1024, 0.8, "cv-ransac", 2.0)
    nested = tmp_path / "nested.yaml"
    nested.write_text(yaml.safe_dump({"feature": {"name": "sift", "num_features": 2048},
                                      "geometry": {"ransac": "degensac", "threshold": 0.7}}))
    c = load_config_file(nested).conf
    assert c.feature.num_features == 2048 and c.geometry.threshold == 0.7
    imc = tmp_path / "method.json"
    imc.write_text(json.dumps([{"config_common": {"json_label": "sift-def", "descriptor": "sift", "num_keypoints": 2048},
                                "config_phototourism_stereo": {
                                    "matcher": {"method": "nn", "filtering": {"type": "snn_ratio_pairwise", "threshold": 0.85},
                                                "symmetric": {"enabled": True, "reduce": "both"}},
                                    "geom": {"method": "cmp-degensac-f", "threshold": 0.5, "max_iter": 100000}}}]))
    s = load_config_file(imc)
    assert s.conf.matching.ratio == 0.85 and s.conf.geometry.max_iters == 100000 and s.label.startswith("sift-def")
    bad = tmp_path / "bad.yaml"
    bad.write_text("feature: [unclosed\n")
    with pytest.raises(ImtuneError, match="invalid YAML"):
        load_config_file(bad)
    bad.write_text("colour: blue\n")
    with pytest.raises(ImtuneError, match="unknown option"):
        load_config_file(bad)


# ------------------------------------------------------------------------------------------------ real data

@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("viz-cache"))


BASE = ["--feature", "sift", "--num-features", "1024", "--quiet"]


def _frozen(strecha, scenes):
    return {"study": "s1", "trial": 3, "config": {
        "feature": {"name": "sift", "num_features": 1024}, "matching": {"ratio": 0.85, "strategy": "both"},
        "geometry": {"ransac": "degensac", "threshold": 0.5, "max_iters": 20000, "seed": 0}},
        "data": {"root": str(strecha), "val_scenes": scenes, "test_scenes": scenes, "min_covisibility": 0.1}}


def test_viz_study_gallery_linked_from_report(strecha, shared_cache, tmp_path, capsys):
    sdir = tmp_path / "studies"
    (sdir / "s1").mkdir(parents=True)
    (sdir / "s1" / "frozen.yaml").write_text(yaml.safe_dump(_frozen(strecha, ["fountain-P11"])))
    (sdir / "s1" / "report.html").write_text("<html><body><h1>report</h1></body></html>")
    rc = main(["viz", "--study", "s1", "--studies-dir", str(sdir), "--cache", shared_cache, "--worst", "1",
               "--best", "1", "--random", "1", "--width", "1000", "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    figs = out["figures"]
    assert [f["section"] for f in figs] == ["worst", "best", "random"]
    assert all(f["scene"] == "fountain-P11" and f["error_kind"] == "epipolar" for f in figs)
    best = figs[1]
    assert best["failure"] is None and best["stats"]["median"] < 1.0
    import cv2
    for f in figs:
        img = cv2.imread(f["png"])
        assert img is not None and img.shape[1] == 1000
        assert f["png"].startswith(str(sdir / "s1" / "viz"))
    gallery = sdir / "s1" / "gallery.html"
    assert out["gallery"] == str(gallery)
    text = gallery.read_text()
    assert all(f["png"].split("/")[-1] in text for f in figs) and "report.html" in text
    assert "gallery.html" in (sdir / "s1" / "report.html").read_text()
    # a chosen pair is added to the same gallery; the earlier figures stay
    rc = main(["viz", "--study", "s1", "--studies-dir", str(sdir), "--cache", shared_cache, "--pair", "0000.jpg",
               "0001.jpg", "--quiet"])
    assert rc == 0
    secs = [e.section for e in read_manifest(gallery)]
    assert sorted(secs) == ["best", "chosen", "random", "worst"]


def test_viz_compare_two_config_files(strecha, shared_cache, tmp_path, capsys):
    a = tmp_path / "a.yaml"
    a.write_text("feature: sift\nnum_features: 1024\nratio: 1.0\nransac: cv-ransac\nthreshold: 3\nmax_iters: 1000\n")
    b = tmp_path / "b.yaml"
    b.write_text(yaml.safe_dump(_frozen(strecha, ["fountain-P11"])))
    rc = main(["viz", "--compare", str(a), str(b), "--data", str(strecha), "--scenes", "fountain-P11", "--pairs",
               "0000.jpg|0003.jpg", "--cache", shared_cache, "--out", str(tmp_path / "cmp"), "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    (fig,) = out["figures"]
    assert fig["section"] == "compare" and len(fig["panels"]) == 2
    assert fig["panels"][0]["label"].startswith("a:") and fig["panels"][1]["label"].startswith("s1")
    import cv2
    img = cv2.imread(fig["png"])
    assert img is not None and 1500 <= img.shape[1] <= 1600
    assert (tmp_path / "cmp" / "gallery.html").is_file()


def test_viz_bad_input_is_one_line(strecha, shared_cache, tmp_path, capsys):
    sdir = tmp_path / "studies"
    (sdir / "nofrozen").mkdir(parents=True)
    (sdir / "broken").mkdir()
    (sdir / "broken" / "frozen.yaml").write_text("study: broken\n")
    cases = [
        (["--study", "nofrozen", "--studies-dir", str(sdir)], "no frozen settings"),
        (["--study", "broken", "--studies-dir", str(sdir)], "not a frozen-settings file"),
        (["--compare", "nothing", str(tmp_path / "x.yaml"), "--studies-dir", str(sdir)], "neither a config file"),
        (BASE + ["--data", str(strecha), "--scenes", "fountain-P11", "--pairs", "0000.jpg|9999.jpg",
                 "--cache", shared_cache, "--out", str(tmp_path / "o")], "not in fountain-P11"),
        (BASE + ["--data", str(strecha), "--scenes", "fountain-P11", "--task", "multiview", "--gt-dir",
                 str(tmp_path / "no-gt"), "--cache", shared_cache, "--out", str(tmp_path / "o")], "build-gt"),
    ]
    for args, words in cases:
        capsys.readouterr()
        rc = main(["viz", *args])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and words in err and "\n" not in err, (args, err)


def _tune(*args):
    """`python -m tuner ARGS` in a real process (pipeline warnings go to stderr through logging's last resort)."""
    import os
    import subprocess
    import sys

    from tests.conftest import ROOT
    env = {k: v for k, v in os.environ.items() if k != "IMTUNE_DEBUG"}
    return subprocess.run([sys.executable, "-m", "tuner", *map(str, args)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300, stdin=subprocess.DEVNULL)


@pytest.fixture(scope="module")
def data3(tmp_path_factory):
    from tests.conftest import copy_strecha_subset
    return copy_strecha_subset(tmp_path_factory.mktemp("viz-data3"), ["0003.jpg", "0004.jpg", "0005.jpg"])


@pytest.mark.parametrize("damage", ["cut-short", "a-json-list"])
def test_a_damaged_gallery_manifest_is_kept_aside_and_said(damage, data3, shared_cache, tmp_path):
    """A gallery.json cut short (or hand-edited into a list): the next `tune viz` silently rewrote the gallery with
    its own figures only, every earlier entry gone and the damaged manifest overwritten. Now one warning line naming
    it, the damaged file kept beside as gallery.json.damaged, and the run goes on."""
    out = tmp_path / "viz"
    argv = ["viz", *BASE, "--data", data3, "--scenes", "fountain-P11", "--cache", shared_cache, "--out", out]
    r = _tune(*argv, "--pairs", "0003.jpg|0004.jpg")
    assert r.returncode == 0, r.stderr[-2000:]
    manifest = out / "gallery.json"
    assert len(read_manifest(out / "gallery.html")) == 1
    bad = manifest.read_bytes()[:200] if damage == "cut-short" else b"[1, 2]\n"
    manifest.write_bytes(bad)
    r = _tune(*argv, "--pairs", "0004.jpg|0005.jpg")
    assert r.returncode == 0, r.stderr[-2000:]
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith(f"warning: gallery manifest {manifest} cannot be read"), err
    assert f"kept as {manifest}.damaged" in err[0]
    assert (out / "gallery.json.damaged").read_bytes() == bad
    (entry,) = read_manifest(out / "gallery.html")  # the gallery restarts from this run's figure
    assert "fountain-P11_0004_0005_" in entry.png


def test_a_gallery_manifest_that_is_a_folder_is_one_line_before_drawing(data3, shared_cache, tmp_path, capsys):
    """A folder named gallery.json (or gallery.html, the gallery in the figures folder) was found after every figure
    was drawn: "cannot write .../gallery.json: Is a directory"."""
    out = tmp_path / "viz"
    for name in ("gallery.json", "gallery.html"):
        (out / name / "inside").mkdir(parents=True)
        capsys.readouterr()
        rc = main(["viz", *BASE, "--data", str(data3), "--scenes", "fountain-P11", "--cache", shared_cache,
                   "--out", str(out)])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and "\n" not in err and f"{out / name} is a folder" in err, err
        assert (out / name / "inside").is_dir() and not list(out.glob("*.png"))
        (out / name / "inside").rmdir()
        (out / name).rmdir()


def test_pairs_whose_image_names_end_alike_get_their_own_figures(scannet, tmp_path, monkeypatch, capsys):
    """A pairs list naming images in folders (ScanNet's scene0707_00/color/15.jpg, scene0708_00/color/15.jpg): the
    figure's name took the file names only, so the worst and the best pair were one PNG, the first overwritten and
    the gallery showing the best pair's figure as the worst. Now folders are in the name (flat names unchanged), and
    names still alike get -2, -3."""
    import shutil
    monkeypatch.setenv("IMTUNE_CACHE", str(tmp_path / "cache"))
    rows = (scannet / "pairs_with_gt.txt").read_text().splitlines()[:2]
    scene = tmp_path / "data" / "sc"
    lines = []
    for folder, row in zip("ab", rows):
        n1, n2, rest = row.split(maxsplit=2)
        (scene / "images" / folder).mkdir(parents=True)
        shutil.copy(scannet / "images" / n1, scene / "images" / folder / "1.jpg")
        shutil.copy(scannet / "images" / n2, scene / "images" / folder / "2.jpg")
        lines.append(f"{folder}/1.jpg {folder}/2.jpg {rest}")
    (scene / "pairs_with_gt.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "figs"
    assert main(["viz", "--data", str(tmp_path / "data"), "--num-features", "256", "--worst", "1", "--best", "1",
                 "--random", "0", "--out", str(out), "--quiet", "--json"]) == 0
    figs = json.loads(capsys.readouterr().out)["figures"]
    assert sorted(f["pair"] for f in figs) == ["a/1.jpg|a/2.jpg", "b/1.jpg|b/2.jpg"]
    assert len({f["png"] for f in figs}) == 2 and len(list(out.glob("*.png"))) == 2
    from pipeline.viz.batch import _png_path
    sc = Scene("s", tmp_path, {})
    used = {}
    names = [_png_path(out, "", sc, Pair(i, "x.jpg"), "h", used).name for i in ("1.jpg", "1.png", "1.jpg")]
    assert names == ["s_1_x_h.png", "s_1_x_h-2.png", "s_1_x_h.png"]
