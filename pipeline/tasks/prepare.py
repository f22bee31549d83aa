"""Cached feature and k-NN stages shared by the tasks.

A tuning trial that changes only r, eta or Gamma hits both caches: it runs no extraction and no
neighbour search (``COUNTERS`` counts real computations; tests read it).
"""
from __future__ import annotations

import dataclasses
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from pipeline.cache import H5Cache, file_digest, make_key
from pipeline.config import FeatureConfig, MatchConfig
from pipeline.data.scene import ImageInfo
from pipeline.errors import ImtuneError
from pipeline.matching import neighbours_needed

COUNTERS: Counter = Counter()  # "extract", "knn", "learned": number of real (uncached) computations in this process
FEATURE_STAGE_VERSION = "1"
KNN_STAGE_VERSION = "1"
LEARNED_STAGE_VERSION = "1"


@dataclass
class ImageFeatures:
    """Features of one image at the working resolution plus the scale factors from the file on disk."""
    key: str
    keypoints: np.ndarray  # (N, 2) float32 px at working resolution
    descriptors: np.ndarray
    binary: bool
    sx: float
    sy: float
    width: int  # working resolution, px
    height: int
    seconds: float  # extraction wall time (when it was computed)
    scales: np.ndarray | None = None
    orientations: np.ndarray | None = None
    scores: np.ndarray | None = None
    name: str = ""  # the image's name in its scene (custom matches are keyed by it)
    path: str = ""  # the image file
    feature: str = ""  # the extractor's registry name (a learned matcher picks its weights by it)


def feature_key(info: ImageInfo, conf: FeatureConfig) -> str:
    from pipeline.features import EXTRACTORS
    cls = EXTRACTORS.get(conf.name)
    return make_key("features", file_digest(info.path), dataclasses.asdict(conf),
                    FEATURE_STAGE_VERSION, getattr(cls, "version", "1"))


def image_features(cache: H5Cache, info: ImageInfo, conf: FeatureConfig) -> ImageFeatures:
    """Features of one image, from the cache or extracted (and cached)."""
    key = feature_key(info, conf)

    def compute():
        from pipeline.data.resize import load_image
        from pipeline.features import get_extractor
        image, sx, sy = load_image(info.path, max_side=conf.max_side)
        t0 = time.perf_counter()
        ext = get_extractor(conf)
        if hasattr(ext, "extract_from_file"):  # imported features (custom:DIR) are read by image name
            f = ext.extract_from_file(info, image, sx, sy)
        else:
            f = ext.extract(image)
        dt = time.perf_counter() - t0
        COUNTERS["extract"] += 1
        out = {"keypoints": np.asarray(f.keypoints, np.float32).reshape(-1, 2),
               "descriptors": np.asarray(f.descriptors),
               "binary": np.array(bool(f.binary)),
               "scale": np.array([sx, sy], np.float64),
               "size": np.array([image.shape[1], image.shape[0]], np.int64),
               "seconds": np.array(dt)}
        for name in ("scales", "orientations", "scores"):
            v = getattr(f, name, None)
            if v is not None:
                out[name] = np.asarray(v, np.float32)
        return out

    a = cache.get_or_compute("features", key, compute)
    return ImageFeatures(key=key, keypoints=a["keypoints"], descriptors=a["descriptors"],
                         binary=bool(a["binary"]), sx=float(a["scale"][0]), sy=float(a["scale"][1]),
                         width=int(a["size"][0]), height=int(a["size"][1]), seconds=float(a["seconds"]),
                         scales=a.get("scales"), orientations=a.get("orientations"), scores=a.get("scores"),
                         name=info.name, path=str(info.path), feature=conf.name)


