"""Intermediate metrics of one configuration over the scenes' stereo pairs (repeatability, matching
scores; the per-pair metrics are in ``pipeline.metrics.repeatability``), computed on the tentative matches
every task uses (``pipeline.tasks.prepare.tentative_matches``: matcher or imported matches, then the
pre-filter), before RANSAC."""
from __future__ import annotations

from pipeline.metrics.repeatability import (
    PX_THRESHOLDS,
    load_depth,
    mean_intermediate,
    mean_of_scenes,
    pair_intermediate,
)


def evaluate_intermediate(scenes, conf, cache=None, min_covisibility: float | None = 0.1, progress: bool = False,
                          thresholds=PX_THRESHOLDS) -> dict:
    """Repeatability and matching scores of one configuration over the scenes' stereo pairs.

    Per pair (tentative matches of ``conf.matching``, before RANSAC): repeatability and depth matching
    score at each threshold (px, working resolution) when both images have depth maps; the epipolar
    matching score always. Returned: {"scenes": {name: {...}}, plus the mean over scenes} where a scene's
    figures are means over its pairs; ``*_3px`` keys give the headline threshold."""
    from tqdm.auto import tqdm

    from pipeline.cache import H5Cache
    from pipeline.data.resize import scaled_K
    from pipeline.tasks.prepare import image_features, pair_knn, tentative_matches
    cache = cache if cache is not None else H5Cache()
    per_scene = {}
    for scene in scenes:
        pairs = scene.select_pairs(min_covisibility)
        feats, depth_cache, recs = {}, {}, []
        for p in tqdm(pairs, desc=f"{scene.name}: intermediate", disable=not progress, leave=False):
            for n in (p.i, p.j):
                if n not in feats:
                    feats[n] = image_features(cache, scene.images[n], conf.feature)
            fi, fj = feats[p.i], feats[p.j]
            tab, _ = pair_knn(cache, fi, fj, conf.matching)
            m, _ = tentative_matches(tab, conf.matching, fi, fj)  # the matches the stereo task sees
            Ki, Kj = scene.intrinsics(p)
            R, t = scene.relative_pose(p)
            depths = []
            for n in (p.i, p.j):
                dp = scene.images[n].depth_path
                if dp is not None and n not in depth_cache:
                    depth_cache[n] = load_depth(dp)
                depths.append(depth_cache.get(n))
            recs.append(pair_intermediate(
                fi.keypoints, fj.keypoints, m, scaled_K(Ki, fi.sx, fi.sy), scaled_K(Kj, fj.sx, fj.sy), R, t,
                (fi.width, fi.height), (fj.width, fj.height), depths[0], depths[1],
                (fi.sx, fi.sy), (fj.sx, fj.sy), thresholds))
        per_scene[scene.name] = mean_intermediate(recs, thresholds)
    out = mean_of_scenes(list(per_scene.values()), thresholds)
    out["scenes"] = per_scene
    return out
