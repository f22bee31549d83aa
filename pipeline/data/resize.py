"""The IMC resizing convention: images at most ``max_side`` px on the long side, intrinsics scaled to match.

Pixel coordinates follow the pixel-centre convention (OpenCV / COLMAP: the centre of the top-left pixel is
(0, 0)); resizing by s maps x to (x + 0.5) * s - 0.5, hence cx' = (cx + 0.5) * sx - 0.5 (halving: cx/2 - 0.25).
Images are never upscaled.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.data.imagefile import check_image_bytes, check_jpeg_decode
from pipeline.errors import ImtuneError


def working_size(w: int, h: int, max_side: int | None = 1024) -> tuple[int, int, float, float]:
    """(w2, h2, sx, sy): the working size in px (long side <= max_side, never upscaled) and the per-axis scales
    sx = w2 / w, sy = h2 / h. ``max_side`` None or <= 0 keeps the original size."""
    w, h = int(w), int(h)
    if w <= 0 or h <= 0:
        raise ImtuneError(f"invalid image size {w}x{h}")
    if not max_side or max_side <= 0 or max(w, h) <= max_side:
        return w, h, 1.0, 1.0
    s = max_side / max(w, h)
    w2 = min(max_side, max(1, int(round(w * s))))
    h2 = min(max_side, max(1, int(round(h * s))))
    return w2, h2, w2 / w, h2 / h


def scaled_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """3x3 intrinsics of the image resized by (sx, sy): fx, skew, cx scaled with sx; fy, cy with sy;
    principal point under the pixel-centre convention (cx' = (cx + 0.5) * sx - 0.5)."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got shape {K.shape}")
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return S @ K


def scale_points(xy: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Pixel coordinates (n, 2) in the original image -> the resized image (pixel-centre convention)."""
    xy = np.asarray(xy, dtype=np.float64)
    return np.stack([(xy[:, 0] + 0.5) * sx - 0.5, (xy[:, 1] + 0.5) * sy - 0.5], axis=1)


def load_image(path: str | Path, max_side: int | None = 1024, gray: bool = True) -> tuple[np.ndarray, float, float]:
    """Read an image, check it is complete, resize it with INTER_AREA to the working size.

    Returns (image uint8: (H, W) if gray else (H, W, 3) RGB, sx, sy) with sx = W / W_file, sy = H / H_file.
    EXIF orientation is ignored (intrinsics refer to the stored pixel grid). A missing, empty, unreadable or
    truncated file, or a JPEG that libjpeg reports as corrupt (``check_jpeg_decode``), raises ImtuneError naming it.
    """
    import cv2

    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ImtuneError(f"image not found: {path}") from None
    except OSError as e:
        raise ImtuneError(f"cannot read image {path}: {e.strerror or e}") from None
    check_image_bytes(path, data)
    check_jpeg_decode(path, data)
    flags = (cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR) | cv2.IMREAD_IGNORE_ORIENTATION
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # its WARN line was a second line of the error
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None or img.size == 0:
        raw = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED) if img is None else None
        if raw is not None and raw.size:  # decodes as stored, not as 8-bit: a 32-bit float TIFF was "corrupt"
            raise ImtuneError(f"image {path} holds {raw.dtype} samples ({raw.shape[2] if raw.ndim == 3 else 1} "
                              "channel(s)), which OpenCV does not convert to 8-bit: save it as 8- or 16-bit PNG / JPEG")
        raise ImtuneError(f"unreadable or corrupt image: {path}")
    if img.dtype != np.uint8:  # 16-bit PNG / TIFF
        img = (img / (np.iinfo(img.dtype.name).max / 255.0)).round().astype(np.uint8) if img.dtype.kind == "u" else \
            np.clip(img, 0, 255).astype(np.uint8)
    if not gray:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    h, w = img.shape[:2]
    w2, h2, sx, sy = working_size(w, h, max_side)
    if (w2, h2) != (w, h):
        img = cv2.resize(img, (w2, h2), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img), sx, sy
