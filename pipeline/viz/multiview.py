"""Multiview figures (the paper's): every image of a reconstructed bag with its keypoints, blue where the
keypoint is in the 3D model (it observes a triangulated point), red where it is not.

    from pipeline.viz.multiview import reconstruct_bag, draw_bag, draw_keypoints, model_keypoint_masks
    bag = reconstruct_bag(job)          # a pipeline.tasks.multiview.BagJob -> record + per-image masks
    img = draw_bag(bag, title="...")    # BGR montage (cv2.imwrite order)
    img = draw_keypoints(image, keypoints, in_model)   # one image

The bag is run by the multiview task's own ``run_bag`` (same database, verification, mapper and model choice:
the model with most registered images), its models kept in a temporary folder just long enough to read
which keypoint of which image has a 3D point. Keypoints are the ones written to COLMAP, in the same order.
"""
from __future__ import annotations

import dataclasses
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ImtuneError
from pipeline.viz.colors import IN_MODEL, NOT_IN_MODEL, bgr
from pipeline.viz.text import fit_text, put_text

SUPERSAMPLE = 2
TEXT = (30, 30, 30)
SUBTLE = (90, 90, 90)
BACKGROUND = (255, 255, 255)


@dataclass
class BagReconstruction:
    """A reconstructed bag. record: the multiview task's bag record (success, NL, TL, RC, errors, ATE, ...);
    names: the bag's images; keypoints: name -> (n, 2) px at the working resolution; masks: name -> (n,) bool,
    True where the keypoint is in the 3D model, None for an image the model did not register; paths: name ->
    image file; image_sizes: name -> (w, h) working px; max_side: the working resolution's long side."""
    record: dict
    names: list
    keypoints: dict
    masks: dict
    paths: dict
    image_sizes: dict
    max_side: int = 1024


def model_keypoint_masks(model, keypoints: dict) -> dict:
    """name -> (n,) bool mask of the keypoints with a 3D point in ``model`` (a pycolmap.Reconstruction), None
    for images the model does not register. ``keypoints``: name -> (n, 2) array (only n is used)."""
    by_name = {}
    for iid in model.reg_image_ids():
        im = model.image(iid)
        by_name[im.name] = im
    out: dict[str, np.ndarray | None] = {}
    for name, k in keypoints.items():
        n = len(np.asarray(k).reshape(-1, 2))
        im = by_name.get(name)
        if im is None:
            out[name] = None
            continue
        mask = np.zeros(n, bool)
        idx = np.asarray(list(im.get_observation_point2D_idxs()), np.int64)
        idx = idx[(idx >= 0) & (idx < n)]
        mask[idx] = True
        out[name] = mask
    return out


def _largest_in(folder: Path):
    from pipeline.colmap_db import largest_model, read_model
    models = {}
    for k, d in enumerate(sorted(p for p in folder.glob("*/sparse/*") if p.is_dir())):
        try:
            models[k] = read_model(d)
        except ImtuneError:
            continue
    models = {k: m for k, m in models.items() if m.num_reg_images() > 0}
    return largest_model(models)


def reconstruct_bag(job, max_side: int = 1024) -> BagReconstruction:
    """Run one bag (a ``pipeline.tasks.multiview.BagJob``) with the multiview task's ``run_bag`` and read which
    keypoints are in its largest model. A failed bag raises a one-line ImtuneError with COLMAP's reason."""
    from pipeline.tasks.multiview import run_bag
    label = f"bag {job.scene} size {job.size} #{job.index}"
    with tempfile.TemporaryDirectory(prefix="imtune-viz-bag-") as tmp:
        rec = run_bag(dataclasses.replace(job, workdir=tmp, keep=True))
        if not rec.get("success"):
            raise ImtuneError(f"{label} failed: {rec.get('failure') or 'no model'} (nothing to draw)")
        model = _largest_in(Path(tmp))
        if model is None:
            raise ImtuneError(f"{label}: the reconstruction succeeded but its model could not be read back")
        masks = model_keypoint_masks(model, job.keypoints)
    return BagReconstruction(record=rec, names=list(job.names), keypoints=dict(job.keypoints), masks=masks,
                             paths=dict(job.paths), image_sizes=dict(job.image_sizes), max_side=max_side)


