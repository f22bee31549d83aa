"""Cheap checks on image files, without decoding pixels.

``image_size`` reads (width, height) in px from the JPEG SOF / PNG IHDR header (falls back to a full decode for
other formats). ``check_image_file`` raises :class:`ImtuneError` naming the file when it is missing, empty or a
truncated JPEG / PNG (OpenCV silently returns None for some corrupt files and decodes truncated JPEGs partially
with only a libjpeg warning, so the bytes are checked here). EXIF orientation is ignored everywhere: sizes and
intrinsics refer to the pixel grid as stored.

``check_jpeg_decode`` catches what the byte walk cannot: a JPEG whose entropy-coded data is damaged (e.g. its middle
overwritten, end marker intact). libjpeg only *warns* about such data ("Corrupt JPEG data: ...", "Premature end of
JPEG file", "Unsupported marker type ...") and OpenCV prints the warning and returns a damaged image; the warning
is not visible to the caller. simplejpeg (libjpeg-turbo) decodes with ``strict=True``, turning exactly these
recoverable errors into a ValueError, so they are caught reliably, without capturing stderr. Policy: such an image
is bad input, an ImtuneError naming the file (exit 2), as a truncated file is; it is never used silently.
"""
from __future__ import annotations

import os
from pathlib import Path

from pipeline.errors import ImtuneError

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"
# SOF markers carrying the frame size (C4 = DHT, C8 = JPG, CC = DAC are not frames).
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def is_image_file(path: Path) -> bool:
    """True for a regular file with a common image extension (case-insensitive), hidden files excluded."""
    return path.is_file() and not path.name.startswith(".") and path.suffix.lower() in IMAGE_EXTENSIONS


def list_images(folder: Path) -> list[str]:
    """Sorted file names of the images directly inside ``folder`` ([] when it does not exist)."""
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if is_image_file(p))


def jpeg_end(data: bytes) -> int | None:
    """Offset just past the JPEG's end-of-image marker, walking its segments; None if truncated or malformed.

    Trailing bytes after EOI (e.g. appended metadata) are allowed; the entropy-coded data after each SOS is
    skipped by searching for the next real marker (0xFF not followed by a stuffed 0x00 or a restart marker).
    """
    n = len(data)
    if n < 4 or data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i < n:
        if data[i] != 0xFF:
            return None
        while i < n and data[i] == 0xFF:  # fill bytes
            i += 1
        if i >= n:
            return None
        marker = data[i]
        i += 1
        if marker == 0xD9:
            return i
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # standalone markers
            continue
        if i + 2 > n:
            return None
        length = int.from_bytes(data[i:i + 2], "big")
        if length < 2 or i + length > n:
            return None
        i += length
        if marker == 0xDA:  # start of scan: skip entropy-coded data up to the next marker
            while True:
                j = data.find(b"\xff", i)
                if j < 0 or j + 1 >= n:
                    return None
                nxt = data[j + 1]
                if nxt == 0x00 or 0xD0 <= nxt <= 0xD7:
                    i = j + 2
                    continue
                if nxt == 0xFF:
                    i = j + 1
                    continue
                i = j
                break
    return None


def _read_tail(path: Path, n: int = 64) -> bytes:
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        f.seek(max(0, size - n))
        return f.read()


def check_image_file(path: Path, full: bool = False) -> None:
    """Raise ImtuneError if ``path`` is missing, empty, or a JPEG / PNG that does not end properly.

    The common case reads only the file's last bytes; a JPEG not ending with FFD9 (possibly a trailer after EOI)
    is parsed in full. ``full=True`` always parses JPEGs in full.
    """
    path = Path(path)
    if not path.is_file():
        raise ImtuneError(f"image not found: {path}")
    try:
        if path.stat().st_size == 0:
            raise ImtuneError(f"image file is empty: {path}")
        with open(path, "rb") as f:
            head = f.read(8)
        if head[:2] == b"\xff\xd8":
            tail = _read_tail(path).rstrip(b"\x00")
            if full or not tail.endswith(b"\xff\xd9"):
                if jpeg_end(path.read_bytes()) is None:
                    raise ImtuneError(f"truncated or corrupt JPEG (no end-of-image marker): {path}")
        elif head == _PNG_MAGIC:
            if _PNG_IEND not in _read_tail(path):
                raise ImtuneError(f"truncated or corrupt PNG (no IEND chunk): {path}")
    except OSError as e:
        raise ImtuneError(f"cannot read image {path}: {e.strerror or e}") from None


def check_image_bytes(path: Path, data: bytes) -> None:
    """Like :func:`check_image_file` on bytes already read (always a full JPEG parse)."""
    if not data:
        raise ImtuneError(f"image file is empty: {path}")
    if data[:2] == b"\xff\xd8" and jpeg_end(data) is None:
        raise ImtuneError(f"truncated or corrupt JPEG (no end-of-image marker): {path}")
    if data[:8] == _PNG_MAGIC and _PNG_IEND not in data[-64:]:
        raise ImtuneError(f"truncated or corrupt PNG (no IEND chunk): {path}")


