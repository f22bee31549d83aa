"""Affine shape and orientation estimators (kornia) for the composed features.

Each runs on local affine frames (kornia LAFs, (1, N, 2, 3)) of the estimation size (the detector's
``frame_mult`` sigmas) and returns new LAFs. Every LAF of the image goes through one kornia call (one
image pyramid, all patches sampled at once: ~4 KB per frame); the networks inside (AffNet, OriNet) run
``batch_size`` patches at a time (:func:`batched_submodule`). Splitting the frames into several kornia
calls instead rebuilds the pyramid per call: 2.7x slower for Baumberg x 4 at 8k frames here.

Affine shape:
- ``affnet``: AffNet (Mishkin et al., ECCV 2018), kornia ``LAFAffNetShapeEstimator``;
- ``baumberg``: the second-moment-matrix iteration of Baumberg (CVPR 2000) / Mikolajczyk & Schmid, kornia
  ``LAFAffineShapeEstimator`` (``PatchAffineShapeEstimator`` on 32 px patches) applied ``affine_iters``
  times, each step re-estimating on the patch normalised by the previous shape (VLFeat's affine
  adaptation, as the paper's "DoG-Affine" / "VL-DoGAff" rows).

Orientation:
- ``gradori``: dominant gradient orientation (36-bin histogram, kornia ``LAFOrienter(19)``, SIFT's method);
- ``orinet``: OriNet (Mishkin et al.), kornia ``LAFOrienter(32, angle_detector=OriNet(True))``;
- ``upright``: none (angle 0); the same as ``FeatureConfig.upright``.
"""
from __future__ import annotations

from typing import Any, ClassVar

from pipeline.errors import ImtuneError


def batched_submodule(module, attr: str, batch: int):
    """Make ``module.<attr>`` (a network applied to a (N, C, H, W) patch batch) run ``batch`` at a time."""
    import torch
    from torch import nn

    class Batched(nn.Module):
        def __init__(self, inner):
            super().__init__()
            self.inner = inner
            self.batch = batch

        def forward(self, x):
            if x.shape[0] <= self.batch:
                return self.inner(x)
            return torch.cat([self.inner(x[i:i + self.batch]) for i in range(0, x.shape[0], self.batch)])

    inner = getattr(module, attr)
    if type(inner).__name__ != "Batched":
        inner = Batched(inner)
        setattr(module, attr, inner)
    inner.batch = int(batch)
    return module


class ShapeStep:
    name: ClassVar[str] = ""
    weights: ClassVar[tuple[str, ...]] = ()
    option_defaults: ClassVar[dict[str, Any]] = {}
    option_bounds: ClassVar[dict[str, str]] = {}
    description: ClassVar[str] = ""

    def __init__(self, opts: dict[str, Any]):
        self.opts = opts

    def __call__(self, lafs, image_t, batch: int):
        raise NotImplementedError


class AffNet(ShapeStep):
    name = "affnet"
    weights = ("affnet",)
    description = "AffNet affine shape"

    def __call__(self, lafs, image_t, batch):
        from kornia.feature import LAFAffNetShapeEstimator

        from pipeline.features.kornia_base import cached_model
        m = cached_model(("affnet",), lambda: LAFAffNetShapeEstimator(True, preserve_orientation=False),
                         self.weights)
        return batched_submodule(m, "features", batch)(lafs, image_t)


class Baumberg(ShapeStep):
    name = "baumberg"
    description = "Baumberg second-moment affine adaptation"
    option_defaults = {"affine_iters": 4}
    option_bounds = {"affine_iters": ">=1"}

    def __call__(self, lafs, image_t, batch):
        from kornia.feature import LAFAffineShapeEstimator

        from pipeline.features.kornia_base import cached_model
        m = cached_model(("baumberg",), lambda: LAFAffineShapeEstimator(32, preserve_orientation=False))
        for _ in range(int(self.opts["affine_iters"])):
            lafs = m(lafs, image_t)
        return lafs


class GradOri(ShapeStep):
    name = "gradori"
    description = "dominant gradient orientation"

    def __call__(self, lafs, image_t, batch):
        from kornia.feature import LAFOrienter

        from pipeline.features.kornia_base import cached_model
        m = cached_model(("gradori",), lambda: LAFOrienter(19))
        return m(lafs, image_t)


class OriNet(ShapeStep):
    name = "orinet"
    weights = ("orinet",)
    description = "OriNet orientation"

    def __call__(self, lafs, image_t, batch):
        from kornia.feature import LAFOrienter
        from kornia.feature import OriNet as KOriNet

        from pipeline.features.kornia_base import cached_model
        m = cached_model(("orinet",), lambda: LAFOrienter(32, angle_detector=KOriNet(True)), self.weights)
        return batched_submodule(m, "angle_detector", batch)(lafs, image_t)


class Upright(ShapeStep):
    name = "upright"
    description = "no orientation (upright)"

    def __call__(self, lafs, image_t, batch):
        return lafs


AFFINE: dict[str, type[ShapeStep]] = {"affnet": AffNet, "baumberg": Baumberg}
ORIENTATION: dict[str, type[ShapeStep]] = {"gradori": GradOri, "orinet": OriNet, "upright": Upright}
ALIASES = {"affine": "baumberg", "aff": "baumberg", "ori": "gradori", "sift-ori": "gradori"}


def canonical(name: str) -> str:
    return ALIASES.get(name, name)


def step_class(name: str) -> type[ShapeStep]:
    n = canonical(name)
    if n in AFFINE:
        return AFFINE[n]
    if n in ORIENTATION:
        return ORIENTATION[n]
    raise ImtuneError(f"unknown affine/orientation step {name!r} (known: {', '.join([*AFFINE, *ORIENTATION])})")
