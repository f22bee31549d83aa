"""Keypoint detectors for the composed (detector + affine shape + orientation + descriptor) features.

Every detector returns :class:`Detections`: centres (px, working resolution, pixel-centre convention),
a characteristic scale ``sigma`` (px), an optional orientation (OpenCV ``KeyPoint.angle`` degrees) and a
response, strongest first, at most the budget. ``frame_mult`` is the half-size, in sigmas, of the frame
on which affine shape and orientation are estimated (kornia's convention: 6 sigma for scale-space
detectors; Key.Net's own frames, which we call 12 sigma).

- ``dog``: OpenCV's SIFT detector (difference of Gaussians, 3 layers per octave, doubled image; the
  lowered contrast threshold of the paper with ``low_threshold``), the DoG of the paper's DoG-* rows; its
  SIFT orientations (gradient histogram, several per location) are kept when nothing re-estimates them.
- ``hessian``: determinant-of-Hessian extrema in scale space (3x3x3), scale-normalised (sigma^4 det H)
  — VLFeat's "Hessian" (the paper's VL-Hess rows).
- ``hessian-laplace`` / ``harris-laplace``: spatial maxima of det H (resp. the scale-normalised Harris
  measure, integration scale 1.4 x differentiation scale, k = 0.04) at each level whose scale-normalised
  Laplacian |sigma^2 (Lxx + Lyy)| is a maximum over the adjacent levels (Mikolajczyk & Schmid's
  characteristic-scale selection).
- ``keynet``: Key.Net (kornia ``KeyNetDetector``: learned + hand-crafted filters on a 3-level pyramid).

The three scale-space detectors are written here on OpenCV Gaussian blurs and numpy rather than with
kornia's ``ScaleSpaceDetector`` (+ ``BlobHessian`` / ``CornerHarris``): that generic implementation took
9-14 s per 1024 px image on this 2-core CPU at 8k features (its 3-D NMS and soft-argmax dominate),
these take a fraction of a second.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import cv2
import numpy as np

from pipeline.errors import ImtuneError


@dataclass
class Detections:
    """xy (N, 2) float32 px; sigma (N,) px; angle (N,) OpenCV degrees or None; response (N,)."""
    xy: np.ndarray
    sigma: np.ndarray
    angle: np.ndarray | None
    response: np.ndarray

    def __len__(self) -> int:
        return int(len(self.xy))

    @classmethod
    def empty(cls) -> Detections:
        z = np.zeros(0, np.float32)
        return cls(np.zeros((0, 2), np.float32), z, None, z.copy())


class Detector:
    """Base class: ``option_defaults`` / ``option_bounds`` join the composed extractor's options."""
    name: ClassVar[str] = ""
    weights: ClassVar[tuple[str, ...]] = ()
    option_defaults: ClassVar[dict[str, Any]] = {}
    option_bounds: ClassVar[dict[str, str]] = {}
    frame_mult: ClassVar[float] = 6.0
    #: the detector assigns orientations itself (kept unless an affine or orientation step re-estimates)
    gives_orientation: ClassVar[bool] = False
    description: ClassVar[str] = ""

    def __init__(self, opts: dict[str, Any], low_threshold: bool, feature_name: str):
        self.opts = opts
        self.low_threshold = low_threshold
        self.feature_name = feature_name

    def detect(self, image: np.ndarray, k: int, dedupe: bool = False, refill: bool = False) -> Detections:
        """At most ``k`` detections, strongest first. ``dedupe``: one detection per (x, y, scale)
        (orientation duplicates removed); ``refill``: de-duplicate before the budget cut."""
        raise NotImplementedError


# --------------------------------------------------------------------------------------------- DoG

class DoG(Detector):
    name = "dog"
    gives_orientation = True
    description = "DoG (OpenCV SIFT detector)"
    option_defaults = {"contrast_threshold": None, "edge_threshold": 10.0, "n_octave_layers": 3, "sigma": 1.6}
    option_bounds = {"contrast_threshold": ">=0", "edge_threshold": ">0", "n_octave_layers": ">=1", "sigma": ">0"}

    def __init__(self, opts, low_threshold, feature_name):
        super().__init__(opts, low_threshold, feature_name)
        from pipeline.features.sift import make_sift_detector
        self.sift = make_sift_detector(opts, low_threshold)

    def detect(self, image, k, dedupe=False, refill=False):
        from pipeline.features._opencv import _kp_arrays, rank_keypoints
        from pipeline.features.sift import sift_pixel_centre
        xy, size, angle, resp, _, _ = _kp_arrays(self.sift.detect(image, None))
        if len(xy) == 0:
            return Detections.empty()
        order = rank_keypoints(xy, size, angle, resp, k, upright=dedupe, refill=refill)[:k]
        xy = sift_pixel_centre(xy)  # OpenCV's +0.25 px (its doubled octave -1) undone: patches cut where they belong
        return Detections(xy[order].astype(np.float32), (size[order] / 2).astype(np.float32),
                          angle[order].astype(np.float32), resp[order].astype(np.float32))


# ------------------------------------------------------------------------ Hessian / Harris-Laplace

