"""Robust two-view estimators behind one interface (the paper's "RANSAC" stage).

    from pipeline.geometry import estimate, get_estimator, ESTIMATORS
    res = estimate("degensac", pts1, pts2, threshold=0.5, confidence=0.999999, max_iters=50000,
                   seed=0, sizes=((w1, h1), (w2, h2)))
    res.F        # (3, 3) float64, x2^T F x1 = 0, ||F||_F = 1; None if the estimator failed
    res.inliers  # (M,) bool
    res.seconds  # CPU time of the library call alone (what the time budget B is measured on); res.wall_seconds: wall time

Names (``ESTIMATORS.names()``; availability with ``ESTIMATORS.availability()``):
``pyransac``, ``degensac`` (pydegensac); ``magsac``, ``magsac++`` (pymagsac); ``gcransac``
(pygcransac); ``cv-ransac``, ``cv-usac``, ``cv-magsac``, ``cv-accurate``, ``cv-lmeds``, ``cv-8pt``
(OpenCV); ``poselib`` (PoseLib); ``colmap`` (pycolmap); ``superansac`` (pysuperansac).
Calibrated (``model = "E"``, need K1, K2; ``pipeline.geometry.essential``): ``poselib-e``, ``cv-e-ransac``,
``cv-e-magsac``, ``colmap-e``, ``superansac-e``. Each backend module documents the
conventions of its library (threshold meaning, image-size order, seeds, quirks).
Backend libraries are imported lazily, at the first estimate, so importing this package is cheap.
"""
from __future__ import annotations

import numpy as np

from pipeline.geometry.base import EstimateResult, Estimator, Sizes, sampson_distance
from pipeline.geometry.imc import imc_geom_to_config
from pipeline.geometry.registry import ESTIMATORS

# Importing registers the backends: the import order is the listing order, so isort leaves it.
# isort: off
from pipeline.geometry import (  # noqa: F401
    pydegensac_backend, magsac_backend, gcransac_backend, opencv_backend, poselib_backend,
    colmap_backend, superansac_backend,
)
# isort: on

__all__ = ["ESTIMATORS", "Estimator", "EstimateResult", "Sizes", "get_estimator", "estimate", "imc_geom_to_config",
           "sampson_distance"]

_INSTANCES: dict[str, Estimator] = {}


def get_estimator(name: str) -> Estimator:
    """The estimator registered as ``name``, ready to use.

    Raises ``ImtuneError`` (one line, listing the known names) for an unknown name and
    ``UnavailableError`` (naming the pip package) when its library is not installed."""
    cls = ESTIMATORS.get(name)
    cls.check_available()
    if name not in _INSTANCES:
        _INSTANCES[name] = cls()
    return _INSTANCES[name]


def estimate(name: str, pts1: np.ndarray, pts2: np.ndarray, threshold: float, confidence: float,
             max_iters: int, seed: int = 0, *, sizes: Sizes | None = None, K1: np.ndarray | None = None,
             K2: np.ndarray | None = None) -> EstimateResult:
    """Estimate F from matches with the estimator ``name``; see :meth:`Estimator.estimate`.

    pts1, pts2: (M, 2) px; threshold: eta in px; confidence in (0, 1); max_iters: Gamma;
    seed: for reproducible runs where the backend supports it; sizes: ((w1, h1), (w2, h2)) px,
    default derived from the point extents. Never raises on degenerate input (F=None instead);
    raises ``ImtuneError`` / ``UnavailableError`` for an unknown / uninstalled estimator.
    K1, K2: (3, 3) intrinsics in px, required by the E estimators (``model == "E"``: an ``EssentialResult`` with E,
    R, t; ImtuneError without them) and ignored by the F estimators."""
    est = get_estimator(name)
    if est.model == "E":
        return est.estimate(pts1, pts2, threshold, confidence, max_iters, seed, sizes=sizes,  # type: ignore[call-arg]
                            K1=K1, K2=K2)
    return est.estimate(pts1, pts2, threshold, confidence, max_iters, seed, sizes=sizes)
