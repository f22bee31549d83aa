"""Robust estimator interface: matched points, inlier threshold (px), confidence, max iterations ->
fundamental matrix, inlier mask, seconds spent."""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np


@dataclass
class EstimateResult:
    """F: (3, 3) fundamental matrix with x2^T F x1 = 0, or None when the estimator failed;
    inliers: (M,) bool mask over the input matches; seconds: wall time of the estimator call."""
    F: np.ndarray | None
    inliers: np.ndarray
    seconds: float


class Estimator(ABC):
    """Base of every robust estimator. Register with ``ESTIMATORS.register(name)``.

    ``estimate`` never raises on degenerate input: it returns F=None and an all-False mask.
    """
    min_matches: int = 8

    @classmethod
    def check_available(cls) -> None:
        """Raise ``UnavailableError`` when the backing package is not installed."""

    @abstractmethod
    def estimate(self, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
                 max_iters: int, seed: int = 0) -> EstimateResult:
        """pts1, pts2: (M, 2) float64 px at the working resolution; threshold: eta in px."""