def _second_derivatives(L: np.ndarray):
    """Central second differences (Lxx, Lyy, Lxy), zero on the one-pixel border."""
    c = L[1:-1, 1:-1]
    lxx = np.zeros_like(L)
    lyy = np.zeros_like(L)
    lxy = np.zeros_like(L)
    lxx[1:-1, 1:-1] = L[1:-1, 2:] + L[1:-1, :-2] - 2 * c
    lyy[1:-1, 1:-1] = L[2:, 1:-1] + L[:-2, 1:-1] - 2 * c
    lxy[1:-1, 1:-1] = 0.25 * (L[2:, 2:] - L[2:, :-2] - L[:-2, 2:] + L[:-2, :-2])
    return lxx, lyy, lxy


def _harris(L: np.ndarray, sigma_d: float, k: float) -> np.ndarray:
    """Scale-normalised Harris measure det(M) - k tr(M)^2, M = sigma_d^2 G(1.4 sigma_d) * [gradients]."""
    lx = np.zeros_like(L)
    ly = np.zeros_like(L)
    lx[:, 1:-1] = 0.5 * (L[:, 2:] - L[:, :-2])
    ly[1:-1, :] = 0.5 * (L[2:, :] - L[:-2, :])
    si = 1.4 * sigma_d
    s2 = np.float32(sigma_d * sigma_d)
    a = cv2.GaussianBlur(lx * lx, (0, 0), si) * s2
    b = cv2.GaussianBlur(ly * ly, (0, 0), si) * s2
    c = cv2.GaussianBlur(lx * ly, (0, 0), si) * s2
    tr = a + b
    return a * b - c * c - np.float32(k) * tr * tr


