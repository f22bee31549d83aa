"""Multiview bags: subsets of a scene's images reconstructed on their own (the IMC multiview task).

The protocol: bags of 5, 10 and 25 images, 100 / 50 / 25 of them (fewer where the scene does not have
that many distinct valid bags), sampled with a seed, each image of a bag seeing at least 100 of the
bag's 3D points. A bag's points are the ground-truth 3D points observed by at least two of its images
(the points the bag can triangulate). Sizes larger than the scene are clipped to the scene's size.
"""
from __future__ import annotations

import itertools
import math
import re

import numpy as np

from pipeline.errors import ImtuneError

#: bag size -> number of bags (the paper's protocol)
DEFAULT_BAGS: dict[int, int] = {5: 100, 10: 50, 25: 25}
MIN_POINTS = 100
MIN_BAG = 3  # COLMAP's incremental mapper returns no model of 2 images, however well matched
ENUMERATE_LIMIT = 5000  # enumerate every subset when there are at most this many, else sample


def parse_bags(spec: str | dict | None) -> dict[int, int]:
    """Bag sizes and counts from "5,10,25" (default counts), "5:100,10:50" (explicit), or a dict.
    None or "" gives the protocol's default. Raises ImtuneError on a malformed spec."""
    if spec is None or spec == "":
        return dict(DEFAULT_BAGS)
    if isinstance(spec, dict):
        items = [(int(k), int(v)) for k, v in spec.items()]
    else:
        items = []
        for tok in str(spec).split(","):
            tok = tok.strip()
            if not tok:
                continue
            m = re.fullmatch(r"(\d+)(?::(\d+))?", tok)
            if not m:
                raise ImtuneError(f"bad bag spec {tok!r} in {spec!r}: expected SIZE or SIZE:COUNT, e.g. 5:100,10:50")
            size = int(m.group(1))
            count = int(m.group(2)) if m.group(2) else DEFAULT_BAGS.get(size, max(1, 500 // max(size, 1)))
            if size in dict(items):  # the last one's count was used, unsaid
                raise ImtuneError(f"bag spec {spec!r}: size {size} is given twice: give each size once "
                                  "(SIZE:COUNT for its number of bags)")
            items.append((size, count))
    for size, count in items:
        if size < MIN_BAG:  # a bag of 2 was a recorded failure every time: SR 0, mAA 0, unsaid
            raise ImtuneError(f"bag size must be >= {MIN_BAG}, got {size} (COLMAP's mapper keeps no model of two "
                              "images: every such bag would fail)")
        if count < 1:
            raise ImtuneError(f"number of bags must be >= 1, got {count} for size {size}")
    if not items:
        raise ImtuneError(f"empty bag spec {spec!r}")
    return dict(items)


def bag_points(bag, point_sets: dict[str, np.ndarray]) -> np.ndarray:
    """The bag's points: ids observed by at least two of its images."""
    ids = np.concatenate([np.unique(np.asarray(point_sets.get(n, []), np.int64)) for n in bag]) if bag else np.zeros(0, np.int64)
    u, c = np.unique(ids, return_counts=True)
    return u[c >= 2]


def bag_is_valid(bag, point_sets: dict[str, np.ndarray], min_points: int = MIN_POINTS) -> bool:
    """True if every image of the bag sees at least ``min_points`` of the bag's points."""
    if min_points <= 0:
        return True
    shared = bag_points(bag, point_sets)
    if len(shared) < min_points:
        return False
    return all(len(np.intersect1d(np.asarray(point_sets.get(n, []), np.int64), shared, assume_unique=False))
               >= min_points for n in bag)


def sample_bags(names: list[str], point_sets: dict[str, np.ndarray] | None, bags: dict[int, int] | None = None,
                min_points: int = MIN_POINTS, seed: int = 0) -> dict[int, list[tuple[str, ...]]]:
    """Sample bags: {size: [tuple of image names, ...]} (sizes clipped to len(names); duplicates merged).

    point_sets: image name -> ids of the 3D points it observes (None: no visibility check, min_points
    must then be 0). Deterministic for a given seed. Each bag lists its images in the order of ``names``.

    Each (clipped) bag size draws from its own generator, seeded by ``(seed, size)`` (``numpy.random.SeedSequence``):
    the bags of one size do not depend on the other sizes or their counts, and asking more bags of a size keeps the
    first ones (a prefix). One generator drawing every size in turn made 6 bags of 5 in place of 3 change every bag
    of 10 and 25, so two studies run with other ``--bags`` shared no bag of their common sizes.
    """
    spec = DEFAULT_BAGS if bags is None else bags
    names = list(names)
    order = {n: k for k, n in enumerate(names)}
    if point_sets is None:
        if min_points > 0:
            raise ImtuneError("bags need 3D points to check visibility (or min_points=0)")
        point_sets = {}
    point_sets = {n: np.unique(np.asarray(v, np.int64)) for n, v in point_sets.items()}
    out: dict[int, list[tuple[str, ...]]] = {}
    for size in sorted(spec):
        k = min(int(size), len(names))
        if k < MIN_BAG or k in out:
            continue
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), k]))  # one generator per size (docstring)
        target = int(spec[size])
        total = math.comb(len(names), k)
        chosen: list[tuple[str, ...]] = []
        if total <= ENUMERATE_LIMIT:
            combos = list(itertools.combinations(range(len(names)), k))
            for idx in rng.permutation(len(combos)):
                bag = tuple(names[i] for i in combos[idx])
                if bag_is_valid(bag, point_sets, min_points):
                    chosen.append(bag)
                    if len(chosen) >= target:
                        break
        else:
            seen: set[tuple[str, ...]] = set()
            tries = 0
            while len(chosen) < target and tries < 200 * target:
                tries += 1
                bag = _grow_bag(names, point_sets, k, rng, min_points)
                if bag is None:
                    continue
                bag = tuple(sorted(bag, key=order.__getitem__))
                if bag in seen:
                    continue
                seen.add(bag)
                if bag_is_valid(bag, point_sets, min_points):
                    chosen.append(bag)
        if chosen:
            out[k] = chosen
    return out


