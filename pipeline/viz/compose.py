"""Composing figures: side by side, stacked, in a grid (white padding; BGR uint8 images)."""
from __future__ import annotations

import numpy as np

BACKGROUND = (255, 255, 255)


def _pad(img: np.ndarray, h: int, w: int) -> np.ndarray:
    out = np.full((h, w, 3), BACKGROUND, np.uint8)
    out[:img.shape[0], :img.shape[1]] = img
    return out


def side_by_side(images: list, gap: int = 16, separator: bool = True) -> np.ndarray:
    """Images next to each other, top-aligned, ``gap`` px apart (a thin grey rule in the gap)."""
    h = max(i.shape[0] for i in images)
    parts = []
    for k, img in enumerate(images):
        if k:
            g = np.full((h, gap, 3), BACKGROUND, np.uint8)
            if separator and gap >= 3:
                g[:, gap // 2 - 1:gap // 2 + 1] = 170
            parts.append(g)
        parts.append(_pad(img, h, img.shape[1]))
    return np.hstack(parts)


def stacked(images: list, gap: int = 16, separator: bool = True) -> np.ndarray:
    """Images one above the other, left-aligned, ``gap`` px apart."""
    w = max(i.shape[1] for i in images)
    parts = []
    for k, img in enumerate(images):
        if k:
            g = np.full((gap, w, 3), BACKGROUND, np.uint8)
            if separator and gap >= 3:
                g[gap // 2 - 1:gap // 2 + 1, :] = 170
            parts.append(g)
        parts.append(_pad(img, img.shape[0], w))
    return np.vstack(parts)


def grid(images: list, columns: int, gap: int = 8) -> np.ndarray:
    """Images in rows of ``columns`` (cells as large as the largest image), ``gap`` px apart."""
    columns = max(1, int(columns))
    ch = max(i.shape[0] for i in images)
    cw = max(i.shape[1] for i in images)
    rows = []
    for r in range(0, len(images), columns):
        cells = [_pad(i, ch, cw) for i in images[r:r + columns]]
        cells += [np.full((ch, cw, 3), BACKGROUND, np.uint8)] * (columns - len(cells))
        row = []
        for k, c in enumerate(cells):
            if k:
                row.append(np.full((ch, gap, 3), BACKGROUND, np.uint8))
            row.append(c)
        rows.append(np.hstack(row))
    out = []
    for k, band in enumerate(rows):
        if k:
            out.append(np.full((gap, band.shape[1], 3), BACKGROUND, np.uint8))
        out.append(band)
    return np.vstack(out)