def _peak_offset(m: np.ndarray, c: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Vertex offset of the parabola through (-1, m), (0, c), (1, p), clipped to [-0.5, 0.5]."""
    den = m - 2 * c + p
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < 0, 0.5 * (m - p) / den, 0.0)
    return np.clip(np.nan_to_num(off), -0.5, 0.5)


class ScaleSpace(Detector):
    """Hessian / Hessian-Laplace / Harris-Laplace on a SIFT-like Gaussian scale space."""
    kind: ClassVar[str] = "hessian"
    option_defaults = {"n_octave_layers": 3, "sigma": 1.6, "double_image": True, "threshold": None,
                       "harris_k": 0.04}
    option_bounds = {"n_octave_layers": ">=1", "sigma": ">0", "threshold": ">=0", "harris_k": "0..0.25"}
    #: response threshold without ``low_threshold`` (scale-normalised responses on a [0, 1] image);
    #: with it, any positive peak counts and the budget keeps the strongest.
    default_threshold: ClassVar[float] = 3e-4  # ~5k peaks on a 1024 px Strecha image
    border: ClassVar[int] = 5

    def _response(self, L: np.ndarray, sig: float):
        lxx, lyy, lxy = _second_derivatives(L)
        s2 = np.float32(sig * sig)
        lap = np.abs(lxx + lyy) * s2 if self.kind != "hessian" else None
        if self.kind == "harris-laplace":
            return _harris(L, sig, float(self.opts["harris_k"])), lap
        return (lxx * lyy - lxy * lxy) * (s2 * s2), lap

    def detect(self, image, k, dedupe=False, refill=False):
        o = self.opts
        n = int(o["n_octave_layers"])
        sigma0 = float(o["sigma"])
        thr = o["threshold"]
        thr = (1e-12 if self.low_threshold else self.default_threshold) if thr is None else float(thr)
        img = image.astype(np.float32) * np.float32(1 / 255)
        double = bool(o["double_image"])
        if double:
            img = cv2.resize(img, (2 * img.shape[1], 2 * img.shape[0]), interpolation=cv2.INTER_LINEAR)
        blur0 = 1.0 if double else 0.5
        base = cv2.GaussianBlur(img, (0, 0), math.sqrt(max(sigma0 ** 2 - blur0 ** 2, 1e-4)))
        nlev = n + 2  # levels 0 .. n+1; detection on 1 .. n
        sig = [sigma0 * 2 ** (s / n) for s in range(nlev)]
        inc = [0.0] + [math.sqrt(sig[s] ** 2 - sig[s - 1] ** 2) for s in range(1, nlev)]
        kernel = np.ones((3, 3), np.uint8)
        b = self.border
        xs_all, ys_all, sg_all, r_all = [], [], [], []
        octave, oct_idx = base, 0
        while min(octave.shape) >= 2 * b + 8:
            levels = [octave]
            for s in range(1, nlev):
                levels.append(cv2.GaussianBlur(levels[-1], (0, 0), inc[s]))
            resp, lap = zip(*(self._response(L, sig[s]) for s, L in enumerate(levels)))
            dil = [cv2.dilate(r, kernel) for r in resp]
            h, w = octave.shape
            for s in range(1, n + 1):
                r = resp[s]
                cand = (r >= dil[s]) & (r > thr)
                if self.kind == "hessian":
                    cand &= (r >= dil[s - 1]) & (r >= dil[s + 1])
                else:
                    cand &= (lap[s] > lap[s - 1]) & (lap[s] > lap[s + 1])
                cand[:b] = False
                cand[-b:] = False
                cand[:, :b] = False
                cand[:, -b:] = False
                yy, xx = np.nonzero(cand)
                if len(yy) == 0:
                    continue
                c = r[yy, xx]
                dx = _peak_offset(r[yy, xx - 1], c, r[yy, xx + 1])
                dy = _peak_offset(r[yy - 1, xx], c, r[yy + 1, xx])
                if self.kind == "hessian":
                    ds = _peak_offset(resp[s - 1][yy, xx], c, resp[s + 1][yy, xx])
                else:
                    ds = _peak_offset(lap[s - 1][yy, xx], lap[s][yy, xx], lap[s + 1][yy, xx])
                f = 2.0 ** oct_idx
                u = (xx + dx) * f  # base-image coordinates
                v = (yy + dy) * f
                if double:
                    u, v = u * 0.5 - 0.25, v * 0.5 - 0.25
                xs_all.append(u)
                ys_all.append(v)
                sg_all.append(sigma0 * 2 ** ((s + ds) / n) * f / (2.0 if double else 1.0))
                r_all.append(c)
            octave = levels[n][::2, ::2]
            oct_idx += 1
        if not xs_all:
            return Detections.empty()
        xy = np.stack([np.concatenate(xs_all), np.concatenate(ys_all)], 1).astype(np.float32)
        sigma = np.concatenate(sg_all).astype(np.float32)
        resp = np.concatenate(r_all).astype(np.float32)
        order = np.lexsort((sigma, xy[:, 1], xy[:, 0], -resp))[:k]  # deterministic ties
        return Detections(xy[order], sigma[order], None, resp[order])


class Hessian(ScaleSpace):
    name = "hessian"
    kind = "hessian"
    description = "Hessian (det-of-Hessian scale-space extrema)"


class HessianLaplace(ScaleSpace):
    name = "hessian-laplace"
    kind = "hessian-laplace"
    description = "Hessian-Laplace (det-of-Hessian peaks, Laplacian scale selection)"


class HarrisLaplace(ScaleSpace):
    name = "harris-laplace"
    kind = "harris-laplace"
    description = "Harris-Laplace (Harris peaks, Laplacian scale selection)"
    default_threshold = 1e-8  # ~3k peaks on a 1024 px Strecha image


# ----------------------------------------------------------------------------------------- Key.Net

class KeyNet(Detector):
    name = "keynet"
    weights = ("keynet",)
    frame_mult = 12.0
    description = "Key.Net (kornia KeyNetDetector)"
    option_defaults = {"score_threshold": 0.0}
    option_bounds = {"score_threshold": ">=0"}

    def detect(self, image, k, dedupe=False, refill=False):
        import torch
        from kornia.feature import KeyNetDetector, get_laf_center, get_laf_scale

        from pipeline.features.kornia_base import cached_model, to_tensor
        thr = float(self.opts["score_threshold"])
        det = cached_model(("keynet", int(k), thr),
                           lambda: KeyNetDetector(True, num_features=int(k), score_threshold=thr), self.weights)
        with torch.inference_mode():
            lafs, resp = det(to_tensor(image))
        resp = resp.reshape(-1)
        keep = resp > 0  # unfilled slots carry a zero response and a zero LAF
        lafs = lafs[:, keep]
        resp = resp[keep].numpy().astype(np.float32)
        xy = get_laf_center(lafs)[0].numpy().astype(np.float64)
        scale = get_laf_scale(lafs).reshape(-1).numpy().astype(np.float64)
        # kornia (like the Key.Net reference) reports level pixel u at u * f (f = image / level size),
        # not at its centre (u + 0.5) f - 0.5: a (f - 1) / 2 px bias that grows with the level and does
        # not cancel between two images (a mirrored image then repeats 11% of detections within 2 px
        # instead of 60%). f is recovered from the frame size, s_mult (22) x f.
        f = scale / float(det.mr_size)
        xy += ((f - 1.0) / 2.0)[:, None]
        xy = xy.astype(np.float32)
        # Key.Net frames are 22 px x the level factor; kornia describes them as they are with 32 px
        # patches (KeyNetHardNet), i.e. as the 12-sigma frames of the other detectors.
        sigma = (scale / 12.0).astype(np.float32)
        order = np.lexsort((sigma, xy[:, 1], xy[:, 0], -resp))[:k]
        return Detections(xy[order], sigma[order], None, resp[order])


DETECTORS: dict[str, type[Detector]] = {
    "dog": DoG, "hessian": Hessian, "hessian-laplace": HessianLaplace, "harris-laplace": HarrisLaplace,
    "keynet": KeyNet,
}
ALIASES = {"hesslap": "hessian-laplace", "harlap": "harris-laplace", "key.net": "keynet", "hes": "hessian"}


def detector_class(name: str) -> type[Detector]:
    n = ALIASES.get(name, name)
    if n not in DETECTORS:
        raise ImtuneError(f"unknown detector {name!r} (known: {', '.join(DETECTORS)})")
    return DETECTORS[n]
