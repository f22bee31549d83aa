"""Patch descriptors (kornia) for the composed features: LAF -> patch -> descriptor, batched.

| name | kornia module | patch | dim | weights |
| --- | --- | --- | --- | --- |
| sift | ``SIFTDescriptor(41, rootsift=False)`` (VLFeat-style, so affine frames can carry SIFT) | 41 | 128 | none |
| rootsift | ``SIFTDescriptor(41, rootsift=True)`` | 41 | 128 | none |
| tfeat | ``TFeat(True)`` (liberty) | 32 | 128 | tfeat-liberty.params |
| mkd | ``MKDDescriptor(32, "concat", "pcawt", "liberty", 128)`` | 32 | 128 | mkd-concat-64.pth |
| hardnet | ``HardNet(True)`` (liberty, augmented) | 32 | 128 | checkpoint_liberty_with_aug.pth |
| hardnet8 | ``HardNet8(True)`` (v2) | 32 | 128 | hardnet8v2.pt |
| sosnet | ``SOSNet(True)`` (liberty) | 32 | 128 | sosnet_32x32_liberty.pth |
| hynet | ``HyNet(True)`` (liberty) | 32 | 128 | HyNet_LIB.pth |

Support (``mr_size``, the SIFT magnification convention of ``FeatureConfig``): the described patch is
``4 * mr_size`` sigmas wide, i.e. the LAF half-size is ``2 * mr_size`` sigma. Defaults: 3 for SIFT (as
OpenCV and VLFeat: 4 bins of 3 sigma) and 6 for the learned descriptors (24-sigma patches: kornia's
DoG-HardNet frames, the IMC baselines' patches with magnification 12 on OpenCV keypoint sizes).
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

from pipeline.errors import ImtuneError


class PatchDescriptor:
    name: ClassVar[str] = ""
    weights: ClassVar[tuple[str, ...]] = ()
    patch_size: ClassVar[int] = 32
    default_mr_size: ClassVar[float] = 6.0
    dim: ClassVar[int] = 128
    description: ClassVar[str] = ""
    option_defaults: ClassVar[dict[str, Any]] = {}
    option_bounds: ClassVar[dict[str, str]] = {}

    def __init__(self, opts: dict[str, Any]):
        self.opts = opts

    def _factory(self) -> Callable[[], Any]:
        raise NotImplementedError

    def module(self):
        from pipeline.features.kornia_base import cached_model
        return cached_model((self.name,), self._factory(), self.weights)


class SIFT(PatchDescriptor):
    name = "sift"
    patch_size = 41
    default_mr_size = 3.0
    description = "SIFT descriptor on LAF patches"
    rootsift: ClassVar[bool] = False

    def _factory(self):
        from kornia.feature import SIFTDescriptor
        return lambda: SIFTDescriptor(41, rootsift=self.rootsift)


class RootSIFT(SIFT):
    name = "rootsift"
    description = "RootSIFT descriptor on LAF patches"
    rootsift = True


class TFeat(PatchDescriptor):
    name = "tfeat"
    weights = ("tfeat",)
    description = "TFeat"

    def _factory(self):
        from kornia.feature import TFeat as K
        return lambda: K(True)


class MKD(PatchDescriptor):
    name = "mkd"
    weights = ("mkd",)
    description = "MKD (concat, PCA-whitened, liberty)"

    def _factory(self):
        from kornia.feature import MKDDescriptor
        return lambda: MKDDescriptor(32, "concat", "pcawt", "liberty", 128)


class HardNet(PatchDescriptor):
    name = "hardnet"
    weights = ("hardnet",)
    description = "HardNet"

    def _factory(self):
        from kornia.feature import HardNet as K
        return lambda: K(True)


class HardNet8(PatchDescriptor):
    name = "hardnet8"
    weights = ("hardnet8",)
    description = "HardNet8"

    def _factory(self):
        from kornia.feature import HardNet8 as K
        return lambda: K(True)


class SOSNet(PatchDescriptor):
    name = "sosnet"
    weights = ("sosnet",)
    description = "SOSNet"

    def _factory(self):
        from kornia.feature import SOSNet as K
        return lambda: K(True)


class HyNet(PatchDescriptor):
    name = "hynet"
    weights = ("hynet",)
    description = "HyNet"

    def _factory(self):
        from kornia.feature import HyNet as K
        return lambda: K(True)


DESCRIPTORS: dict[str, type[PatchDescriptor]] = {
    c.name: c for c in (SIFT, RootSIFT, TFeat, MKD, HardNet, HardNet8, SOSNet, HyNet)}


def descriptor_class(name: str) -> type[PatchDescriptor]:
    if name not in DESCRIPTORS:
        raise ImtuneError(f"unknown patch descriptor {name!r} (known: {', '.join(DESCRIPTORS)})")
    return DESCRIPTORS[name]