def pair_knn(cache: H5Cache, fi: ImageFeatures, fj: ImageFeatures, conf: MatchConfig):
    """Both-direction k-NN tables of a pair (cached), and the seconds the search took when computed.

    With ``conf.custom_matches`` no search runs: the tables returned (``CustomTables``) carry the imported
    matches (read ``tentative_matches`` for them; ``filter_matches`` on them gives the same matches when they are
    one-to-one).

    With a learned matcher (``conf.method`` "lightglue") the network runs instead of the search and its raw output
    (:class:`pipeline.matching.learned.LearnedMatches`: every candidate match and its confidence) is what is
    cached, per feature set and pair; ``tentative_matches`` thresholds it at ``conf.min_confidence``. The seconds
    are the network's: matching time, as the search's."""
    from pipeline.matching.knn import KnnTables, knn_tables
    if conf.custom_matches:
        return custom_tables(fi, fj, conf), 0.0
    if conf.learned:
        return pair_learned(cache, fi, fj, conf)
    for f in (fi, fj):
        if f.descriptors.ndim != 2 or f.descriptors.shape[1] == 0:
            raise ImtuneError(f"image {f.name or f.key}: the features have no descriptors (custom features without "
                              "descriptors.h5 need custom matches: --matches custom:DIR)")
    k = neighbours_needed(conf)
    key = make_key("knn", fi.key, fj.key, k, conf.method, KNN_STAGE_VERSION)

    def compute():
        t0 = time.perf_counter()
        tab = knn_tables(fi.descriptors, fj.descriptors, binary=fi.binary, k=k, method=conf.method)
        dt = time.perf_counter() - t0
        COUNTERS["knn"] += 1
        out = {f.name: np.asarray(getattr(tab, f.name)) for f in dataclasses.fields(tab)}
        out["seconds"] = np.array(dt)
        return out

    a = cache.get_or_compute("knn", key, compute)
    tab = KnnTables(**{f.name: a[f.name] for f in dataclasses.fields(KnnTables)})
    return tab, float(a["seconds"])


def pair_learned(cache: H5Cache, fi: ImageFeatures, fj: ImageFeatures, conf: MatchConfig):
    """A learned matcher's raw output for a pair (cached; :func:`pair_knn` calls it) and its seconds."""
    from pipeline.matching.learned import LearnedMatches, get_learned_matcher
    matcher = get_learned_matcher(conf.method, conf.matcher_options)
    feature = fi.feature or fj.feature
    if not feature:
        raise ImtuneError(f"{conf.method}: the features of {fi.name or fi.key} do not say which extractor made them "
                          "(ImageFeatures.feature)")
    key = make_key("learned", fi.key, fj.key, matcher.cache_parts(feature), LEARNED_STAGE_VERSION)

    def compute():
        matcher.warmup(feature)  # the network's construction is not matching time
        t0 = time.perf_counter()
        raw = matcher.match(fi, fj, feature)
        dt = time.perf_counter() - t0
        COUNTERS["learned"] += 1
        return {"matches": raw.matches, "confidence": raw.confidence, "n": np.array([raw.n1, raw.n2], np.int64),
                "seconds": np.array(dt)}

    a = cache.get_or_compute("learned", key, compute)
    n = np.asarray(a["n"]).reshape(-1)
    if int(n[0]) != len(fi.keypoints) or int(n[1]) != len(fj.keypoints):
        raise ImtuneError(f"cache entry learned/{key}: made for {int(n[0])} and {int(n[1])} keypoints, the pair has "
                          f"{len(fi.keypoints)} and {len(fj.keypoints)}: delete it (it is recomputed)")
    raw = LearnedMatches(np.asarray(a["matches"], np.int32).reshape(-1, 2), np.asarray(a["confidence"], np.float32),
                         int(n[0]), int(n[1]))
    return raw, float(a["seconds"])


# --------------------------------------------------------------------- tentative matches of a pair

