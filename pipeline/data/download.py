"""Fetch the public data sets from their original homes (urllib only), into ``<dest>/<name>/``.

    from pipeline.data.download import download
    download("strecha")                          # -> <download location>/strecha/<scene>/...
    download("strecha", "/data/imtune")          # -> /data/imtune/strecha/<scene>/...

``dest`` defaults to the download location (:func:`download_home`: $IMTUNE_DATA_HOME, else the user data folder
``~/.local/share/imtune/data``), where :mod:`pipeline.data.locate`, and so every command, looks for data. Each
source is a file or an archive (zip / tar*) with an optional sha256 (None where no digest is published: the
Strecha files live on a git branch); every downloaded image is decoded and every Strecha camera file's size line
is checked against its image, so a truncated or mismatched file fails the download. ``base_url`` (or the
environment variable IMTUNE_DOWNLOAD_BASE) replaces scheme and host of every URL, keeping its path: a mirror or a
local test server.

Nothing half-made is left behind: everything is assembled in a temporary folder beside the target
(``<dest>/.<name>-download-*``) and renamed into place at the end; on any failure or Ctrl-C the temporary folder
is removed, and so is ``dest`` itself (and any parent) if this call created it and it is still empty.

Strecha images published at 3072x2048 are downsampled by exactly 2 after download (-> 1536x1024, area
interpolation, JPEG quality 95; fx, fy, skew halved, c' = c/2 - 0.25, size halved), the layout ``../shared/data``
uses; images already at that size (a mirror of ``../shared/data``) are kept as they are.
"""
from __future__ import annotations

import base64
import hashlib
import os
import shutil
import tarfile
import tempfile
import urllib.error
import urllib.parse
import urllib.request
import zipfile
from collections.abc import Callable
from http.client import HTTPException
from pathlib import Path
from typing import NamedTuple

from pipeline.data.imagefile import check_image_file, is_image_file
from pipeline.errors import ImtuneError

ENV_BASE = "IMTUNE_DOWNLOAD_BASE"
ENV_DATA_HOME = "IMTUNE_DATA_HOME"
TIMEOUT_S = 60.0
_CHUNK = 1 << 20


class Source(NamedTuple):
    """One thing to fetch: ``url``; ``sha256`` hex digest or None (not checked); ``kind`` "file" | "zip" | "tar"
    (any tar compression); ``target``: path inside the data set folder it ends up at ("" = the folder itself);
    ``member``: for archives, the folder or file inside the archive to take ("" = the whole archive)."""
    url: str
    sha256: str | None
    kind: str
    target: str
    member: str = ""


_GH = "https://raw.githubusercontent.com"
_STRECHA_REPO = f"{_GH}/openMVG/SfM_quality_evaluation/master/Benchmarking_Camera_Calibration_2008"
#: scene -> images (named 0000.jpg ... in the repository; cameras gt_dense_cameras/NNNN.jpg.camera): all six scenes
#: of Strecha et al. 2008 as ../shared/data holds them (castle-P19 / P30 share 11 images, Herz-Jesus-P8 / P25 a
#: facade: pipeline.data.STRECHA_FAMILIES keeps each family on one side of the default split)
STRECHA_SCENES = {"fountain-P11": 11, "Herz-Jesus-P8": 8, "entry-P10": 10, "castle-P19": 19, "castle-P30": 30,
                  "Herz-Jesus-P25": 25}
_HLOC_SACRE = f"{_GH}/cvg/Hierarchical-Localization/master/datasets/sacre_coeur/mapping"
SACRE_COEUR_IMAGES = (
    "02928139_3448003521.jpg", "03903474_1471484089.jpg", "10265353_3838484249.jpg", "17295357_9106075285.jpg",
    "32809961_8274055477.jpg", "44120379_8371960244.jpg", "51091044_3486849416.jpg", "60584745_2207571072.jpg",
    "71295362_4051449754.jpg", "93341989_396310999.jpg")
_SUPERGLUE_ASSETS = f"{_GH}/magicleap/SuperGluePretrainedNetwork/master/assets"
# The 15 ScanNet pairs of SuperGlue's scannet_sample_pairs_with_gt.txt: scene, frame of image 0, frame of image 1.
_SCANNET_PAIRS = (
    ("0711", "001680", "001995"), ("0713", "001320", "002025"), ("0721", "000375", "002745"),
    ("0722", "000045", "000735"), ("0726", "000135", "000210"), ("0737", "000930", "001095"),
    ("0738", "000885", "001065"), ("0743", "000000", "001275"), ("0744", "000585", "002310"),
    ("0747", "000000", "001530"), ("0752", "000075", "001440"), ("0755", "000120", "002055"),
    ("0758", "000165", "000510"), ("0768", "001095", "003435"), ("0806", "000225", "001095"))
