"""Text on figures: OpenCV's TrueType renderer (``cv2.FontFace``, OpenCV >= 5: anti-aliased, Unicode such as
degree signs and accented letters; Greek letters and arrows, which its faces lack, spelled out) with a fallback to
the Hershey fonts (ASCII only) on older OpenCV builds."""
from __future__ import annotations

import numpy as np

_ASCII = {"°": " deg", "η": "eta", "Γ": "Gamma", "≤": "<=", "≥": ">=", "·": "-", "—": "-", "–": "-", "×": "x",
          "…": "...", "→": "->"}
#: characters OpenCV's built-in TrueType faces (OpenCV 5.1: sans, serif, uni, italic) have no glyph for: drawn as '?'
_NO_GLYPH = {"η": "eta", "Γ": "Gamma", "→": "->"}
_FACE = None


def _face():
    global _FACE
    if _FACE is None:
        import cv2
        try:
            _FACE = cv2.FontFace("sans")
        except Exception:  # OpenCV 4.x: no FontFace
            _FACE = False
    return _FACE


def _ascii(text: str) -> str:
    for k, v in _ASCII.items():
        text = text.replace(k, v)
    return text.encode("ascii", "replace").decode()


def _drawable(text: str) -> str:
    for k, v in _NO_GLYPH.items():
        text = text.replace(k, v)
    return text


def text_width(text: str, size: float, weight: int = 400) -> int:
    """Width in px of ``text`` drawn with :func:`put_text` at ``size`` px."""
    import cv2
    face = _face()
    if face:
        text = _drawable(text)
        r = cv2.getTextSize((100000, int(size * 3) + 10), text, (0, int(size * 2)), face, int(round(size)), weight)
        return int(r[2]) + int(r[0])
    scale = size / 30.0
    (w, _), _ = cv2.getTextSize(_ascii(text), cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, int(round(weight / 300 * scale))))
    return int(w)


def put_text(img: np.ndarray, text: str, x: int, baseline: int, size: float, color_bgr, weight: int = 400) -> int:
    """Draw ``text`` with its baseline at ``baseline`` (px), starting at ``x``; returns the x where it ends."""
    import cv2
    face = _face()
    if face:
        text = _drawable(text)
        color = tuple(int(c) for c in color_bgr)
        cv2.putText(img, text, (int(x), int(baseline)), color, face, int(round(size)), weight)
        return int(x) + text_width(text, size, weight)
    scale = size / 30.0
    th = max(1, int(round(weight / 300 * scale)))
    cv2.putText(img, _ascii(text), (int(x), int(baseline)), cv2.FONT_HERSHEY_SIMPLEX, scale,
                tuple(int(c) for c in color_bgr), th, cv2.LINE_AA)
    return int(x) + text_width(text, size, weight)


def fit_text(text: str, max_width: int, size: float, weight: int = 400) -> str:
    """``text`` shortened with an ellipsis so that it fits in ``max_width`` px."""
    if text_width(text, size, weight) <= max_width:
        return text
    lo, hi = 0, len(text)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if text_width(text[:mid] + "…", size, weight) <= max_width:
            lo = mid
        else:
            hi = mid - 1
    return text[:lo] + "…"
