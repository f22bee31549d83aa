"""Stereo figures: the two images of a pair side by side with the estimator's inliers, each line coloured by
its error against the ground truth (:mod:`pipeline.viz.colors`, :mod:`pipeline.viz.gt`).

    from pipeline.viz.stereo import pair_matches, render_pair, draw_matches
    pm = pair_matches(scene, pair, conf, cache)          # the stereo task's own stages, same config and seed
    fig = render_pair(scene, pair, conf, cache, out="fountain-0000-0005.png")   # PNG + numbers
    fig = draw_matches(img1, img2, pts1, pts2, errors)   # the drawing alone (any points, any errors)

The figure is drawn at ``width`` px (default 1600; images never upscaled), on a canvas supersampled 2x and
reduced with area interpolation, so lines and dots are anti-aliased at fractional widths. At most
``max_lines`` matches are drawn (a seeded random sample; the legend says how many of how many), thinner
when there are many, blended over a desaturated image; NaN errors first, then by increasing error, so the
wrong (red) matches are on top.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.config import PipelineConfig
from pipeline.config_files import config_label  # noqa: F401  (re-exported)
from pipeline.data.scene import Pair, Scene
from pipeline.errors import ImtuneError
from pipeline.tasks.stereo import PairResult, has_ground_truth  # noqa: F401  (re-exported)
from pipeline.viz.colors import BLUE, ERROR_MAX_PX, RED, bgr, error_colors
from pipeline.viz.gt import ERROR_KINDS, match_errors
from pipeline.viz.text import fit_text, put_text, text_width

SUPERSAMPLE = 2
LAYOUTS = ("horizontal", "vertical")
TEXT = (30, 30, 30)       # BGR, dark grey
SUBTLE = (90, 90, 90)
BACKGROUND = (255, 255, 255)


# ---------------------------------------------------------------------------------------------- matches

PairMatches = PairResult  # the stereo task's own result of a pair (matches, inliers, F, R, t, record)


def pair_matches(scene: Scene, pair: Pair, conf: PipelineConfig, cache=None, estimator=None) -> PairResult:
    """One pair through the stereo task's own stages (``pipeline.tasks.stereo.evaluate_pair``: cached features
    and k-NN tables, the tentative matches every task uses, the estimator with the configured seed): its
    matches, inliers, F and record, exactly once. A pair without ground truth is drawn without pose errors."""
    from pipeline.cache import H5Cache
    from pipeline.geometry import get_estimator
    from pipeline.tasks.prepare import image_features, pair_knn
    from pipeline.tasks.stereo import evaluate_pair
    for n in (pair.i, pair.j):
        if n not in scene.images:
            raise ImtuneError(f"image {n} is not in scene {scene.name}")
    cache = cache if cache is not None else H5Cache()
    est = estimator if estimator is not None else get_estimator(conf.geometry.ransac)
    fi = image_features(cache, scene.images[pair.i], conf.feature)
    fj = image_features(cache, scene.images[pair.j], conf.feature)
    tab, knn_s = pair_knn(cache, fi, fj, conf.matching)
    return evaluate_pair(scene, pair, fi, fj, tab, knn_s, conf, est)


# ---------------------------------------------------------------------------------------------- drawing

@dataclass
class MatchFigure:
    """A drawn figure. image: (H, W, 3) uint8 BGR (``cv2.imwrite`` order); scale: figure px per working px;
    origin1, origin2: figure position of each image's top-left corner; drawn: indices of the matches drawn;
    stats: error statistics of all the matches given (not only the drawn ones)."""
    image: np.ndarray
    scale: float
    origin1: tuple[float, float]
    origin2: tuple[float, float]
    drawn: np.ndarray
    stats: dict = field(default_factory=dict)

    def to_figure(self, pts: np.ndarray, which: int) -> np.ndarray:
        """Working-resolution px of image ``which`` (1 or 2) -> figure px (pixel-centre convention)."""
        o = self.origin1 if which == 1 else self.origin2
        p = np.asarray(pts, float).reshape(-1, 2)
        return (p + 0.5) * self.scale - 0.5 + np.asarray(o, float)

    def save(self, path: str | Path) -> Path:
        return save_png(self.image, path)


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write a BGR image as PNG (atomically: temp name, then rename); ImtuneError if it cannot be written."""
    import os

    import cv2
    path = Path(path)
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise ImtuneError(f"cannot encode PNG for {path}")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)  # a file in the way, a read-only disk: the line below
        tmp.write_bytes(buf.tobytes())
        os.replace(tmp, path)
    except OSError as e:
        raise ImtuneError(f"cannot write {path}: {e.strerror or e}") from None
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _to_bgr(img: np.ndarray) -> np.ndarray:
    import cv2
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR)  # images come in RGB (load_image)
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_RGBA2BGR)
    raise ValueError(f"expected a gray or RGB image, got shape {img.shape}")


