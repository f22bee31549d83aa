"""IMC resizing convention (working size, K scaling, pixel-centre convention) and image-file checks."""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.data.imagefile import check_image_file, image_size, jpeg_end
from pipeline.data.resize import load_image, scale_points, scaled_K, working_size
from pipeline.errors import ImtuneError


def _shared() -> Path:
    env = os.environ.get("IMTUNE_SHARED")
    if env:
        return Path(env) / "data" if (Path(env) / "data").is_dir() else Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def _jpeg(path: Path, w: int = 64, h: int = 48, seed: int = 0) -> Path:
    img = np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)
    assert cv2.imwrite(str(path), img)
    return path


@pytest.mark.parametrize("w,h,max_side,expected", [
    (1536, 1024, 1024, (1024, 683)),
    (1024, 2048, 1024, (512, 1024)),
    (800, 600, 1024, (800, 600)),       # never upscaled
    (1024, 768, 1024, (1024, 768)),
    (3000, 2000, None, (3000, 2000)),   # no limit
    (1296, 968, 640, (640, 478)),
])
def test_working_size(w, h, max_side, expected):
    w2, h2, sx, sy = working_size(w, h, max_side)
    assert (w2, h2) == expected
    assert max(w2, h2) <= (max_side or max(w, h))
    assert sx == pytest.approx(w2 / w) and sy == pytest.approx(h2 / h)


def test_working_size_rejects_bad_size():
    with pytest.raises(ImtuneError):
        working_size(0, 10)


def test_scaled_K_halving_matches_readme_convention():
    K = np.array([[2759.48, 0.3, 1520.69], [0, 2764.16, 1006.81], [0, 0, 1]])
    K2 = scaled_K(K, 0.5, 0.5)
    assert K2[0, 0] == pytest.approx(1379.74) and K2[1, 1] == pytest.approx(1382.08)
    assert K2[0, 1] == pytest.approx(0.15)
    assert K2[0, 2] == pytest.approx(1520.69 / 2 - 0.25) and K2[1, 2] == pytest.approx(1006.81 / 2 - 0.25)
    np.testing.assert_array_equal(scaled_K(K, 1.0, 1.0), K)


def test_scaled_K_is_consistent_with_resized_pixel_coordinates():
    rng = np.random.default_rng(1)
    K = np.array([[900.0, 1.5, 640.2], [0, 880.0, 470.9], [0, 0, 1]])
    X = rng.uniform([-2, -2, 4], [2, 2, 9], (50, 3))
    x = (K @ X.T).T
    x = x[:, :2] / x[:, 2:]
    sx, sy = 1024 / 1296, 765 / 968
    x2 = (scaled_K(K, sx, sy) @ X.T).T
    np.testing.assert_allclose(x2[:, :2] / x2[:, 2:], scale_points(x, sx, sy), atol=1e-9)


def test_pixel_centre_convention_matches_cv2_inter_area():
    """A blob's centroid moves exactly as (x + 0.5) * s - 0.5 under INTER_AREA downsampling by 2."""
    h, w, (cx, cy) = 96, 128, (40.3, 25.7)
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 3.0 ** 2))
    small = cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    ys, xs = np.mgrid[0:h // 2, 0:w // 2]
    got = np.array([(small * xs).sum(), (small * ys).sum()]) / small.sum()
    np.testing.assert_allclose(got, scale_points(np.array([[cx, cy]]), 0.5, 0.5)[0], atol=1e-6)


def test_load_image_resizes_with_area_and_reports_scales(tmp_path):
    p = _jpeg(tmp_path / "a.jpg", 1536, 1024)
    img, sx, sy = load_image(p)
    assert img.shape == (683, 1024) and img.dtype == np.uint8
    assert (sx, sy) == (1024 / 1536, 683 / 1024)
    rgb, _, _ = load_image(p, max_side=None, gray=False)
    assert rgb.shape == (1024, 1536, 3)
    bgr = cv2.imread(str(p))
    np.testing.assert_array_equal(rgb, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))


def test_load_image_missing_empty_garbage(tmp_path):
    with pytest.raises(ImtuneError, match="nope.jpg"):
        load_image(tmp_path / "nope.jpg")
    (tmp_path / "empty.jpg").write_bytes(b"")
    with pytest.raises(ImtuneError, match="empty.jpg"):
        load_image(tmp_path / "empty.jpg")
    (tmp_path / "garbage.jpg").write_bytes(b"this is not an image at all" * 10)
    with pytest.raises(ImtuneError, match="garbage.jpg"):
        load_image(tmp_path / "garbage.jpg")


def test_truncated_jpeg_is_rejected_although_cv2_decodes_it(tmp_path):
    data = _jpeg(tmp_path / "full.jpg", 320, 240).read_bytes()
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(data[: len(data) // 2])
    assert cv2.imread(str(cut)) is not None  # OpenCV silently decodes half an image: the check must catch it
    with pytest.raises(ImtuneError, match="cut.jpg"):
        load_image(cut)
    with pytest.raises(ImtuneError, match="cut.jpg"):
        check_image_file(cut)
    assert jpeg_end(data) == len(data)


def test_truncated_real_jpeg(tmp_path):
    src = _shared() / "strecha" / "fountain-P11" / "images" / "0000.jpg"
    if not src.is_file():
        pytest.skip(f"shared data not found at {src.parent} (set IMTUNE_SHARED)")
    data = src.read_bytes()
    cut = tmp_path / "0000.jpg"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImtuneError, match="0000.jpg"):
        load_image(cut)


def test_jpeg_with_trailer_after_eoi_is_accepted(tmp_path):
    p = _jpeg(tmp_path / "t.jpg")
    p.write_bytes(p.read_bytes() + b"APPENDED-METADATA" * 5)
    check_image_file(p)
    img, _, _ = load_image(p)
    assert img.shape == (48, 64)


def test_png_checks_and_sizes(tmp_path):
    p = tmp_path / "a.png"
    cv2.imwrite(str(p), np.zeros((30, 50), np.uint8))
    assert image_size(p) == (50, 30)
    check_image_file(p)
    assert load_image(p)[0].shape == (30, 50)
    cut = tmp_path / "cut.png"
    cut.write_bytes(p.read_bytes()[:-20])
    with pytest.raises(ImtuneError, match="cut.png"):
        check_image_file(cut)
    with pytest.raises(ImtuneError, match="cut.png"):
        load_image(cut)


def test_image_size_reads_jpeg_header(tmp_path):
    p = _jpeg(tmp_path / "s.jpg", 77, 33)
    assert image_size(p) == (77, 33)
    with pytest.raises(ImtuneError, match="missing.jpg"):
        image_size(tmp_path / "missing.jpg")
