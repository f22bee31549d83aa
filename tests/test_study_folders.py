"""Where a study's files go (``tuner.freeze.study_dir``) and which study a frozen file belongs to: no two studies
share a folder, no study writes outside the studies folder, a frozen file copied into another study's folder is
refused, and a test never switches silently to other data than its study's."""
from __future__ import annotations

import pytest
import yaml

from pipeline.errors import ImtuneError
from tuner.freeze import MAX_DIR_NAME, load_frozen, study_data_root, study_dir


def test_safe_names_keep_their_folder(tmp_path):
    for name in ("sift-8000-degensac-stereo", "findings-2-tuned-sift-2048-degensac-p12", "a_b", "x.y+z"):
        assert study_dir(tmp_path, name) == tmp_path / name


def test_no_two_studies_share_a_folder_and_none_leaves_the_studies_folder(tmp_path):
    names = ["a/b", "a_b", "a b", "a\\b", "a_b_", "..", ".", "", "../x", "/etc", "name with spaces ✓",
             "name with spaces ✗", "é", "e", "x" * 300, "x" * 301, "." * 5]
    dirs = [study_dir(tmp_path, n) for n in names]
    assert len(set(dirs)) == len(names), dict(zip(names, dirs))
    for n, d in zip(names, dirs):
        assert d.parent == tmp_path, (n, d)  # one level below, whatever the name
        assert d.name not in ("", ".", "..") and "/" not in d.name and len(d.name) <= MAX_DIR_NAME, (n, d)
    # a long name gets a folder the file system accepts: writing in it works
    long_dir = study_dir(tmp_path, "x" * 300)
    long_dir.mkdir()
    (long_dir / "frozen.yaml").write_text("x")


def _frozen(path, study, root):
    path.mkdir(parents=True, exist_ok=True)
    (path / "frozen.yaml").write_text(yaml.safe_dump({
        "study": study, "trial": 3, "config": {"feature": {"name": "sift"}},
        "data": {"root": str(root), "test_scenes": ["entry-P10"]}}))


def test_a_frozen_file_of_another_study_is_refused(tmp_path, capsys):
    from tuner.cli import main
    sdir = tmp_path / "studies"
    _frozen(study_dir(sdir, "copy"), "orig", tmp_path)
    with pytest.raises(ImtuneError, match=r"holds the frozen settings of study 'orig', not 'copy'"):
        load_frozen(sdir, "copy")
    capsys.readouterr()
    rc = main(["test", "--study", "copy", "--studies-dir", str(sdir), "--reference", "none", "--runs", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert "'orig', not 'copy'" in err and "tune test --study orig" in err and "Traceback" not in err
    assert not (study_dir(sdir, "orig") / "test.json").exists() and not (study_dir(sdir, "copy") / "test.json").exists()


def test_a_test_never_switches_silently_to_other_data(tmp_path, capsys):
    from tuner.cli import main
    sdir = tmp_path / "studies"
    gone = tmp_path / "moved-away"
    _frozen(study_dir(sdir, "s1"), "s1", gone)
    frozen = load_frozen(sdir, "s1")
    with pytest.raises(ImtuneError, match="does not exist .*give --data DIR"):
        study_data_root(frozen)
    assert study_data_root(frozen, tmp_path) == tmp_path  # --data wins
    (gone).mkdir()
    assert study_data_root(frozen) == gone  # the data it was tuned on
    gone.rmdir()
    capsys.readouterr()
    rc = main(["test", "--study", "s1", "--studies-dir", str(sdir), "--reference", "none", "--runs", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and str(gone) in err and "--data" in err, err
    assert not (study_dir(sdir, "s1") / "test.json").exists()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from tests.conftest import copy_strecha_subset
    return copy_strecha_subset(tmp_path_factory.mktemp("study-folders-data"), ["0003.jpg", "0004.jpg", "0005.jpg"])


@pytest.mark.parametrize("cmd", ["run", "test"])
@pytest.mark.parametrize("what", ["the study folder is a file", "frozen.yaml is a folder", "test.json is a folder"])
def test_a_study_file_in_the_way_is_one_line_before_any_work(what, cmd, tiny, tmp_path, capsys):
    """`tune run` ran every trial (and `tune test` the whole test) before finding that its study folder was a file
    ("cannot write .../frozen.yaml: File exists") or its frozen.yaml / test.json a folder ("... Is a directory").
    Now one line naming the culprit before any trial or test run; what is in the way is left alone."""
    from tuner.cli import main
    sdir = tmp_path / "studies"
    d = sdir / "s"
    if what == "the study folder is a file":
        sdir.mkdir()
        d.write_text("mine")
        needle = f"study folder {d} is not a folder (a file is in the way"
    else:
        _frozen(d, "s", tiny)
        name = what.split()[0]
        if name == "frozen.yaml":
            (d / name).unlink()
        (d / name / "inside").mkdir(parents=True)
        needle = f"{d / name} is a folder where study 's' writes its {name}: move it away"
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    argv = (["run", "--data", str(tiny), "--num-features", "512", "--n-trials", "2", "--calibration-pairs", "2",
             "--no-test"] if cmd == "run" else ["test", "--data", str(tiny), "--scenes", "fountain-P11", "--runs", "1"])
    capsys.readouterr()
    rc = main(argv + ["--study", "s", "--studies-dir", str(sdir), "--storage", storage, "--cache",
                      str(tmp_path / "cache"), "--jobs", "1", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and err.startswith("tune: error: ") and needle in err, err
    assert not (tmp_path / "optuna.db").exists() and not (tmp_path / "cache").exists()  # no trial, no test run
    assert d.read_text() == "mine" if d.is_file() else (d / what.split()[0] / "inside").is_dir()