SCANNET_IMAGES = tuple(f"scene{s}_00_frame-{f}.jpg" for s, *fr in _SCANNET_PAIRS for f in fr)
_IMW2020 = "https://www.cs.ubc.ca/research/kmyi_data/imw2020"


def _strecha_sources() -> list[Source]:
    out = []
    for scene, n in STRECHA_SCENES.items():
        for k in range(n):
            f = f"{k:04d}.jpg"
            out.append(Source(f"{_STRECHA_REPO}/{scene}/images/{f}", None, "file", f"{scene}/images/{f}"))
            out.append(Source(f"{_STRECHA_REPO}/{scene}/gt_dense_cameras/{f}.camera", None, "file",
                              f"{scene}/gt_dense_cameras/{f}.camera"))
    return out


#: data set name -> what to fetch. Checksums are None where no published digest exists (upstream files on a
#: branch may change); pass verified digests here to pin them.
SOURCES: dict[str, list[Source]] = {
    "strecha": _strecha_sources(),
    "sacre_coeur": [Source(f"{_HLOC_SACRE}/{f}", None, "file", f"images/{f}") for f in SACRE_COEUR_IMAGES],
    "scannet_sample": [Source(f"{_SUPERGLUE_ASSETS}/scannet_sample_pairs_with_gt.txt", None, "file",
                              "pairs_with_gt.txt")]
    + [Source(f"{_SUPERGLUE_ASSETS}/scannet_sample_images/{f}", None, "file", f"images/{f}") for f in SCANNET_IMAGES],
    # IMC-PT 2020 validation scenes with ground truth (reichstag, sacre_coeur, st_peters_square), benchmark layout
    # <scene>/set_100/{images,calibration,depth_maps,new-vis-pairs,sub_set}.
    "phototourism": [Source(f"{_IMW2020}/ValidationData/imw2020-valid.tar.gz", None, "tar", "", "imw2020-valid")],
}


#: long side (px) of the Strecha layout in ../shared/data; published images at twice this are halved to it.
STRECHA_LONG_SIDE = 1536