def _grow_bag(names, point_sets, k, rng, min_points):
    """Random bag grown from a random image, each next image drawn among those sharing points with the bag
    (weighted by how many), so that valid bags are found quickly in large scenes."""
    bag = [names[rng.integers(len(names))]]
    pts = set(point_sets.get(bag[0], np.zeros(0, np.int64)).tolist())
    while len(bag) < k:
        cand = [n for n in names if n not in bag]
        if min_points > 0 and point_sets:
            w = np.array([len(pts.intersection(point_sets.get(n, np.zeros(0, np.int64)).tolist())) for n in cand], float)
            if w.sum() <= 0:
                return None
            nxt = cand[rng.choice(len(cand), p=w / w.sum())]
        else:
            nxt = cand[rng.integers(len(cand))]
        bag.append(nxt)
        pts.update(point_sets.get(nxt, np.zeros(0, np.int64)).tolist())
    return bag


def scene_point_sets(scene) -> dict[str, np.ndarray] | None:
    """image name -> ids of the 3D points it observes, from a scene's observations (None if it has none)."""
    if scene.observations is None:
        return None
    return {n: np.asarray(ids, np.int64) for n, (ids, _) in scene.observations.items() if n in scene.images}


def scene_bags(scene, bags: dict[int, int] | None = None, min_points: int = MIN_POINTS, seed: int = 0,
               use_existing: bool = True) -> dict[int, list[tuple[str, ...]]]:
    """A scene's bags: the ones it ships (IMC-PT sub_set, or built ground truth) when ``use_existing``
    (limited to the requested sizes and counts), else sampled from its 3D points; requested sizes it does not ship
    are sampled from its 3D points too.

    Raises ImtuneError naming the scene when it has neither bags nor 3D points, or ships some requested sizes and has
    no 3D points to sample the others from."""
    spec = DEFAULT_BAGS if bags is None else bags
    pts = scene_point_sets(scene)
    if use_existing and scene.bags:
        names = set(scene.images)
        wanted = {min(s, len(scene.images)): c for s, c in sorted(spec.items(), reverse=True)}
        wanted = {s: c for s, c in wanted.items() if s >= MIN_BAG}
        out = {}
        for size, lst in sorted(scene.bags.items()):
            if size not in wanted:
                continue
            ok = [tuple(b) for b in lst if set(b) <= names]
            if ok:
                out[size] = ok[: wanted[size]]
        missing = sorted(set(wanted) - set(out))
        if not missing:  # {} where no requested size reaches MIN_BAG: the caller says so
            return out
        if pts is not None or min_points <= 0:  # the sizes it does not ship, sampled from its 3D points
            return dict(sorted({**sample_bags(list(scene.images), pts, {s: wanted[s] for s in missing},
                                              min_points=min_points, seed=seed), **out}.items()))
        # the mean over the sizes it ships was reported as the mean over every requested size, unsaid
        asked = {s: sorted(r for r in spec if min(r, len(scene.images)) == s) for s in missing}
        said = ", ".join(f"{s}" + ("" if asked[s] == [s] else f" ({', '.join(map(str, asked[s]))} on its "
                                                                f"{len(scene.images)} images)") for s in missing)
        shipped = sorted(scene.bags)
        raise ImtuneError(f"scene {scene.name}: its bags are of size(s) {', '.join(map(str, shipped))}, not of size(s) "
                          f"{said} as requested: pass --bags {','.join(map(str, shipped))} to evaluate the sizes it "
                          "ships, or run `tune data build-gt` for it to sample the others from 3D points")
    if pts is None:
        if min_points > 0:
            if any(im.R is None for im in scene.images.values()):  # e.g. a pairs list: relative poses only
                raise ImtuneError(f"scene {scene.name}: no multiview bags, and its images have no absolute poses to "
                                  f"build them from ({scene.source or 'this format'} gives a relative pose per pair): "
                                  "the multiview task needs a data set with camera poses (Strecha, IMC-PT, COLMAP) "
                                  "or a folder of images SfM can reconstruct (`tune data build-gt`); use the stereo "
                                  "task on this one")
            raise ImtuneError(f"scene {scene.name}: no multiview bags and no 3D points to sample them from; "
                              f"run `tune data build-gt` for it first")
    return sample_bags(list(scene.images), pts, spec, min_points=min_points, seed=seed)
