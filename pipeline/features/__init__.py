"""Local features: a registry of extractors behind one interface.

    from pipeline.features import extract, get_extractor, EXTRACTORS
    feats = extract(FeatureConfig(name="rootsift", num_features=2048), gray_uint8_image)
    feats.keypoints      # (N, 2) float32 px, strongest first
    EXTRACTORS.availability()   # {name: (available, reason)}

Registered here (OpenCV): sift, rootsift, orb, akaze, kaze, brisk, freak, beblid, teblid, surf
(surf needs a non-free OpenCV build).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.config import FeatureConfig
from pipeline.errors import ImtuneError
from pipeline.features.base import Extractor, Features
from pipeline.features.registry import EXTRACTORS
# Importing the family modules registers their extractors.
from pipeline.features import sift, orb, akaze, brisk, boost, surf  # noqa: F401,E402  (order = `tune list` order)

__all__ = ["EXTRACTORS", "Extractor", "Features", "get_extractor", "extract"]


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
