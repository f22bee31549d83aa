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

COUNTERS: Counter = Counter()  # "extract", "knn": number of real (uncached) computations in this process
FEATURE_STAGE_VERSION = "1"
KNN_STAGE_VERSION = "1"


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
        from pipeline.features import extract
        image, sx, sy = load_image(info.path, max_side=conf.max_side)
        t0 = time.perf_counter()
        f = extract(conf, image)
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
                         scales=a.get("scales"), orientations=a.get("orientations"), scores=a.get("scores"))


def knn_k(conf: MatchConfig) -> int:
    """Neighbours kept per direction: 2 for the ratio test, more for FGINN's spatial search."""
    return 10 if conf.fginn else 2


def pair_knn(cache: H5Cache, fi: ImageFeatures, fj: ImageFeatures, conf: MatchConfig):
    """Both-direction k-NN tables of a pair (cached), and the seconds the search took when computed."""
    from pipeline.matching.knn import KnnTables, knn_tables
    k = knn_k(conf)
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
