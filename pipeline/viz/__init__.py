"""Qualitative figures (the paper's): stereo matches coloured by their ground-truth error, multiview keypoints
in / not in the 3D model, side-by-side comparisons, and an HTML gallery. Drawn with OpenCV only.

    from pipeline.viz import render_pair, draw_matches, error_colors      # stereo
    from pipeline.viz import draw_keypoints, draw_bag, reconstruct_bag     # multiview
    from pipeline.viz import side_by_side, write_gallery                   # composition, gallery

Modules: ``colors`` (the colour scale), ``gt`` (errors against the ground truth: depth reprojection or
symmetric epipolar distance), ``stereo``, ``multiview``, ``compose``, ``gallery``, ``select`` (which pairs).
"""
from __future__ import annotations

from pipeline.viz.colors import BLUE, ERROR_MAX_PX, GREEN, RED, YELLOW, error_colors
from pipeline.viz.gt import gt_fundamental, match_errors, symmetric_epipolar_distance

__all__ = ["BLUE", "ERROR_MAX_PX", "GREEN", "RED", "YELLOW", "error_colors", "gt_fundamental", "match_errors",
           "symmetric_epipolar_distance", "draw_matches", "render_pair", "pair_matches", "MatchFigure",
           "config_label", "draw_keypoints", "draw_bag", "reconstruct_bag", "side_by_side", "write_gallery"]

_LAZY = {
    "draw_matches": "pipeline.viz.stereo", "render_pair": "pipeline.viz.stereo", "pair_matches": "pipeline.viz.stereo",
    "MatchFigure": "pipeline.viz.stereo", "config_label": "pipeline.viz.stereo",
    "draw_keypoints": "pipeline.viz.multiview", "draw_bag": "pipeline.viz.multiview",
    "reconstruct_bag": "pipeline.viz.multiview", "side_by_side": "pipeline.viz.compose",
    "write_gallery": "pipeline.viz.gallery",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(name)
