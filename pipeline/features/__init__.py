"""Local features: a registry of extractors behind one interface.

    from pipeline.features import extract, get_extractor, EXTRACTORS
    feats = extract(FeatureConfig(name="rootsift", num_features=2048), gray_uint8_image)
    feats.keypoints      # (N, 2) float32 px, strongest first
    EXTRACTORS.availability()   # {name: (available, reason)}

Registered here (OpenCV): sift, rootsift, orb, akaze, kaze, brisk, freak, beblid, teblid, surf
(surf needs a non-free OpenCV build). Through kornia (learned and affine features, see
``kornia_compose`` / ``kornia_e2e``): the paper's rows dog-tfeat, dog-mkd, dog-hardnet, dog-sosnet,
dog-affnet-hardnet, keynet-hardnet, keynet-sosnet, dog-affine-sift, hessian-affnet-sift, ...; aliked,
disk; any composed ``det[+affine][+orientation]+desc`` name (e.g. ``keynet+affnet+mkd``); and
``custom:DIR`` (features imported from h5 files, ``custom_h5``). :func:`resolve_feature` resolves any of
these names to its extractor class; ``EXTRACTORS.get`` does too. docs/extending.md shows how to register
a new extractor.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.config import FeatureConfig
from pipeline.errors import ImtuneError
from pipeline.features.base import Extractor, Features
from pipeline.features.registry import EXTRACTORS

# Importing the family modules registers their extractors: the import order is the `tune list` order, so isort
# leaves it.
# isort: off
from pipeline.features import sift, orb, akaze, brisk, boost, surf  # noqa: F401,E402
# kornia families (torch/kornia are imported only when one of them runs)
from pipeline.features import kornia_compose, kornia_e2e, custom_h5  # noqa: F401,E402
# COLMAP's own SIFT (pycolmap is imported only when it runs)
from pipeline.features import colmap_sift  # noqa: F401,E402
# isort: on

__all__ = ["EXTRACTORS", "Extractor", "Features", "get_extractor", "extract", "resolve_feature", "load_plugins"]


def _resolve_dynamic(name: str):
    """Names that are not registered one by one: ``custom:DIR`` and composed ``det+...+desc``."""
    if not isinstance(name, str):
        return None
    if name.startswith(custom_h5.PREFIX):
        return custom_h5.custom_class(name)
    if "+" in name:
        return kornia_compose.parse_composed(name)
    return None


EXTRACTORS.add_resolver(_resolve_dynamic)


@EXTRACTORS.register("custom", "bring your own: --feature custom:DIR (IMC h5 import layout; see Extending in the docs)")
class _CustomPlaceholder(Extractor):
    """Listed by `tune list`; the usable name is ``custom:DIR``."""

    def __init__(self, conf):
        raise ImtuneError(f"feature {conf.name!r}: give the folder, --feature custom:DIR (IMC h5 layout: "
                          "DIR[/<scene>]/keypoints.h5, descriptors.h5)")

    def extract(self, image):  # pragma: no cover - never constructed
        raise NotImplementedError


PLUGINS_ENV = "IMTUNE_PLUGINS"
_LOADED_PLUGINS: set[str] = set()


def _import_from_here(name: str):
    """``importlib.import_module(name)``, and when its top package is found nowhere on sys.path, again with the
    current folder on sys.path for that import only, as `python -m tuner` would find it: the `tune` console script
    does not put the current folder on sys.path, so ``IMTUNE_PLUGINS=mylab.features tune`` beside mylab/ failed
    with "No module named 'mylab'". The folder is appended (it shadows nothing) and removed afterwards (a
    ``pipeline/`` folder there must not become the spawned workers' ``pipeline`` package); every process, a
    pool worker included, imports its plug-ins itself."""
    import importlib
    import os
    import sys
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as e:
        here = os.getcwd()
        if e.name != name.split(".")[0] or here in sys.path or "" in sys.path:
            raise
        sys.path.append(here)
        try:
            return importlib.import_module(name)
        finally:
            if here in sys.path:
                sys.path.remove(here)


def load_plugins(spec: str | None = None) -> list[str]:
    """Import the plug-in modules named in ``spec`` (default: ``$IMTUNE_PLUGINS``; comma-separated
    module names, e.g. ``mylab.features``, importable or found in the current folder, or paths to ``.py``
    files) so that what they register
    (extractors, pre-filters, estimators) is known to the CLI too. Done once when ``pipeline.features``
    is imported; a module that fails to import is a one-line ImtuneError naming it."""
    import importlib
    import importlib.util
    import os
    from pathlib import Path
    spec = os.environ.get(PLUGINS_ENV, "") if spec is None else spec
    done = []
    for item in filter(None, (x.strip() for x in spec.split(","))):
        if item in _LOADED_PLUGINS:
            continue
        try:
            if item.endswith(".py"):
                path = Path(item).expanduser().resolve()
                if not path.is_file():
                    raise ImtuneError(f"{PLUGINS_ENV}: plug-in file {path} not found")
                mod_spec = importlib.util.spec_from_file_location(f"imtune_plugin_{path.stem}", path)
                if mod_spec is None or mod_spec.loader is None:  # not for a .py file that exists
                    raise ImtuneError(f"{PLUGINS_ENV}: plug-in file {path} cannot be imported")
                module = importlib.util.module_from_spec(mod_spec)
                mod_spec.loader.exec_module(module)
            else:
                _import_from_here(item)
        except ImtuneError:
            raise
        except SystemExit as e:  # was the process's silent end: `tune list` exited 0 (or the plug-in's code) unsaid
            raise ImtuneError(f"{PLUGINS_ENV}: plug-in {item!r} called sys.exit({e.code!r}) while importing; a plug-in "
                              "module should only define and register (fix it, or drop it from "
                              f"{PLUGINS_ENV})") from None
        except Exception as e:
            msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
            if isinstance(e, ModuleNotFoundError) and e.name == item.split(".")[0]:
                msg += (" (a module name must be importable: installed, on PYTHONPATH or in the current folder; "
                        "or give the path of a .py file)")
            raise ImtuneError(f"{PLUGINS_ENV}: plug-in {item!r} failed to import: {type(e).__name__}: {msg}") from None
        _LOADED_PLUGINS.add(item)
        done.append(item)
    return done


def resolve_feature(name: str) -> type[Extractor]:
    """The extractor class of a feature name: a registered name (``tune list``), a composed
    ``det[+affine][+orientation]+desc`` name, or ``custom:DIR``. One-line ImtuneError if unknown or
    malformed (the class's ``check_available()`` says whether it can run here)."""
    return EXTRACTORS.get(name)


def get_extractor(conf: FeatureConfig | str | dict[str, Any]) -> Extractor:
    """The extractor for ``conf`` (a FeatureConfig; a name or a dict of FeatureConfig fields also work).

    Raises ImtuneError for an unknown name or bad options, UnavailableError (a subclass) when the
    method cannot run here (e.g. surf without a non-free OpenCV)."""
    if isinstance(conf, str):
        conf = FeatureConfig(name=conf)
    elif isinstance(conf, dict):
        try:
            conf = FeatureConfig(**conf)
        except TypeError as e:
            raise ImtuneError(f"bad feature config: {e}") from None
    return EXTRACTORS.get(conf.name)(conf)


def extract(conf: FeatureConfig | str | dict[str, Any], image: np.ndarray) -> Features:
    """Detect and describe ``image`` ((H, W) uint8 grayscale, working resolution) with ``conf``."""
    return get_extractor(conf).extract(image)


load_plugins()
