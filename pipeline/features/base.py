"""Extractor base class and the Features record.

An extractor takes a grayscale uint8 image (H, W) already resized to the working resolution (IMC
convention, long side <= 1024 px) and returns keypoints in that image's pixel coordinates (x, y; the
centre of the top-left pixel is (0, 0)).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.config import FeatureConfig


@dataclass
class Features:
    """keypoints (N, 2) float32 px; scales (N,) px; orientations (N,) degrees; scores (N,);
    descriptors (N, D): float32, or uint8 packed bits when ``binary`` (Hamming distance)."""
    keypoints: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray | None = None
    orientations: np.ndarray | None = None
    scores: np.ndarray | None = None
    binary: bool = False

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


class Extractor(ABC):
    """Base class of every feature extractor. Subclasses register with ``EXTRACTORS.register(name)``.

    ``version`` is part of every cache key: bump it when the output of ``extract`` changes.
    """
    version: ClassVar[str] = "1"
    binary: ClassVar[bool] = False

    def __init__(self, conf: FeatureConfig):
        self.check_available()
        self.conf = conf

    @classmethod
    def check_available(cls) -> None:
        """Raise ``UnavailableError`` with a one-line reason when this extractor cannot run here."""

    @abstractmethod
    def extract(self, image: np.ndarray) -> Features:
        """Detect and describe. ``image``: (H, W) uint8 grayscale at the working resolution."""