def custom_tables(fi: ImageFeatures, fj: ImageFeatures, conf: MatchConfig, task: str = "stereo"):
    """``CustomTables`` of a pair from ``conf.custom_matches`` (imported matches; no search). ``task``
    picks the file: stereo (matches_stereo_0.h5, matches.h5) or multiview (matches_multiview.h5, ...)."""
    from pipeline.matching.custom_matches import CustomTables, load_pair_matches
    if not (fi.name and fj.name):
        raise ImtuneError("custom matches need the image names of the pair (ImageFeatures.name)")
    if not conf.custom_matches:
        raise ImtuneError("custom matches need their folder (MatchConfig.custom_matches)")
    m = load_pair_matches(conf.custom_matches, fi.name, fj.name, fi.path, len(fi.keypoints), len(fj.keypoints),
                          task=task)
    return CustomTables.from_matches(m, len(fi.keypoints), len(fj.keypoints), neighbours_needed(conf))


def tentative_matches(tables, conf: MatchConfig, fi: ImageFeatures, fj: ImageFeatures, task: str = "stereo"):
    """THE tentative-matches function: every task, the intermediate metrics, the budget calibration and the
    figures call it, so they all see the same matches. The tentative matches a task hands to the estimator (or COLMAP): the matcher's (ratio test,
    strategy, distance threshold, FGINN on the k-NN ``tables``) or the imported ones (custom matches;
    ``task`` "multiview" reads the multiview match file), then the pre-filter ``conf.prefilter``.
    A learned matcher's cached output (``LearnedMatches``) is thresholded at ``conf.min_confidence``.
    Returns (matches (M, 2) int32 [i, j], distances (M,) float32; 0 for custom matches, 1 - confidence for a
    learned matcher)."""
    from pipeline.matching.custom_matches import CustomTables
    from pipeline.matching.filter import filter_matches
    from pipeline.matching.learned import LearnedMatches
    if isinstance(tables, LearnedMatches) or conf.learned:
        if not isinstance(tables, LearnedMatches):
            raise ImtuneError(f"matcher {conf.method}: expected its cached output (pair_knn), got k-NN tables")
        m, c = tables.select(conf.min_confidence)  # LightGlue's filter_threshold, applied per trial
        d = (1.0 - c).astype(np.float32)
    elif isinstance(tables, CustomTables) or conf.custom_matches:
        if task != "stereo" or not isinstance(tables, CustomTables):
            tables = custom_tables(fi, fj, conf, task)
        m = np.asarray(tables.matches, np.int32).reshape(-1, 2)
        d = np.zeros(len(m), np.float32)
    else:
        m, d = filter_matches(tables, conf, fi.keypoints, fj.keypoints)
    if conf.prefilter and conf.prefilter != "none" and len(m):
        from pipeline.matching.prefilters import PairContext, apply_prefilter
        ratio = None
        if not isinstance(tables, (CustomTables, LearnedMatches)) and np.asarray(tables.dist12).ndim == 2 \
                and np.asarray(tables.dist12).shape[1] >= 2:
            # each match's own ratio: of its row of image 1 when it is that row's nearest neighbour, else (a match
            # found from image 2 only, strategy "either") of its row of image 2
            # (its own name: `d`, the match distances returned below, was overwritten here by these (M, 2) rows)
            d2 = np.asarray(tables.dist12, np.float64)[m[:, 0], :2]
            from_2 = np.asarray(tables.idx12)[m[:, 0], 0] != m[:, 1]
            d21 = np.asarray(tables.dist21, np.float64)
            if from_2.any() and d21.ndim == 2 and d21.shape[1] >= 2:
                d2[from_2] = d21[m[from_2, 1], :2]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(np.isfinite(d2[:, 1]) & (d2[:, 1] > 0), d2[:, 0] / d2[:, 1], 0.0)
        ctx = PairContext(fi.keypoints, fj.keypoints, (fi.width, fi.height), (fj.width, fj.height),
                          fi.scales, fj.scales, fi.orientations, fj.orientations, ratio,
                          None if isinstance(tables, (CustomTables, LearnedMatches)) else tables)
        keep = apply_prefilter(conf.prefilter, m, ctx, conf.prefilter_options)
        m, d = m[keep], d[keep]
    return m, d
