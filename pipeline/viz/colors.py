"""Colours of the qualitative figures (RGB tuples; OpenCV drawing takes them reversed, as BGR).

Match error against the ground truth, in px (see :mod:`pipeline.viz.gt`):

- 0 px: green, blending linearly to yellow at ``max_px`` (5 px by default);
- above ``max_px`` (including +inf, e.g. a point that lands behind the camera): red;
- NaN (cannot be computed: no depth at either keypoint, no ground truth): blue.

Multiview keypoints: blue where the keypoint is in the 3D model, red where it is not.
"""
from __future__ import annotations

import numpy as np

GREEN = (0, 220, 0)
YELLOW = (255, 230, 0)
RED = (255, 30, 30)
BLUE = (40, 110, 255)
ERROR_MAX_PX = 5.0

IN_MODEL = BLUE
NOT_IN_MODEL = RED


def error_colors(errors, max_px: float = ERROR_MAX_PX) -> np.ndarray:
    """(N,) errors in px -> (N, 3) uint8 RGB: green (0 px) -> yellow (``max_px``), red above, blue for NaN."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if max_px <= 0:
        raise ValueError(f"max_px must be > 0, got {max_px}")
    finite = np.isfinite(e)
    t = np.clip(np.where(finite, e, 0.0) / max_px, 0.0, 1.0)[:, None]
    rgb = np.asarray(GREEN, float) + t * (np.asarray(YELLOW, float) - np.asarray(GREEN, float))
    rgb[(e > max_px) | np.isposinf(e)] = RED
    rgb[np.isnan(e)] = BLUE
    return np.rint(rgb).astype(np.uint8)


def bgr(rgb) -> tuple[int, int, int]:
    """An RGB colour as the (B, G, R) int tuple OpenCV drawing functions take."""
    r, g, b = (int(v) for v in rgb)
    return b, g, r
