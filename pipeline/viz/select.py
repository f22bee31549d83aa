"""Which pairs to draw: named pairs, the worst / best / a random sample of an evaluation, or the pairs on
which two configurations disagree most."""
from __future__ import annotations

import math

import numpy as np

from pipeline.data.scene import Pair, Scene
from pipeline.errors import ImtuneError


def parse_pair_specs(text: str | None) -> list[str]:
    """``"a|b,scene:c|d"`` -> ["a|b", "scene:c|d"] (commas separate pairs; whitespace ignored)."""
    if not text:
        return []
    return [s.strip() for s in str(text).split(",") if s.strip()]


def find_pair(scenes: list[Scene], spec: str) -> tuple[Scene, Pair]:
    """The scene and pair named by ``spec``: ``"i|j"`` or ``"scene:i|j"`` (image names as the scene lists them).

    A listed evaluation pair is returned as listed (with its co-visibility); a pair given in the other order
    is drawn in the order asked. Two images of the scene that form no listed pair are accepted when the scene
    has ground-truth poses for both. Anything else raises a one-line ImtuneError."""
    s = spec.strip()
    scene_name = None
    if ":" in s.split("|")[0]:
        scene_name, s = s.split(":", 1)
    if s.count("|") != 1:
        raise ImtuneError(f"pair {spec!r}: expected 'IMAGE1|IMAGE2' or 'SCENE:IMAGE1|IMAGE2'")
    a, b = (x.strip() for x in s.split("|"))
    if not a or not b or a == b:
        raise ImtuneError(f"pair {spec!r}: expected two different image names")
    cands = scenes
    if scene_name is not None:
        cands = [sc for sc in scenes if sc.name == scene_name]
        if not cands:
            raise ImtuneError(f"pair {spec!r}: scene {scene_name!r} is not loaded "
                              f"(scenes: {', '.join(sc.name for sc in scenes)})")
    hits = [sc for sc in cands if a in sc.images and b in sc.images]
    if not hits:
        where = cands[0].name if len(cands) == 1 else f"any of {', '.join(sc.name for sc in cands)}"
        missing = [n for n in (a, b) if not any(n in sc.images for sc in cands)]
        example = next((f"{p.i}|{p.j}" for sc in cands for p in sc.pairs[:1]), None)
        raise ImtuneError(f"pair {a}|{b} is not in {where}: image {missing[0] if missing else a + ' / ' + b} not found"
                          + (f" (pairs look like {example})" if example else ""))
    if len(hits) > 1:
        raise ImtuneError(f"pair {a}|{b} is in several scenes ({', '.join(sc.name for sc in hits)}); "
                          f"write it as SCENE:{a}|{b}")
    sc = hits[0]
    for p in sc.pairs:
        if (p.i, p.j) == (a, b):
            return sc, p
    for p in sc.pairs:
        if (p.i, p.j) == (b, a):
            if p.R is not None and p.t is not None:  # reverse the listed ground truth
                R = np.asarray(p.R, float)
                return sc, Pair(a, b, R=R.T, t=-R.T @ np.asarray(p.t, float).reshape(3), K_i=p.K_j, K_j=p.K_i,
                                covisibility=p.covisibility)
            return sc, Pair(a, b, covisibility=p.covisibility)
    if sc.images[a].R is None or sc.images[b].R is None:
        raise ImtuneError(f"pair {a}|{b} is not an evaluation pair of scene {sc.name} and the scene has no "
                          f"ground-truth pose for both images")
    return sc, Pair(a, b)


def _err(r: dict) -> float:
    try:
        e = float(r["err"])
    except (KeyError, TypeError, ValueError):  # absent, None (a failure) or not a number
        return math.inf
    return math.inf if math.isnan(e) else e


def select_records(records: list[dict], worst: int = 2, best: int = 2, random: int = 2,
                   seed: int = 0) -> list[tuple[dict, str]]:
    """(record, reason) for the ``worst`` pairs (largest pose error; failures first, then fewest inliers),
    the ``best`` (smallest error, then most inliers) and ``random`` others (seeded), without repeats."""
    order_worst = sorted(records, key=lambda r: (-_err(r), r.get("NI", 0), r.get("pair", "")))
    order_best = sorted(records, key=lambda r: (_err(r), -r.get("NI", 0), r.get("pair", "")))
    out, seen = [], set()

    def take(lst, n, reason):
        k = 0
        for r in lst:
            if k >= n:
                break
            key = (r.get("scene"), r.get("pair"))
            if key in seen:
                continue
            seen.add(key)
            out.append((r, reason))
            k += 1
    take(order_worst, max(0, worst), "worst")
    take(order_best, max(0, best), "best")
    rest = [r for r in records if (r.get("scene"), r.get("pair")) not in seen]
    if random > 0 and rest:
        idx = np.random.default_rng(seed).choice(len(rest), size=min(random, len(rest)), replace=False)
        for k in sorted(idx):
            out.append((rest[k], "random"))
    return out


def disagreements(records_a: list[dict], records_b: list[dict], n: int = 3,
                  cap_deg: float = 45.0) -> list[tuple[str, str]]:
    """(scene, pair) of the ``n`` pairs whose pose errors differ most between two evaluations (errors capped at
    ``cap_deg`` so that a failure counts as a large error, ties broken by the difference in inliers)."""
    b = {(r["scene"], r["pair"]): r for r in records_b}
    scored = []
    for r in records_a:
        k = (r["scene"], r["pair"])
        if k not in b:
            continue
        ea, eb = min(_err(r), cap_deg), min(_err(b[k]), cap_deg)
        scored.append((-abs(ea - eb), -abs(r.get("NI", 0) - b[k].get("NI", 0)), k))
    scored.sort()
    return [k for *_, k in scored[:max(0, n)]]
