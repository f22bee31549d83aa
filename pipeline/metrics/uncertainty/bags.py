"""Multiview bag records: what identifies a bag, whether two sets hold the same bags, how bags are weighed."""
from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

# ------------------------------------------------------------------------------------------ multiview runs

def _bag_unit(r: Mapping) -> tuple:
    """A bag record's key: ((scene, bag size), its images) -- what makes two records the same bag. The runs of one
    test reconstruct the same bags (only COLMAP's seed varies); two configurations do only where their bags were
    drawn alike (the bag seed and the scene's 3D points; each bag size has its own generator, seeded by the bag seed
    and the size, so another count of one size changes no other size's bags and more bags of a size keep the first
    ones), so the bag index alone can name another bag in each. A record without its images (a test.json of an
    earlier imtune) is keyed by its index, which names the same bag only within one test."""
    imgs = r.get("images")
    st = (r["scene"], int(r["bag_size"]))
    return (st, tuple(str(x) for x in imgs)) if imgs else (st, int(r["bag"]))



def is_bag_records(records: Sequence[Mapping]) -> bool:
    """Whether records are multiview bag records ("scene", "bag_size", "errors"), not stereo pair records."""
    return bool(records) and all("errors" in r and "bag_size" in r for r in records)



def bags_differ(bags_a: Sequence[Mapping], bags_b: Sequence[Mapping]) -> str | None:
    """Why two sets of bag records (each maybe several runs' records) cannot be compared bag by bag, or None when
    they hold the same bags (scene, size and images; :func:`_bag_unit`). A reason names what to do about it."""
    def known(recs):
        return all(r.get("images") for r in recs)
    if not (known(bags_a) and known(bags_b)):
        return ("a test.json of an earlier imtune does not record its bags' images, so its bags cannot be matched "
                "(rerun `tune test` to record them)")
    ka, kb = {_bag_unit(r) for r in bags_a}, {_bag_unit(r) for r in bags_b}
    if ka != kb:
        return (f"the bags differ ({len(ka - kb)} of {len(ka)} bags only in one, {len(kb - ka)} of {len(kb)} only in "
                "the other: another bag seed, bag sizes or counts, scenes, or 3D points)")
    return None



def _bag_weights(strata: Iterable[tuple], scene_names: Sequence[str]) -> dict:
    """{(scene, size): weight} as the multiview task averages: the mean over a scene's bag sizes, then over the
    scenes (a scene without bags counts 0, its weight going to no stratum)."""
    strata = list(dict.fromkeys(strata))
    out = {}
    for n in scene_names:
        mine = [st for st in strata if st[0] == n]
        for st in sorted(mine, key=lambda x: x[1]):
            out[st] = 1.0 / (len(scene_names) * len(mine))
    return out