def _muted(img_bgr: np.ndarray, amount: float = 0.55, brightness: float = 0.85) -> np.ndarray:
    """Desaturate by ``amount`` and darken slightly, so coloured lines stand out."""
    import cv2
    gray = cv2.cvtColor(cv2.cvtColor(img_bgr, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    out = (1.0 - amount) * img_bgr.astype(np.float32) + amount * gray.astype(np.float32)
    return np.clip(out * brightness + 10, 0, 255).astype(np.uint8)


def line_width(n: int) -> float:
    """Line width (figure px) for n lines: thick for a few, thin for many."""
    if n <= 50:
        return 2.5
    if n <= 150:
        return 2.0
    if n <= 400:
        return 1.5
    return 1.0


def error_stats(errors: np.ndarray, max_px: float = ERROR_MAX_PX) -> dict:
    """Counts and fractions of errors <= 1 px, <= max_px, > max_px, not computable; median of the computable."""
    e = np.asarray(errors, float).reshape(-1)
    n = len(e)
    known = ~np.isnan(e)
    out = {"n": int(n), "n_known": int(known.sum()), "le1": int((e[known] <= 1.0).sum()),
           "le_max": int((e[known] <= max_px).sum()), "gt_max": int((e[known] > max_px).sum()),
           "unknown": int((~known).sum()), "max_px": float(max_px),
           "median": float(np.median(e[known])) if known.any() else None}
    return out


def _multiple(n: int, k: int) -> int:
    return int(math.ceil(n / k) * k)


def _wrap(segments: list, max_width: int, size: float, sep: str = ";  ", weight: int = 400) -> list:
    """Greedy line filling of text segments (each fitted to the width on its own)."""
    lines, cur = [], ""
    for seg in segments:
        cand = seg if not cur else cur + sep + seg
        if text_width(cand, size, weight) <= max_width:
            cur = cand
        else:
            if cur:
                lines.append(cur)
            cur = fit_text(seg, max_width, size, weight)
    if cur:
        lines.append(cur)
    return lines


def _legend(width: int, ss: int, font: float, error_kind: str, stats: dict, what: str, n_drawn: int,
            max_px: float, note: str | None) -> np.ndarray:
    """The legend band: colour bar 0..max_px, > max_px and n/a swatches, what the error is, statistics."""
    import cv2
    f = font * ss
    pad = int(0.6 * f)
    row = int(1.55 * f)
    small = 0.9 * f
    band = np.full((pad + 8 * row, width * ss, 3), BACKGROUND, np.uint8)
    x = pad
    y0 = pad + int(0.1 * f)
    bar_h = int(0.8 * f)
    base = y0 + bar_h
    x = put_text(band, "error:", x, base, f, TEXT, 600) + int(0.5 * f)
    bar_w = int(9 * f)
    ramp = error_colors(np.linspace(0.0, max_px, bar_w), max_px)
    band[y0:y0 + bar_h, x:x + bar_w] = ramp[None, :, ::-1]
    cv2.rectangle(band, (x, y0), (x + bar_w - 1, y0 + bar_h - 1), SUBTLE, max(1, ss // 2))
    ticks = [0, 1, 2, 3, 4, 5] if abs(max_px - 5.0) < 1e-9 else [0, max_px / 2, max_px]
    tick_f = 0.75 * f
    for tv in ticks:
        tx = x + int(round(tv / max_px * (bar_w - 1)))
        cv2.line(band, (tx, y0 + bar_h), (tx, y0 + bar_h + int(0.25 * f)), SUBTLE, max(1, ss // 2), cv2.LINE_AA)
        lab = f"{tv:g}"
        put_text(band, lab, tx - text_width(lab, tick_f) // 2, y0 + bar_h + int(0.25 * f) + int(tick_f), tick_f, SUBTLE)
    x += bar_w + int(0.4 * f)
    x = put_text(band, "px", x, base, f, TEXT) + int(1.0 * f)
    sw = int(0.8 * f)
    na = "not computable" + (" (no depth)" if error_kind == "depth" else "")
    for color, label in ((RED, f"> {max_px:g} px"), (BLUE, na)):
        cv2.rectangle(band, (x, y0), (x + sw, y0 + bar_h - 1), bgr(color), -1)
        cv2.rectangle(band, (x, y0), (x + sw, y0 + bar_h - 1), SUBTLE, max(1, ss // 2))
        x = put_text(band, label, x + sw + int(0.3 * f), base, f, TEXT) + int(1.0 * f)
    # further rows: what the error is, the statistics, how many lines are drawn, the note
    kind = ERROR_KINDS.get(error_kind, error_kind)
    n, k = stats["n"], stats["n_known"]
    segs = []
    if n == 0:
        segs = [kind, f"no {what} to draw"]
    elif k == 0:
        segs = [kind]
    else:
        pct = (lambda c: f"{100.0 * c / k:.0f}%")  # noqa: E731
        segs.append(f"{kind}:  {pct(stats['le1'])} ≤ 1 px,  {pct(stats['le_max'])} ≤ {max_px:g} px,  "
                    f"{pct(stats['gt_max'])} > {max_px:g} px" +
                    (f",  {stats['unknown']} not computable" if stats["unknown"] else ""))
        if stats["median"] is not None:
            segs.append(f"median {stats['median']:.2f} px")
    if n_drawn:  # how many lines: right-aligned on the first row if there is room
        d = (f"all {n} {what} drawn" if n_drawn == n else f"{n_drawn} of {n} {what} drawn (random sample)")
        right = width * ss - pad - text_width(d, small)
        if right > x:
            put_text(band, d, right, base, small, SUBTLE)
        else:
            segs.append(d)
    lines = _wrap(segs, width * ss - 2 * pad, small)
    if note:
        lines += _wrap([note], width * ss - 2 * pad, small)
    y = base + row + int(0.35 * f)
    for ln in lines[:6]:
        put_text(band, ln, pad, y, small, SUBTLE)
        y += int(1.35 * f)
    h = _multiple(y - int(1.35 * f) + pad, ss)
    return band[:h]


def _header(width: int, ss: int, font: float, lines: list) -> np.ndarray:
    """Title band: the first entry bold, the others regular. An entry is a string (fitted to the width) or a
    list of segments (wrapped onto as many lines as needed)."""
    f = font * ss
    pad = int(0.6 * f)
    row = int(1.5 * f)
    if not lines:
        return np.zeros((0, width * ss, 3), np.uint8)
    rows = []  # (text, size, weight, colour)
    for k, ln in enumerate(lines):
        size = f * (1.1 if k == 0 else 0.95)
        weight = 700 if k == 0 else 400
        segs = [str(x) for x in ln] if isinstance(ln, (list, tuple)) else [str(ln)]
        for t in _wrap(segs, width * ss - 2 * pad, size, sep="      ", weight=weight):
            rows.append((t, size, weight, TEXT if k == 0 else SUBTLE))
    band = np.full((_multiple(pad + row * len(rows) + pad // 2, ss), width * ss, 3), BACKGROUND, np.uint8)
    for k, (t, size, weight, col) in enumerate(rows):
        put_text(band, t, pad, pad + row * k + int(size), size, col, weight)
    return band


def draw_matches(image1: np.ndarray, image2: np.ndarray, pts1: np.ndarray, pts2: np.ndarray,
                 errors: np.ndarray | None = None, *, title: list | tuple | str | None = None,
                 error_kind: str = "epipolar", what: str = "inliers", max_lines: int = 200, width: int = 1600,
                 layout: str = "horizontal", max_px: float = ERROR_MAX_PX, seed: int = 0, gap: int = 8,
                 alpha: float = 0.8, note: str | None = None, font: float | None = None) -> MatchFigure:
    """Draw matches between two images, coloured by error (px; NaN = not computable, drawn blue).

    image1, image2: gray (H, W) or RGB (H, W, 3) uint8, at the resolution of the points; pts1, pts2: (M, 2) px;
    errors: (M,) px (None: all NaN); title: entries above the images (the first in bold), each a string or a
    list of segments wrapped to the width; error_kind: "depth",
    "epipolar" or "none" (the legend says which measure); what: what the lines are ("inliers", "tentative
    matches"); max_lines: at most this many lines (seeded random sample); width: figure width in px
    (horizontal: both images; vertical: the wider image; never upscaled); layout: "horizontal" (side by side)
    or "vertical" (image 1 above image 2); note: an extra legend line."""
    import cv2
    if layout not in LAYOUTS:
        raise ImtuneError(f"unknown layout {layout!r} (choose {' or '.join(LAYOUTS)})")
    p1 = np.asarray(pts1, float).reshape(-1, 2)
    p2 = np.asarray(pts2, float).reshape(-1, 2)
    if len(p1) != len(p2):
        raise ValueError(f"pts1 and pts2 differ in length ({len(p1)} vs {len(p2)})")
    e = np.full(len(p1), np.nan) if errors is None else np.asarray(errors, float).reshape(-1)
    if len(e) != len(p1):
        raise ValueError(f"errors ({len(e)}) and points ({len(p1)}) differ in length")
    a, b = _to_bgr(image1), _to_bgr(image2)
    (h1, w1), (h2, w2) = a.shape[:2], b.shape[:2]
    if layout == "horizontal":
        s = min(1.0, (width - gap) / float(w1 + w2))
        fw = int(round((w1 + w2) * s + gap))
        fh = int(round(max(h1, h2) * s))
        o1, o2 = (0.0, 0.0), (w1 * s + gap, 0.0)
    else:
        s = min(1.0, width / float(max(w1, w2)))
        fw = int(round(max(w1, w2) * s))
        fh = int(round((h1 + h2) * s + gap))
        o1 = ((fw - w1 * s) / 2.0, 0.0)
        o2 = ((fw - w2 * s) / 2.0, h1 * s + gap)
    ss = SUPERSAMPLE
    canvas = np.full((fh * ss, fw * ss, 3), BACKGROUND, np.uint8)
    for img, (ox, oy), (w, h) in ((a, o1, (w1, h1)), (b, o2, (w2, h2))):
        tw, th = max(1, int(round(w * s * ss))), max(1, int(round(h * s * ss)))
        interp = cv2.INTER_AREA if tw < w else cv2.INTER_LINEAR
        small = _muted(cv2.resize(img, (tw, th), interpolation=interp))
        x0, y0 = int(round(ox * ss)), int(round(oy * ss))
        tw, th = min(tw, canvas.shape[1] - x0), min(th, canvas.shape[0] - y0)
        canvas[y0:y0 + th, x0:x0 + tw] = small[:th, :tw]
    # which matches, in which order
    m = len(p1)
    idx = np.arange(m)
    if m > max_lines > 0:
        idx = np.sort(np.random.default_rng(seed).choice(m, size=max_lines, replace=False))
    elif max_lines <= 0:
        idx = idx[:0]
    key = np.where(np.isnan(e[idx]), -1.0, np.nan_to_num(e[idx], posinf=1e30))
    idx = idx[np.argsort(key, kind="stable")]
    fig = MatchFigure(image=canvas, scale=s, origin1=o1, origin2=o2, drawn=idx,
                      stats=error_stats(e, max_px))
    q1 = (fig.to_figure(p1[idx], 1) + 0.5) * ss - 0.5  # figure px -> supersampled canvas px
    q2 = (fig.to_figure(p2[idx], 2) + 0.5) * ss - 0.5
    cols = error_colors(e[idx], max_px)
    lw = line_width(len(idx))
    thick = max(1, int(round(lw * ss)))
    radius = max(2 * ss, int(round(1.3 * lw * ss)))
    SH = 4  # fixed-point bits of the coordinates (sub-pixel precision)
    sc = float(1 << SH)
    overlay = canvas.copy()
    for (x1, y1), (x2, y2), c in zip(q1, q2, cols):
        cv2.line(overlay, (int(round(x1 * sc)), int(round(y1 * sc))), (int(round(x2 * sc)), int(round(y2 * sc))),
                 bgr(c), thick, cv2.LINE_AA, SH)
    cv2.addWeighted(overlay, alpha, canvas, 1.0 - alpha, 0.0, dst=canvas)
    outline = (20, 20, 20)
    for q in (q1, q2):
        for (x, y), c in zip(q, cols):
            ctr = (int(round(x * sc)), int(round(y * sc)))
            cv2.circle(canvas, ctr, int((radius + max(1, ss // 2)) * sc), outline, -1, cv2.LINE_AA, SH)
            cv2.circle(canvas, ctr, int(radius * sc), bgr(c), -1, cv2.LINE_AA, SH)
    font = font if font is not None else max(13.0, min(24.0, fw / 68.0))
    lines = [title] if isinstance(title, str) else list(title or [])
    head = _header(fw, ss, font, lines)
    leg = _legend(fw, ss, font, error_kind, fig.stats, what, len(idx), max_px, note)
    full = np.vstack([head, canvas, leg])
    out_h = full.shape[0] // ss
    full = cv2.resize(full[:out_h * ss], (fw, out_h), interpolation=cv2.INTER_AREA)
    dy = head.shape[0] / ss
    fig.image = full
    fig.origin1 = (o1[0], o1[1] + dy)
    fig.origin2 = (o2[0], o2[1] + dy)
    return fig


# ---------------------------------------------------------------------------------------------- one pair

def _deg(v) -> str:
    if v is None or not math.isfinite(float(v)):
        return "∞"
    v = float(v)
    return f"{v:.2f}°" if v < 10 else f"{v:.1f}°"


def pair_title(scene_name: str, pair: Pair, rec: dict, label: str | None = None) -> list:
    """Title of a stereo figure: [segments of the first (bold) entry: the pair; NI and NM; the pose errors or
    the failure], then the configuration (and co-visibility) — see ``draw_matches``' ``title``."""
    head = [f"{scene_name}:  {pair.i}  |  {pair.j}", f"NI {rec.get('NI', 0)} of NM {rec.get('NM', 0)}"]
    if rec.get("failure"):
        head.append(f"FAILED: {rec['failure']}")
    elif rec.get("no_ground_truth"):
        head.append("no ground truth: pose error not computable")
    else:
        head.append(f"pose error  R {_deg(rec.get('err_R'))}   t {_deg(rec.get('err_t'))}")
    lines: list = [head]
    sub = []
    if label:
        sub.append(label)
    if pair.covisibility is not None:
        sub.append(f"co-visibility {pair.covisibility:.2f}")
    if sub:
        lines.append(sub)
    return lines


def load_pair_images(scene: Scene, pair: Pair, pm: PairResult, max_side: int) -> tuple[np.ndarray, np.ndarray]:
    """The pair's two images in colour (RGB) at the working resolution of ``pm``'s keypoints."""
    import cv2

    from pipeline.data.resize import load_image
    out = []
    for name, (w, h) in zip((pair.i, pair.j), pm.sizes):
        img, _, _ = load_image(scene.images[name].path, max_side=max_side, gray=False)
        if img.shape[1] != w or img.shape[0] != h:
            img = cv2.resize(img, (int(w), int(h)), interpolation=cv2.INTER_AREA)
        out.append(img)
    return out[0], out[1]


def render_pair(scene: Scene, pair: Pair, conf: PipelineConfig, cache=None, out: str | Path | None = None, *,
                width: int = 1600, max_lines: int = 200, layout: str = "horizontal", label: str | None = None,
                use_depth: bool = True, estimator=None, seed: int = 0, pm: PairMatches | None = None) -> dict:
    """Draw one pair for one configuration (and write it as PNG when ``out`` is given).

    Lines are the estimator's inliers; when the estimator failed, the tentative matches instead (the legend
    says so). ``pm``: the pair's :class:`PairResult` when the caller has it (an evaluation with ``keep_pairs``):
    nothing is recomputed. Returns a dict: the stereo record's numbers (NM, NI, err, err_R, err_t in degrees, failure),
    ``error_kind`` ("depth" | "epipolar" | "none"), ``stats`` of the errors, ``png`` (path or None) and
    ``figure`` (the :class:`MatchFigure`)."""
    pm = pm if pm is not None else pair_matches(scene, pair, conf, cache, estimator)
    rec = pm.record
    if pm.F is not None and pm.inliers.any():
        sel, what = pm.inliers, "inliers"
    else:
        sel, what = np.ones(len(pm.pts1), bool), "tentative matches"
    p1, p2 = pm.pts1[sel], pm.pts2[sel]
    if pm.K1 is not None and pm.K2 is not None:
        errors, kind = match_errors(scene, pair, p1, p2, pm.K1, pm.K2, pm.sizes, use_depth=use_depth)
    else:
        errors, kind = np.full(len(p1), np.nan), "none"
    img1, img2 = load_pair_images(scene, pair, pm, conf.feature.max_side)
    note = None
    if what != "inliers":
        why = rec.get("failure") or "no model"
        note = f"no inliers ({why}): the lines are the tentative matches"
    fig = draw_matches(img1, img2, p1, p2, errors, title=pair_title(scene.name, pair, rec, label or config_label(conf)),
                       error_kind=kind, what=what, max_lines=max_lines, width=width, layout=layout, seed=seed,
                       note=note)
    png = fig.save(out) if out is not None else None
    keys = ("NM", "NI", "err", "err_R", "err_t", "failure", "covisibility", "no_ground_truth")
    return {"scene": scene.name, "pair": pair.key, **{k: rec.get(k) for k in keys}, "error_kind": kind,
            "what": what, "stats": fig.stats, "png": str(png) if png is not None else None, "figure": fig}