def _strecha_downsample(folder: Path) -> None:
    """Halve every Strecha image whose long side is at least 2 x STRECHA_LONG_SIDE (the published 3072x2048) and
    rescale its camera file (pixel-centre convention), in place; smaller images (already in the ../shared/data
    layout) are kept. Every camera file's size line must match its image either way."""
    import cv2
    import numpy as np

    from pipeline.data.resize import scaled_K
    from pipeline.data.strecha import read_camera, write_camera

    for cam_path in sorted(folder.glob("*/gt_dense_cameras/*.camera")):
        img_path = cam_path.parent.parent / "images" / cam_path.name[: -len(".camera")]
        cam = read_camera(cam_path)
        img = cv2.imread(str(img_path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ImtuneError(f"unreadable downloaded image {img_path}")
        h, w = img.shape[:2]
        if (w, h) != cam["size"]:
            raise ImtuneError(f"{cam_path} states size {cam['size'][0]}x{cam['size'][1]} but {img_path} is {w}x{h}")
        if max(w, h) < 2 * STRECHA_LONG_SIDE:
            continue
        w2, h2 = int(round(w / 2)), int(round(h / 2))
        small = cv2.resize(img, (w2, h2), interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 95])
        if not ok:
            raise ImtuneError(f"cannot encode {img_path}")
        img_path.write_bytes(np.asarray(buf).tobytes())
        write_camera(cam_path, scaled_K(cam["K"], w2 / w, h2 / h), cam["dist"], cam["R"], cam["C"], (w2, h2))


#: data set name -> step run on the assembled folder before it is moved into place.
POSTPROCESS: dict[str, Callable[[Path], None]] = {"strecha": _strecha_downsample}


def download_home() -> tuple[Path, str]:
    """(the download location, what defined it): where :func:`download` writes by default and where
    :mod:`pipeline.data.locate` looks (rule 4). ``$IMTUNE_DATA_HOME``, else the user data folder + ``imtune/data``
    (platformdirs when installed, else ``$XDG_DATA_HOME/imtune/data``, default ``~/.local/share/imtune/data``)."""
    if os.environ.get(ENV_DATA_HOME):
        return Path(os.environ[ENV_DATA_HOME]).expanduser().resolve(), f"${ENV_DATA_HOME}"
    try:
        import platformdirs
    except ImportError:  # optional: the XDG rule below is what platformdirs does on Linux
        pass
    else:
        return Path(platformdirs.user_data_dir("imtune", appauthor=False)) / "data", "platformdirs user data folder"
    xdg = os.environ.get("XDG_DATA_HOME")
    if xdg and Path(xdg).is_absolute():  # the XDG spec: a relative value is invalid and ignored
        return Path(xdg) / "imtune" / "data", "$XDG_DATA_HOME/imtune/data"
    return Path.home() / ".local" / "share" / "imtune" / "data", "~/.local/share/imtune/data"


def _shown(url: str) -> str:
    """``url`` as shown in messages: a password in its userinfo masked."""
    import re
    return re.sub(r"(//[^/@\s]*?:)[^/\s]*@", r"\1***@", url)


def base_url_of(base_url: str | None = None) -> str | None:
    """The mirror every URL is redirected to: ``base_url`` (``--base-url``), else $IMTUNE_DOWNLOAD_BASE, else None
    (the original homes). It must be an http(s)://HOST[/PATH] or file:///PATH URL: anything else (a typo, a bare
    path, words) is a one-line ImtuneError naming where it came from, before anything is fetched or created."""
    where = "--base-url"
    if base_url is None:
        base_url, where = os.environ.get(ENV_BASE) or None, f"${ENV_BASE}"
    if base_url is None:
        return None
    try:
        u = urllib.parse.urlsplit(str(base_url).strip())
        u.port  # noqa: B018 - raises ValueError for a port that is no number
        ok = not any(c.isspace() for c in str(base_url).strip()) and (
            (u.scheme in ("http", "https") and bool(u.hostname)) or (u.scheme == "file" and bool(u.path)))
    except ValueError:
        ok = False
    if not ok:
        raise ImtuneError(f"{where} {_shown(str(base_url))!r} is not a download URL: give the http://HOST/PATH, "
                          "https://... or file:///PATH of a mirror with the same paths as the original home")
    return str(base_url).strip()


def resolve_url(url: str, base_url: str | None) -> str:
    """``url`` with scheme and host replaced by ``base_url`` (its path prefix kept), or ``url`` unchanged."""
    if not base_url:
        return url
    path = urllib.parse.urlsplit(url).path
    return base_url.rstrip("/") + "/" + path.lstrip("/")


class NetworkError(ImtuneError):
    """The host could not be reached or the transfer broke (not an HTTP status, not a local write)."""


#: what `tune data download` adds to a NetworkError (no network, a firewall, a mirror that is down)
NET_HINT = (f"no network here? copy the data set from a machine that has it and pass --data DIR, or download from a "
            f"mirror with --base-url URL (or ${ENV_BASE})")


def _secrets(url: str | None) -> list[str]:
    """The password of ``url``'s userinfo, as written and percent-decoded (what a message must never show)."""
    try:
        pw = urllib.parse.urlsplit(url or "").password
    except ValueError:
        return []
    return sorted({s for s in (pw, urllib.parse.unquote(pw or "")) if s}, key=len, reverse=True)


def _redacted(text: str, url: str | None) -> str:
    """``text`` with ``url``'s password replaced by ``***`` wherever it appears (a library's own message may quote
    the host part it failed to parse, password included)."""
    for sec in _secrets(url):
        text = text.replace(sec, "***")
    return text


def _request(url: str) -> urllib.request.Request:
    """The request for ``url``. A mirror's credentials in the userinfo (``http://user:password@host/path``, as
    curl and wget take them) become a Basic Authorization header on the URL without them: urllib / http.client
    have no userinfo support (they read ``password@host`` as the port). Written by hand because urllib's
    HTTPBasicAuthHandler answers a 401 challenge only after a realm lookup; the header is an unredirected one, so
    a redirect to another host never receives the credentials."""
    u = urllib.parse.urlsplit(url)
    if u.scheme not in ("http", "https") or (u.username is None and u.password is None):
        return urllib.request.Request(url)
    bare = urllib.parse.urlunsplit((u.scheme, u.netloc.rpartition("@")[2], u.path, u.query, u.fragment))
    user, pw = urllib.parse.unquote(u.username or ""), urllib.parse.unquote(u.password or "")
    req = urllib.request.Request(bare)
    req.add_unredirected_header("Authorization",
                                "Basic " + base64.b64encode(f"{user}:{pw}".encode()).decode("ascii"))
    return req


def _fetch(url: str, out: Path, sha256: str | None, quiet: bool) -> None:
    """Stream ``url`` to ``out`` with a progress bar; ImtuneError (one line) on any network or checksum error.
    A password in ``url`` is sent as Basic authentication (:func:`_request`) and never shown."""
    try:
        _fetch_shown(url, out, sha256, quiet)
    except ImtuneError as e:
        raise type(e)(_redacted(str(e), url)) from None


def _fetch_shown(url: str, out: Path, sha256: str | None, quiet: bool) -> None:
    from tqdm import tqdm

    digest = hashlib.sha256()
    req = _request(url)
    url = _shown(url)  # every message below
    try:
        with urllib.request.urlopen(req, timeout=TIMEOUT_S) as r, open(out, "wb") as f:
            total = r.headers.get("Content-Length")
            total = int(total) if total and total.isdigit() else None
            got = 0
            with tqdm(total=total, unit="B", unit_scale=True, desc=Path(out).name, leave=False,
                      disable=quiet or (total is not None and total < 8 * _CHUNK)) as bar:
                while chunk := r.read(_CHUNK):
                    f.write(chunk)
                    digest.update(chunk)
                    got += len(chunk)
                    bar.update(len(chunk))
    except urllib.error.HTTPError as e:
        raise ImtuneError(f"download failed: {url}: HTTP {e.code} {e.reason}") from None
    except urllib.error.URLError as e:
        raise NetworkError(f"download failed: {url}: {e.reason}") from None
    except TimeoutError as e:
        raise NetworkError(f"download failed: {url}: timed out ({e})") from None
    except (HTTPException, ConnectionError) as e:
        raise NetworkError(f"download failed: {url}: {type(e).__name__}: {e}") from None
    except OSError as e:  # writing the file (a full disk, no permission): the network is not the cause
        raise ImtuneError(f"download failed: {url}: {type(e).__name__}: {e}") from None
    if total is not None and got != total:
        raise ImtuneError(f"download failed: {url}: incomplete ({got} of {total} bytes)")
    if sha256 and digest.hexdigest() != sha256.lower():
        raise ImtuneError(f"download failed: {url}: sha256 mismatch (got {digest.hexdigest()}, expected {sha256})")


def _inside(root: Path, member: str) -> bool:
    target = (root / member).resolve()
    return target == root.resolve() or root.resolve() in target.parents


def _extract(archive: Path, kind: str, out: Path, url: str) -> None:
    """Extract safely (no absolute paths, no '..', no links leaving ``out``); ImtuneError if corrupt."""
    out.mkdir(parents=True, exist_ok=True)
    try:
        if kind == "zip":
            with zipfile.ZipFile(archive) as z:
                bad = [n for n in z.namelist() if not _inside(out, n)]
                if bad:
                    raise ImtuneError(f"unsafe path in archive from {url}: {bad[0]}")
                z.extractall(out)
        elif kind == "tar":
            with tarfile.open(archive) as t:
                members = t.getmembers()
                bad = [m.name for m in members if not _inside(out, m.name)
                       or ((m.issym() or m.islnk()) and not _inside(out, str(Path(m.name).parent / m.linkname)))
                       or m.isdev()]
                if bad:
                    raise ImtuneError(f"unsafe path in archive from {url}: {bad[0]}")
                if hasattr(tarfile, "data_filter"):
                    t.extractall(out, filter="data")
                else:  # pragma: no cover - Python without extraction filters
                    t.extractall(out)
        else:
            raise ImtuneError(f"unknown archive kind {kind!r} for {url}")
    except (zipfile.BadZipFile, tarfile.TarError, EOFError, OSError) as e:
        raise ImtuneError(f"corrupt archive from {url}: {type(e).__name__}: {e}") from None


def _place(src: Path, dst: Path) -> None:
    """Move ``src`` (file or folder) to ``dst``, merging into an existing folder."""
    if src.is_dir() and dst.is_dir():
        for child in src.iterdir():
            _place(child, dst / child.name)
        return
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        shutil.rmtree(dst) if dst.is_dir() else dst.unlink()
    shutil.move(str(src), str(dst))


def describe_source(name: str, base_url: str | None = None) -> str:
    """'58 files from raw.githubusercontent.com' — what ``download(name)`` will fetch, for a progress line."""
    if name not in SOURCES:
        raise ImtuneError(f"unknown data set {name!r}{_suggest(name)} (available: {', '.join(SOURCES)})")
    base = base_url_of(base_url)
    hosts = sorted({_host(resolve_url(s.url, base)) for s in SOURCES[name]})
    n = len(SOURCES[name])
    return f"{n} file{'s' if n != 1 else ''} from {', '.join(hosts)}"


def _host(url: str) -> str:
    """HOST[:PORT] of a URL (never its user name or password); "local files" for file://."""
    u = urllib.parse.urlsplit(url)
    if u.scheme == "file":
        return "local files"
    return (u.hostname or "") + (f":{u.port}" if u.port else "")


def _suggest(name: str) -> str:
    from pipeline.registry import did_you_mean
    return did_you_mean(name, SOURCES)


def _missing_parents(p: Path) -> list[Path]:
    """``p`` and its ancestors that do not exist yet, deepest first (what a mkdir(parents=True) creates)."""
    out = []
    while not p.exists() and p != p.parent:
        out.append(p)
        p = p.parent
    return out


def _remove_if_empty(dirs: list[Path]) -> None:
    for d in dirs:  # deepest first; stops at the first that is not empty (or not ours any more)
        try:
            d.rmdir()
        except OSError:
            break


def downloaded(final: Path) -> bool:
    """``final`` (``<dest>/<name>``) holds a data set: a folder with something in it. An empty folder is none (it was
    "ready", nothing downloaded); a file or a FIFO there is a one-line ImtuneError naming it (it was "ready" too)."""
    from pipeline.fileio import kind_at
    final = Path(final)
    kind = kind_at(final)
    if kind in (None, "a broken link"):
        return False
    if kind != "a folder":
        raise ImtuneError(f"{final} is {kind} where the data set's folder goes: move it away, or give --dest another "
                          "folder")
    return any(final.iterdir())


def download(name: str, dest: str | Path | None = None, base_url: str | None = None, *, force: bool = False,
             quiet: bool = False, on_connected: Callable[[], None] | None = None) -> Path:
    """Download data set ``name`` (a key of SOURCES) into ``<dest>/<name>`` and return that folder.

    ``dest`` defaults to the download location (:func:`download_home`), where the commands look. An existing ``<dest>/<name>`` is kept as is unless ``force``. ``base_url`` (default:
    $IMTUNE_DOWNLOAD_BASE) redirects every URL to another host, keeping the path. Errors are ImtuneError with a
    one-line message; after an error or an interrupt nothing of this call is left on disk. ``on_connected`` is
    called once the first file has arrived (the progress bar starts then too), so that a caller announces a
    download only when one is really under way: offline, the error is the only output.
    """
    if name not in SOURCES:
        raise ImtuneError(f"unknown data set {name!r}{_suggest(name)} (available: {', '.join(SOURCES)})")
    if dest is None:
        dest = download_home()[0]
    dest = Path(dest).expanduser()
    final = dest / name
    base = base_url_of(base_url)  # a mistyped mirror: one line, before anything is created
    if not force and downloaded(final):
        return final
    created = _missing_parents(dest)
    try:
        dest.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{name}-download-", dir=dest))
    except OSError as e:
        _remove_if_empty(created)
        raise ImtuneError(f"cannot write to {dest}: {e.strerror or e}") from None
    from tqdm import tqdm

    done = False
    try:
        stage, fetched = tmp / name, tmp / "_fetched"
        stage.mkdir()
        fetched.mkdir()
        sources = SOURCES[name]
        bar = None
        for k, src in enumerate(sources):
            url = resolve_url(src.url, base)
            file = fetched / f"{k:05d}-{Path(urllib.parse.urlsplit(url).path).name or 'download'}"
            _fetch(url, file, src.sha256, quiet)
            if bar is None:
                if on_connected is not None:
                    on_connected()
                bar = tqdm(total=len(sources), desc=f"download {name}", unit="file", disable=quiet)
            bar.update(1)
            if src.kind == "file":
                _place(file, stage / src.target if src.target else stage / file.name)
                continue
            xdir = tmp / f"_x{k:05d}"
            _extract(file, src.kind, xdir, _shown(url))
            file.unlink()
            member = xdir / src.member if src.member else xdir
            if not member.exists():
                raise ImtuneError(f"archive from {_shown(url)} has no {src.member!r}")
            _place(member, stage / src.target if src.target else stage / (member.name if member.is_file() else ""))
            shutil.rmtree(xdir, ignore_errors=True)
        if bar is not None:
            bar.close()
        for f in stage.rglob("*"):  # a truncated image fails here, not hours later
            if is_image_file(f):
                check_image_file(f)
        if name in POSTPROCESS:
            POSTPROCESS[name](stage)
        if final.exists():
            os.replace(final, tmp / "_old")
        os.replace(stage, final)
        done = True
    except OSError as e:
        raise ImtuneError(f"cannot write data set {name} to {dest}: {e.strerror or e}") from None
    finally:  # also on KeyboardInterrupt: the temporary folder goes, and so does a dest this call made
        shutil.rmtree(tmp, ignore_errors=True)
        if not done:
            _remove_if_empty(created)
    return final