def check_jpeg_decode(path: Path, data: bytes) -> None:
    """Raise ImtuneError naming ``path`` if libjpeg reports the JPEG ``data`` as corrupt (a recoverable error it
    would otherwise only warn about and decode into a damaged image). Non-JPEG data is not checked. A JPEG that
    simplejpeg cannot decode at all (a variant it does not support) is left to the caller's decoder."""
    if data[:2] != b"\xff\xd8":
        return
    try:
        import simplejpeg
    except ImportError:
        raise ImtuneError("checking JPEG images needs simplejpeg (a dependency of imtune): pip install simplejpeg") \
            from None
    try:
        simplejpeg.decode_jpeg(data, colorspace="GRAY", strict=True)
        return
    except ValueError as e:
        warning = " ".join(str(e).split())
    try:  # a recoverable error (a libjpeg warning) decodes when not strict; anything else is not corruption
        simplejpeg.decode_jpeg(data, colorspace="GRAY", strict=False)
    except ValueError:
        return
    raise ImtuneError(f"corrupt JPEG {path}: libjpeg reports \"{warning}\" (the decoded image would be damaged); "
                      "replace the file or remove it from the scene")


def _jpeg_size(f) -> tuple[int, int] | None:
    if f.read(2) != b"\xff\xd8":
        return None
    while True:
        b = f.read(1)
        if b != b"\xff":
            return None
        while b == b"\xff":
            b = f.read(1)
        if not b:
            return None
        marker = b[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:
            continue
        if marker in (0xD9, 0xDA):
            return None
        raw = f.read(2)
        if len(raw) < 2:
            return None
        length = int.from_bytes(raw, "big")
        if length < 2:
            return None
        if marker in _SOF_MARKERS:
            seg = f.read(5)
            if len(seg) < 5:
                return None
            h, w = int.from_bytes(seg[1:3], "big"), int.from_bytes(seg[3:5], "big")
            return (w, h) if w > 0 and h > 0 else None
        f.seek(length - 2, os.SEEK_CUR)
        nxt = f.read(1)
        if nxt != b"\xff":
            return None
        f.seek(-1, os.SEEK_CUR)


def exif_orientation(path: Path) -> int | None:
    """The EXIF orientation tag (1-8) of a JPEG, None when it has none or is no JPEG (never raises). imtune, like
    COLMAP, reads pixels as stored and ignores it; it is read only to say so when sizes disagree."""
    import struct
    try:
        with open(path, "rb") as f:
            if f.read(2) != b"\xff\xd8":
                return None
            while True:
                head = f.read(4)
                if len(head) < 4 or head[0] != 0xFF or head[1] in (0xD9, 0xDA):
                    return None
                length = int.from_bytes(head[2:4], "big")
                if head[1] != 0xE1:
                    f.seek(length - 2, os.SEEK_CUR)
                    continue
                seg = f.read(length - 2)
                if not seg.startswith(b"Exif\x00\x00"):
                    continue
                tiff = seg[6:]
                e = "<" if tiff[:2] == b"II" else ">"
                ifd = struct.unpack(e + "I", tiff[4:8])[0]
                for k in range(struct.unpack(e + "H", tiff[ifd:ifd + 2])[0]):
                    tag, typ, _, value = struct.unpack(e + "HHIH", tiff[ifd + 2 + 12 * k: ifd + 12 + 12 * k])
                    if tag == 0x0112 and typ == 3:
                        return int(value) if 1 <= value <= 8 else None
                return None
    except (OSError, struct.error, IndexError):
        return None


def rotated_by_exif(path: Path, expected: tuple[int, int]) -> str:
    """The words " (it carries EXIF orientation N, ...)" when ``path`` is ``expected`` (w, h) px only as its EXIF
    orientation tag displays it (transposed, tags 5-8); "" otherwise. For size-mismatch errors."""
    o = exif_orientation(path)
    if o is None or o < 5 or tuple(image_size(path)) != (expected[1], expected[0]):
        return ""
    return (f" (it carries EXIF orientation {o}, which viewers apply and imtune, like COLMAP, does not: store the "
            "pixels upright and drop the tag, or give intrinsics for the pixels as stored)")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) in px of the image as stored (EXIF orientation ignored). ImtuneError if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise ImtuneError(f"image not found: {path}")
    try:
        with open(path, "rb") as f:
            head = f.read(24)
            if head[:8] == _PNG_MAGIC and head[12:16] == b"IHDR":
                return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            if head[:2] == b"\xff\xd8":
                f.seek(0)
                size = _jpeg_size(f)
                if size is not None:
                    return size
    except OSError as e:
        raise ImtuneError(f"cannot read image {path}: {e.strerror or e}") from None
    import cv2  # other formats (or odd JPEGs): decode

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # as stored, no EXIF rotation
    if img is None:
        raise ImtuneError(f"unreadable image: {path}")
    return int(img.shape[1]), int(img.shape[0])