def _to_bgr(img):
    from pipeline.viz.stereo import _muted
    from pipeline.viz.stereo import _to_bgr as conv
    return _muted(conv(img), amount=0.6, brightness=0.9)


def keypoint_radius(n_points: int, panel_width: int) -> float:
    """Dot radius (px in the output) for n keypoints on a panel ``panel_width`` px wide."""
    dens = n_points / max(1.0, panel_width / 500.0) ** 2
    if dens <= 500:
        return 2.6
    if dens <= 2000:
        return 2.0
    if dens <= 5000:
        return 1.6
    return 1.3


def draw_keypoints(image: np.ndarray, keypoints: np.ndarray, in_model: np.ndarray | None, *, width: int = 640,
                   caption: str | None = None, radius: float | None = None, font: float | None = None) -> np.ndarray:
    """One image with its keypoints: blue where ``in_model`` is True, red elsewhere (all red and "not
    registered" when ``in_model`` is None). image: gray or RGB uint8 at the keypoints' resolution;
    keypoints: (n, 2) px; width: output width in px (never upscaled); caption: a line under the image
    (default: "k of n keypoints in the 3D model (p%)"). Returns BGR uint8."""
    import cv2
    k = np.asarray(keypoints, float).reshape(-1, 2)
    mask = None if in_model is None else np.asarray(in_model, bool).reshape(-1)
    if mask is not None and len(mask) != len(k):
        raise ValueError(f"in_model has {len(mask)} entries for {len(k)} keypoints")
    img = _to_bgr(image)
    h, w = img.shape[:2]
    s = min(1.0, width / float(w))
    ow, oh = max(1, int(round(w * s))), max(1, int(round(h * s)))
    ss = SUPERSAMPLE
    canvas = cv2.resize(img, (ow * ss, oh * ss), interpolation=cv2.INTER_AREA if ow * ss < w else cv2.INTER_LINEAR)
    r = radius if radius is not None else keypoint_radius(len(k), ow)
    SH = 4
    sc = float(1 << SH)
    q = (k + 0.5) * s * ss - 0.5  # working px -> supersampled canvas px (pixel-centre convention)
    rad = int(round(r * ss * sc))
    edge = int(round((r + 0.6) * ss * sc))
    groups = [(np.ones(len(k), bool) if mask is None else ~mask, NOT_IN_MODEL)]
    if mask is not None:
        groups.append((mask, IN_MODEL))  # in-model points on top
    for sel, col in groups:
        for x, y in q[sel]:
            c = (int(round(x * sc)), int(round(y * sc)))
            cv2.circle(canvas, c, edge, (255, 255, 255), -1, cv2.LINE_AA, SH)
        for x, y in q[sel]:
            c = (int(round(x * sc)), int(round(y * sc)))
            cv2.circle(canvas, c, rad, bgr(col), -1, cv2.LINE_AA, SH)
    canvas = cv2.resize(canvas, (ow, oh), interpolation=cv2.INTER_AREA)
    if caption is None:
        if mask is None:
            caption = f"not registered · {len(k)} keypoints"
        else:
            n_in = int(mask.sum())
            caption = f"{n_in} of {len(k)} keypoints in the 3D model ({100.0 * n_in / max(1, len(k)):.0f}%)"
    f = font if font is not None else max(12.0, min(18.0, ow / 32.0))
    band = np.full((int(1.7 * f), ow, 3), BACKGROUND, np.uint8)
    put_text(band, fit_text(caption, ow - 8, f), 4, int(1.25 * f), f, TEXT)
    return np.vstack([canvas, band])


