"""pipeline.data.locate: which data folder each rule picks, and the main job's download when none is found.

Downloads come from a local HTTP server on 127.0.0.1 (tests/test_data_download.py's fixture), never the internet.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from pipeline.data import download as dl
from pipeline.data import locate as lc
from pipeline.errors import ImtuneError
from tests.test_data_download import SIX_SCENES, STRECHA_PREFIX, _closed_port_url, _mirror_strecha, server  # noqa: F401


def _set(root: Path, name: str = "strecha") -> Path:
    """A minimal non-empty data set folder ``root/name`` (locate does not parse it)."""
    (root / name / "fountain-P11" / "images").mkdir(parents=True)
    return root / name


@pytest.fixture
def env(tmp_path, monkeypatch):
    """A clean environment: HOME in tmp, no IMTUNE_* variables, no ../shared, cwd without imtune.yaml."""
    for k in (lc.ENV_DATA, lc.ENV_DATA_HOME, "XDG_DATA_HOME", dl.ENV_BASE):
        monkeypatch.delenv(k, raising=False)
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv(lc.ENV_SHARED, str(tmp_path / "no-shared"))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    if (lc.PROJECT_ROOT / lc.CONFIG_FILE).is_file():
        pytest.skip(f"{lc.PROJECT_ROOT / lc.CONFIG_FILE} exists and would take part")
    return tmp_path


def _default_home(home: Path) -> Path:
    try:
        import platformdirs
    except ImportError:
        return home / ".local" / "share" / "imtune" / "data"
    return Path(platformdirs.user_data_dir("imtune", appauthor=False)) / "data"


def test_download_home(env, monkeypatch):
    home = env / "home"
    assert lc.download_home()[0] == _default_home(home)
    monkeypatch.setenv("XDG_DATA_HOME", str(env / "xdg"))
    try:
        import platformdirs  # noqa: F401
    except ImportError:
        assert lc.download_home() == (env / "xdg" / "imtune" / "data", "$XDG_DATA_HOME/imtune/data")
    monkeypatch.setenv(lc.ENV_DATA_HOME, str(env / "dh"))
    assert lc.download_home() == ((env / "dh").resolve(), "$IMTUNE_DATA_HOME")


def test_precedence_each_rule_beats_the_next(env, monkeypatch):
    shared = _set(env / "shared" / "data")
    monkeypatch.setenv(lc.ENV_SHARED, str(env / "shared"))
    assert lc.locate() == lc.Located(shared.resolve(), "../shared/data", "$IMTUNE_SHARED/data")

    downloaded = _set(env / "dh")
    monkeypatch.setenv(lc.ENV_DATA_HOME, str(env / "dh"))
    assert lc.locate() == lc.Located(downloaded.resolve(), "download location", "$IMTUNE_DATA_HOME")

    yaml_set = _set(env / "work" / "mine")
    (env / "work" / "imtune.yaml").write_text("data: mine/strecha\n")  # relative to the yaml file
    loc = lc.locate()
    assert (loc.path, loc.rule, loc.detail) == (yaml_set.resolve(), "imtune.yaml", str(env / "work" / "imtune.yaml"))

    env_set = _set(env / "env")
    monkeypatch.setenv(lc.ENV_DATA, str(env_set))
    assert lc.locate() == lc.Located(env_set.resolve(), "IMTUNE_DATA")

    cli_set = _set(env / "cli")
    assert lc.locate(str(cli_set)) == lc.Located(cli_set.resolve(), "--data")
    assert lc.resolve_data(str(cli_set)) == cli_set.resolve()


def test_named_folder_that_does_not_exist_is_an_error_not_a_fall_through(env, monkeypatch):
    _set(env / "dh")
    monkeypatch.setenv(lc.ENV_DATA_HOME, str(env / "dh"))
    with pytest.raises(ImtuneError, match=r"data folder .*nope \(from --data\) does not exist"):
        lc.locate(str(env / "nope"))
    (env / "a-file.txt").write_text("x")  # a file where a folder is named: said so, not "does not exist"
    with pytest.raises(ImtuneError, match=r"a-file.txt \(from --data\) is a file, not a folder"):
        lc.locate(str(env / "a-file.txt"))
    monkeypatch.setenv(lc.ENV_DATA, str(env / "gone"))
    with pytest.raises(ImtuneError, match=r"gone \(from IMTUNE_DATA\) does not exist"):
        lc.locate()
    monkeypatch.delenv(lc.ENV_DATA)
    (env / "work" / "imtune.yaml").write_text("data: missing\n")
    with pytest.raises(ImtuneError, match=r"missing \(from imtune.yaml in .*imtune.yaml\) does not exist"):
        lc.locate()
    (env / "work" / "imtune.yaml").write_text("data: [unclosed\n")
    with pytest.raises(ImtuneError, match="invalid YAML"):
        lc.locate()
    _set(env / "work" / "mine")  # `data:` twice: PyYAML kept the last without a word
    (env / "work" / "imtune.yaml").write_text("data: mine/strecha\nscenes: [a]\ndata: elsewhere\n")
    with pytest.raises(ImtuneError, match=r"imtune.yaml: key 'data' is given twice \(lines 1 and 3\)"):
        lc.locate()



@pytest.mark.parametrize("text,needle", [
    ("dta: mine/strecha\n", "unknown key 'dta' (expected data"),
    ("data:\n", "data must be the path of the data folder, got None"),
    ("data: ''\n", "data must be the path of the data folder, got ''"),
    ("data: [mine, strecha]\n", "data must be the path of the data folder, got ['mine', 'strecha']"),
])
def test_imtune_yaml_key_misspelt_or_data_not_a_path_is_an_error(env, monkeypatch, text, needle):
    """A misspelt key or an empty data: was skipped for the next rule (the download location here), and a list was
    "data folder .../['mine', 'strecha'] does not exist"."""
    _set(env / "dh")
    monkeypatch.setenv(lc.ENV_DATA_HOME, str(env / "dh"))
    (env / "work" / "imtune.yaml").write_text(text)
    with pytest.raises(ImtuneError) as e:
        lc.locate()
    assert str(e.value).startswith(f"{env / 'work' / 'imtune.yaml'}: ") and needle in str(e.value), str(e.value)

def test_empty_download_folder_is_skipped(env, monkeypatch):
    (env / "dh" / "strecha").mkdir(parents=True)  # what an old interrupted download left
    monkeypatch.setenv(lc.ENV_DATA_HOME, str(env / "dh"))
    shared = _set(env / "shared" / "data")
    monkeypatch.setenv(lc.ENV_SHARED, str(env / "shared"))
    assert lc.locate().path == shared.resolve()


def test_nothing_found_names_where_it_looked_and_the_fix(env):
    with pytest.raises(lc.DataNotFound) as e:
        lc.resolve_data()
    msg = str(e.value)
    assert "\n" not in msg
    assert str(_default_home(env / "home") / "strecha") in msg and str(env / "no-shared" / "data" / "strecha") in msg
    assert "`tune data download strecha`" in msg and "--data DIR" in msg


def test_main_job_downloads_the_default_set_then_finds_it(env, server, monkeypatch, capsys):
    mirror, base = server
    _mirror_strecha(mirror)
    monkeypatch.setattr(dl, "STRECHA_LONG_SIDE", 32)
    monkeypatch.setenv(dl.ENV_BASE, base)
    home = _default_home(env / "home")
    root = lc.resolve_data(download=True, quiet=True)
    assert root == home / "strecha"
    assert sorted(p.name for p in root.iterdir()) == sorted(SIX_SCENES)
    err = capsys.readouterr().err
    assert "downloading the default data set strecha (206 files from 127.0.0.1" in err
    # from now on every command finds it by the download-location rule, with no network
    monkeypatch.setenv(dl.ENV_BASE, _closed_port_url())
    loc = lc.locate()
    assert (loc.path, loc.rule) == (root, "download location")
    assert lc.resolve_data(download=True) == root


def test_main_job_offline_one_line_and_nothing_left(env, monkeypatch, capsys):
    monkeypatch.setenv(dl.ENV_BASE, _closed_port_url())
    with pytest.raises(lc.DataNotFound) as e:
        lc.resolve_data(download=True, quiet=True)
    msg = str(e.value)
    assert "\n" not in msg and "downloading it failed" in msg and "Connection refused" in msg
    assert "`tune data download strecha`" in msg and "--data DIR" in msg
    assert capsys.readouterr().err == ""  # no "downloading ..." announcement when nothing could be fetched
    assert not (env / "home" / ".local").exists()
    assert not [p for p in env.rglob("*") if "strecha" in p.name]


def test_download_default_dest_is_the_download_location(env, server, monkeypatch):
    mirror, base = server
    _mirror_strecha(mirror)
    monkeypatch.setattr(dl, "STRECHA_LONG_SIDE", 32)
    monkeypatch.setenv(lc.ENV_DATA_HOME, str(env / "dh"))
    out = dl.download("strecha", base_url=base, quiet=True)
    assert out == (env / "dh" / "strecha").resolve()
    assert lc.locate().path == out
    assert os.listdir(env / "dh") == ["strecha"]
