"""download(): served from a local HTTP server on 127.0.0.1 (never the internet)."""
from __future__ import annotations

import base64
import functools
import hashlib
import http.server
import io
import socket
import tarfile
import threading
import urllib.parse
import zipfile
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from pipeline.data import default_splits, load_imc_pt2020, load_strecha
from pipeline.data import download as dl
from pipeline.data.strecha import read_camera, write_camera
from pipeline.errors import ImtuneError

STRECHA_PREFIX = "openMVG/SfM_quality_evaluation/master/Benchmarking_Camera_Calibration_2008"


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture
def server(tmp_path):
    """(mirror folder, base URL) of an HTTP server on an ephemeral loopback port."""
    root = tmp_path / "mirror"
    root.mkdir()
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(root)))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield root, f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


def _closed_port_url() -> str:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return f"http://127.0.0.1:{port}"


#: the six scenes of Strecha et al. 2008 and their image counts, as ../shared/data README lists them (the upstream
#: folder Benchmarking_Camera_Calibration_2008): written out here, not read from the code under test
SIX_SCENES = {"fountain-P11": 11, "Herz-Jesus-P8": 8, "entry-P10": 10, "castle-P19": 19, "castle-P30": 30,
              "Herz-Jesus-P25": 25}

K_FULL = np.array([[80.0, 0.4, 31.7], [0, 81.0, 23.9], [0, 0, 1]])