def bag_title(rec: dict, label: str | None = None) -> list[str]:
    """Title lines of a bag figure: scene, bag, registered images, NL, TL, mAA, ATE; then the configuration."""
    from pipeline.metrics.pose import mean_average_accuracy
    names = rec.get("images", [])
    reg = rec.get("registered", [])
    parts = [f"{rec.get('scene')}:  bag of {rec.get('bag_size')} (#{rec.get('bag')})",
             f"registered {len(reg)}/{len(names)}", f"NL {rec.get('NL', 0)} points",
             f"TL {float(rec.get('TL', 0)):.2f}"]
    errs = rec.get("errors") or []
    if errs:
        parts.append(f"mAA(10°) {mean_average_accuracy(errs, 10):.3f}")
    ate = rec.get("ATE")
    if ate is not None and math.isfinite(float(ate)):
        parts.append(f"ATE {float(ate):.3g}")
    lines = ["    ".join(parts)]
    if label:
        lines.append(label)
    return lines


def draw_bag(bag: BagReconstruction, *, title: list | str | None = None, label: str | None = None,
             panel_width: int = 520, columns: int | None = None, images: dict | None = None,
             max_width: int = 2200) -> np.ndarray:
    """A montage of the bag's images with their keypoints (blue: in the 3D model; red: not), a title
    (default :func:`bag_title`) and a legend. images: name -> image (default: read from ``bag.paths`` at the
    working resolution); panel_width: px per image, reduced so that the montage is at most ``max_width`` px
    wide (5 columns for bags of more than 6 images, 3 for 5-6). Returns BGR uint8."""
    import cv2

    from pipeline.data.resize import load_image
    names = list(bag.names)
    cols = columns or min(len(names), 5 if len(names) > 6 else (3 if len(names) > 4 else len(names)))
    cols = max(1, cols)
    panel_width = int(min(panel_width, (max_width - 8 * (cols - 1)) / cols))  # the montage stays <= max_width
    panels = []
    for n in names:
        if images is not None and n in images:
            img = images[n]
        else:
            img, _, _ = load_image(bag.paths[n], max_side=bag.max_side, gray=False)
        w, h = bag.image_sizes.get(n, (img.shape[1], img.shape[0]))
        if (img.shape[1], img.shape[0]) != (w, h):
            img = cv2.resize(img, (int(w), int(h)), interpolation=cv2.INTER_AREA)
        kp = bag.keypoints[n]
        m = bag.masks.get(n)
        cap = (f"{n}: not registered · {len(kp)} keypoints" if m is None else
               f"{n}: {int(m.sum())} of {len(kp)} in the model ({100.0 * m.sum() / max(1, len(kp)):.0f}%)")
        panels.append(draw_keypoints(img, kp, m, width=panel_width, caption=cap))
    from pipeline.viz.compose import grid
    body = grid(panels, cols, gap=8)
    fw = body.shape[1]
    f = max(14.0, min(22.0, fw / 70.0))
    lines = [title] if isinstance(title, str) else list(title or bag_title(bag.record, label))
    head = np.full((int(0.6 * f) + int(1.5 * f) * len(lines) + int(0.3 * f), fw, 3), BACKGROUND, np.uint8)
    for k, ln in enumerate(lines):
        size = f * (1.1 if k == 0 else 0.95)
        weight = 700 if k == 0 else 400
        put_text(head, fit_text(ln, fw - 16, size, weight), 8, int(0.6 * f) + int(1.5 * f) * k + int(size),
                 size, TEXT if k == 0 else SUBTLE, weight)
    leg = np.full((int(2.0 * f), fw, 3), BACKGROUND, np.uint8)
    x = 8
    cy = int(0.95 * f)
    for col, lab in ((IN_MODEL, "keypoint in the 3D model (observes a triangulated point)"),
                     (NOT_IN_MODEL, "keypoint not in the model")):
        cv2.circle(leg, (x + int(0.4 * f), cy), int(0.35 * f), bgr(col), -1, cv2.LINE_AA)
        x = put_text(leg, lab, x + int(1.0 * f), cy + int(0.35 * f), 0.9 * f, TEXT) + int(1.2 * f)
    return np.vstack([head, body, leg])


def bag_stats(bag: BagReconstruction) -> dict:
    """Per image: keypoints, keypoints in the model, registered."""
    out = {}
    for n in bag.names:
        m = bag.masks.get(n)
        out[n] = {"keypoints": int(len(bag.keypoints[n])), "in_model": int(m.sum()) if m is not None else 0,
                  "registered": m is not None}
    return out