def _mirror_strecha(root: Path):
    rng = np.random.default_rng(0)
    for scene, n in SIX_SCENES.items():  # the upstream layout: a download that fetches fewer misses some
        for k in range(n):
            base = root / STRECHA_PREFIX / scene
            (base / "images").mkdir(parents=True, exist_ok=True)
            (base / "gt_dense_cameras").mkdir(exist_ok=True)
            cv2.imwrite(str(base / "images" / f"{k:04d}.jpg"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
            write_camera(base / "gt_dense_cameras" / f"{k:04d}.jpg.camera", K_FULL, [0, 0, 0], np.eye(3),
                         [k, 1.0, 2.0], (64, 48))


def _no_leftovers(dest: Path):
    assert not dest.exists() or not [p for p in dest.iterdir() if p.name.startswith(".")]


def test_strecha_download_layout_and_downsampling(server, tmp_path, monkeypatch):
    mirror, base = server
    _mirror_strecha(mirror)
    monkeypatch.setattr(dl, "STRECHA_LONG_SIDE", 32)  # the toy 64x48 images stand for the published 3072x2048
    dest = tmp_path / "data"
    out = dl.download("strecha", dest, base_url=base, quiet=True)
    assert out == dest / "strecha"
    assert sorted(p.name for p in out.iterdir()) == sorted(SIX_SCENES)  # all six scenes of the upstream folder
    for scene, n in SIX_SCENES.items():
        assert len(list((out / scene / "images").glob("*.jpg"))) == n
        assert len(list((out / scene / "gt_dense_cameras").glob("*.camera"))) == n
    img = cv2.imread(str(out / "fountain-P11" / "images" / "0003.jpg"))
    assert img.shape == (24, 32, 3)
    cam = read_camera(out / "fountain-P11" / "gt_dense_cameras" / "0003.jpg.camera")
    assert cam["size"] == (32, 24)
    np.testing.assert_allclose(cam["K"], [[40.0, 0.2, 31.7 / 2 - 0.25], [0, 40.5, 23.9 / 2 - 0.25], [0, 0, 1]])
    np.testing.assert_allclose(cam["C"], [3, 1, 2])
    np.testing.assert_allclose(cam["R"], np.eye(3))
    scene = load_strecha(out, "fountain-P11")
    assert len(scene.images) == 11 and len(scene.pairs) == 55
    assert default_splits(out) == {"val": ["fountain-P11", "Herz-Jesus-P8", "Herz-Jesus-P25"],
                                   "test": ["castle-P19", "castle-P30", "entry-P10"]}
    _no_leftovers(dest)
    # already there: no network needed
    assert dl.download("strecha", dest, base_url=_closed_port_url(), quiet=True) == out


def test_strecha_already_in_shared_layout_is_kept(server, tmp_path, monkeypatch):
    mirror, base = server
    _mirror_strecha(mirror)
    monkeypatch.setattr(dl, "STRECHA_LONG_SIDE", 64)  # 64x48 = the target layout: no second halving
    out = dl.download("strecha", tmp_path / "data", base_url=base, quiet=True)
    for scene in dl.STRECHA_SCENES:
        for f in ("images/0001.jpg", "gt_dense_cameras/0001.jpg.camera"):
            assert (out / scene / f).read_bytes() == (mirror / STRECHA_PREFIX / scene / f).read_bytes()


def test_interrupt_leaves_nothing(server, tmp_path):
    mirror, base = server
    _mirror_strecha(mirror)
    dest = tmp_path / "a" / "b"

    def interrupt():
        raise KeyboardInterrupt  # what Ctrl-C raises in the main thread, after the first file arrived

    with pytest.raises(KeyboardInterrupt):
        dl.download("strecha", dest, base_url=base, quiet=True, on_connected=interrupt)
    assert not (tmp_path / "a").exists()


def test_env_var_base_and_force(server, tmp_path, monkeypatch):
    mirror, base = server
    _mirror_strecha(mirror)
    dest = tmp_path / "data"
    (dest / "strecha").mkdir(parents=True)
    (dest / "strecha" / "stale.txt").write_text("old")
    monkeypatch.setenv(dl.ENV_BASE, base)
    out = dl.download("strecha", dest, force=True, quiet=True)
    assert not (out / "stale.txt").exists() and (out / "entry-P10" / "images" / "0009.jpg").is_file()
    _no_leftovers(dest)


def test_network_errors_are_one_line_and_leave_nothing(server, tmp_path):
    mirror, base = server
    dest = tmp_path / "data"
    with pytest.raises(ImtuneError, match="download failed: .*0000.jpg: HTTP 404") as e:
        dl.download("strecha", dest, base_url=base, quiet=True)
    assert "\n" not in str(e.value)
    assert not dest.exists()  # the destination this call created goes too: nothing half-made
    (dest / "keep").mkdir(parents=True)  # a destination that exists (with content) is left as it was
    with pytest.raises(ImtuneError, match="download failed: http://127.0.0.1") as e:
        dl.download("sacre_coeur", dest, base_url=_closed_port_url(), quiet=True)
    assert "\n" not in str(e.value) and not (dest / "sacre_coeur").exists()
    _no_leftovers(dest)


def test_tune_data_download_unreachable_says_what_else_works(tmp_path, capsys):
    """`tune data download` with the host unreachable (a closed loopback port stands in for no network): one line,
    exit 2, saying what else works (--data with a copy, a mirror with --base-url); an HTTP 404 is no network
    problem and gets no such hint."""
    from tuner.cli import main
    capsys.readouterr()
    rc = main(["data", "download", "sacre_coeur", "--dest", str(tmp_path / "d"), "--base-url", _closed_port_url(),
               "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("tune: error: download failed: http://127.0.0.1") and "--data DIR" in err[0] \
        and "--base-url URL" in err[0] and "IMTUNE_DOWNLOAD_BASE" in err[0], err
    assert not (tmp_path / "d" / "sacre_coeur").exists()


def test_unknown_name_lists_available(tmp_path):
    with pytest.raises(ImtuneError, match="unknown data set 'nope'.*strecha.*sacre_coeur.*scannet_sample.*phototourism"):
        dl.download("nope", tmp_path)


def test_resolve_url():
    url = "https://www.cs.ubc.ca/research/kmyi_data/imw2020/ValidationData/imw2020-valid.tar.gz"
    assert dl.resolve_url(url, None) == url
    assert dl.resolve_url(url, "http://127.0.0.1:8000/m/") == \
        "http://127.0.0.1:8000/m/research/kmyi_data/imw2020/ValidationData/imw2020-valid.tar.gz"


def _set_100(sdir: Path):
    keys = ["11111111_1", "22222222_2", "33333333_3"]
    for k, key in enumerate(keys):
        (sdir / "images").mkdir(parents=True, exist_ok=True)
        (sdir / "calibration").mkdir(exist_ok=True)
        cv2.imwrite(str(sdir / "images" / f"{key}.jpg"), np.full((30, 40), 50 * k, np.uint8))
        with h5py.File(sdir / "calibration" / f"calibration_{key}.h5", "w") as f:
            f["K"], f["R"], f["T"] = np.array([[50.0, 0, 20], [0, 50, 15], [0, 0, 1]]), np.eye(3), np.array([k, 0., 0.])
    (sdir / "new-vis-pairs").mkdir()
    np.save(sdir / "new-vis-pairs" / "keys-th-0.0.npy", np.array([f"{keys[0]}-{keys[1]}", f"{keys[1]}-{keys[2]}"]))
    np.save(sdir / "new-vis-pairs" / "keys-th-0.1.npy", np.array([f"{keys[0]}-{keys[1]}"]))


def test_phototourism_tarball(server, tmp_path):
    mirror, base = server
    src = tmp_path / "src"
    for scene in ("reichstag", "sacre_coeur"):
        _set_100(src / "imw2020-valid" / scene / "set_100")
    archive = mirror / "research/kmyi_data/imw2020/ValidationData/imw2020-valid.tar.gz"
    archive.parent.mkdir(parents=True)
    with tarfile.open(archive, "w:gz") as t:
        t.add(src / "imw2020-valid", arcname="imw2020-valid")
    out = dl.download("phototourism", tmp_path / "data", base_url=base, quiet=True)
    assert sorted(p.name for p in out.iterdir()) == ["reichstag", "sacre_coeur"]
    scene = load_imc_pt2020(out, "sacre_coeur")
    assert len(scene.images) == 3 and [p.covisibility for p in scene.pairs] == [0.1, 0.0]
    _no_leftovers(tmp_path / "data")


def _zip_bytes(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def test_zip_member_extraction_checksum_and_safety(server, tmp_path, monkeypatch):
    mirror, base = server
    jpg = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))[1].tobytes()
    data = _zip_bytes({"toy-main/README": b"x", "toy-main/pics/a.jpg": jpg, "toy-main/pics/b.jpg": jpg})
    (mirror / "pkg").mkdir()
    (mirror / "pkg" / "toy.zip").write_bytes(data)
    good = hashlib.sha256(data).hexdigest()
    monkeypatch.setitem(dl.SOURCES, "toy", [dl.Source("https://example.org/pkg/toy.zip", good, "zip", "images",
                                                      "toy-main/pics")])
    out = dl.download("toy", tmp_path / "d1", base_url=base, quiet=True)
    assert sorted(p.name for p in (out / "images").iterdir()) == ["a.jpg", "b.jpg"]
    assert [p.name for p in out.iterdir()] == ["images"]

    monkeypatch.setitem(dl.SOURCES, "toy", [dl.Source("https://example.org/pkg/toy.zip", "0" * 64, "zip", "", "")])
    with pytest.raises(ImtuneError, match="sha256 mismatch"):
        dl.download("toy", tmp_path / "d2", base_url=base, quiet=True)
    assert not (tmp_path / "d2" / "toy").exists()

    (mirror / "pkg" / "evil.zip").write_bytes(_zip_bytes({"../../evil.txt": b"pwned"}))
    monkeypatch.setitem(dl.SOURCES, "toy", [dl.Source("https://example.org/pkg/evil.zip", None, "zip", "", "")])
    with pytest.raises(ImtuneError, match="unsafe path"):
        dl.download("toy", tmp_path / "d3", base_url=base, quiet=True)
    assert not list(tmp_path.rglob("evil.txt"))

    (mirror / "pkg" / "broken.zip").write_bytes(data[: len(data) // 2])
    monkeypatch.setitem(dl.SOURCES, "toy", [dl.Source("https://example.org/pkg/broken.zip", None, "zip", "", "")])
    with pytest.raises(ImtuneError, match="corrupt archive"):
        dl.download("toy", tmp_path / "d4", base_url=base, quiet=True)
    _no_leftovers(tmp_path / "d4")


def test_truncated_download_is_detected(server, tmp_path):
    mirror, base = server
    folder = mirror / "cvg/Hierarchical-Localization/master/datasets/sacre_coeur/mapping"
    folder.mkdir(parents=True)
    for k, name in enumerate(dl.SACRE_COEUR_IMAGES):
        data = cv2.imencode(".jpg", np.full((30, 40), 20 * k, np.uint8))[1].tobytes()
        (folder / name).write_bytes(data if k != 4 else data[: len(data) // 2])
    with pytest.raises(ImtuneError, match=dl.SACRE_COEUR_IMAGES[4]):
        dl.download("sacre_coeur", tmp_path / "data", base_url=base, quiet=True)
    assert not (tmp_path / "data" / "sacre_coeur").exists()
    _no_leftovers(tmp_path / "data")
    (folder / dl.SACRE_COEUR_IMAGES[4]).write_bytes(cv2.imencode(".jpg", np.zeros((30, 40), np.uint8))[1].tobytes())
    out = dl.download("sacre_coeur", tmp_path / "data", base_url=base, quiet=True)
    assert len(list((out / "images").iterdir())) == 10


# -- a mirror that asks for a password ------------------------------------------------------------------------

PASSWORD = "p@ss w0rd/s3cret"  # '@', ' ' and '/' percent-encoded in the URL, decoded in the header
USERINFO = "imtune:" + urllib.parse.quote(PASSWORD, safe="")


def _auth_server(root: Path, seen: list, redirect_to: str | None = None):
    """An HTTP server on loopback serving ``root``: 401 for wrong Basic credentials, the file for imtune:PASSWORD
    or for none at all; ``seen`` collects every request's Authorization header; ``redirect_to``: answer every
    authorised GET with a 302 there (and a request without credentials with 401)."""
    expected = "Basic " + base64.b64encode(f"imtune:{PASSWORD}".encode()).decode()

    class Handler(_Quiet):
        def do_GET(self):
            got = self.headers.get("Authorization")
            seen.append(got)
            if redirect_to is None and got is None:
                return super().do_GET()  # no credentials (a redirect's target): served; ``seen`` records it
            if got != expected:
                self.send_response(401)
                self.send_header("WWW-Authenticate", 'Basic realm="mirror"')
                self.end_headers()
                return
            if redirect_to is not None:
                self.send_response(302)
                self.send_header("Location", redirect_to + self.path)
                self.end_headers()
                return
            return super().do_GET()

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(root)))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd, httpd.server_address[1]


def test_a_mirror_password_in_the_url_is_sent_as_basic_auth_and_never_shown(tmp_path, capsys):
    """A mirror URL with credentials (http://user:password@host/..., as curl and wget take them) failed with
    "InvalidURL: nonnumeric port: '<password>@host'": the password in the error line, and no way to use such a
    mirror. Now the credentials go as Basic authentication (never to a redirect's host) and no message shows them."""
    root = tmp_path / "mirror"
    root.mkdir()
    (root / "f.bin").write_bytes(b"imtune" * 100)
    seen: list = []
    httpd, port = _auth_server(root, seen)
    try:
        out = tmp_path / "f.bin"
        dl._fetch(f"http://{USERINFO}@127.0.0.1:{port}/f.bin", out, hashlib.sha256(b"imtune" * 100).hexdigest(),
                  True)
        assert out.read_bytes() == b"imtune" * 100
        wrong = "imtune:" + urllib.parse.quote("not-" + PASSWORD, safe="")
        with pytest.raises(ImtuneError) as e:
            dl._fetch(f"http://{wrong}@127.0.0.1:{port}/f.bin", tmp_path / "g.bin", None, True)
        assert "HTTP 401" in str(e.value) and "p@ss" not in str(e.value) and "p%40ss" not in str(e.value), e.value
        assert "imtune:***@127.0.0.1" in str(e.value)
    finally:
        httpd.shutdown()
        httpd.server_close()
    # a redirect to another host does not carry the credentials
    target_seen: list = []
    target, tport = _auth_server(root, target_seen)
    front_seen: list = []
    front, fport = _auth_server(root, front_seen, redirect_to=f"http://127.0.0.1:{tport}")
    try:
        dl._fetch(f"http://{USERINFO}@127.0.0.1:{fport}/f.bin", tmp_path / "h.bin", None, True)
        assert (tmp_path / "h.bin").read_bytes() == b"imtune" * 100
        assert front_seen and front_seen[0] is not None and target_seen == [None], (front_seen, target_seen)
    finally:
        for h in (front, target):
            h.shutdown()
            h.server_close()
    # the CLI, host unreachable: one line, no form of the password anywhere
    from tuner.cli import main
    capsys.readouterr()
    closed = _closed_port_url().replace("http://", f"http://{USERINFO}@")
    rc = main(["data", "download", "sacre_coeur", "--dest", str(tmp_path / "d"), "--base-url", closed, "--quiet"])
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("tune: error: download failed: http://imtune:***@"), err
    for shown in (cap.out, cap.err):
        assert "p@ss" not in shown and "p%40ss" not in shown and "s3cret" not in shown, shown


def test_an_empty_folder_or_a_file_at_the_data_set_is_not_ready(server, tmp_path, monkeypatch, capsys):
    """`tune data download strecha` with an empty folder at <dest>/strecha (a user's mkdir, an emptied copy) said
    "already in ...", "ready", exit 0, nothing downloaded; with a file there too. Now an empty folder is downloaded
    into, and a file is one line naming it."""
    from tuner.cli import main
    mirror, base = server
    _mirror_strecha(mirror)
    monkeypatch.setattr(dl, "STRECHA_LONG_SIDE", 64)
    dest = tmp_path / "data"
    (dest / "strecha").mkdir(parents=True)
    assert main(["data", "download", "strecha", "--dest", str(dest), "--base-url", base, "--quiet"]) == 0
    assert (dest / "strecha" / "entry-P10" / "images" / "0009.jpg").is_file()
    _no_leftovers(dest)
    other = tmp_path / "other"
    other.mkdir()
    (other / "strecha").write_text("mine")
    capsys.readouterr()
    assert main(["data", "download", "strecha", "--dest", str(other), "--base-url", base, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"tune: error: {other / 'strecha'} is a file where the data set's folder goes: move it away, or "
                   "give --dest another folder"), err
    assert (other / "strecha").read_text() == "mine"
