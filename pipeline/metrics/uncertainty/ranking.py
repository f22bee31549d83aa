"""Methods ranked with ties: paired tests where they share pairs (bags), overlapping intervals otherwise."""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from pipeline.metrics.uncertainty.bags import _bag_unit, _bag_weights, is_bag_records
from pipeline.metrics.uncertainty.intervals import _scene_order
from pipeline.metrics.uncertainty.multiplicity import bonferroni
from pipeline.metrics.uncertainty.paired import _mean_scores, format_p, paired_bags, paired_bootstrap
from pipeline.metrics.uncertainty.scores import DEFAULT_LEVEL, DEFAULT_RESAMPLES, maa_from_errors


def _item(it) -> tuple[str, Sequence[Mapping]]:
    if isinstance(it, Mapping):
        return str(it["name"]), it["records"]
    name, recs = it
    return str(name), recs



def rank_with_ties(items, tau: int = 10, n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0,
                   level: float = DEFAULT_LEVEL, compare=None, value=None) -> list[dict]:
    """Rank methods by mAA(tau), sharing ranks where a difference is not significant.

    items: ``[(name, records), ...]`` or ``[{"name", "records"}, ...]``, records as for
    :func:`paired_bootstrap` (several runs' records may be concatenated: they are averaged per pair), or multiview
    bag records as for :func:`paired_bags` (every item's: then each comparison is :func:`paired_bags` on the common
    bags, and the mAA the multiview task's weighting of bags, sizes and scenes).
    The methods are ordered by mAA(tau) (highest first; ties keep the given order); each one is compared
    by :func:`paired_bootstrap` with the *leader* of the rank above it (the first, best method holding that rank;
    it as A, this one as B) and shares that rank when the difference is not significant (its CI contains 0, or
    the sign-flip test does not confirm it: ``significant``). Ranks are competition ranks (1, 1, 3): a method
    that differs significantly from the leader gets its position and leads a new rank. Comparing with the leader,
    not the row directly above, keeps small steps from chaining a tie from the top far down (C sharing rank 1
    through B though A and C differ significantly: 14 of 15 rows at rank 1 in a real table). Two methods without
    a common pair are not compared (no shared rank; the note says so).

    Multiplicity: the leader is the best of several noisy estimates and a table makes many comparisons, so each is
    made at the Bonferroni level over the k (k - 1) / 2 pairs of the k methods the ranking could compare
    (``level`` 0.95, 5 methods: the 99.5% CI and p < 0.005; the sign-flip test and the bootstrap get at least 20 /
    alpha resamples, at most 100,000, so that p can reach it). At 5% per comparison, five methods with the same
    error distribution were split off rank 1 in 28% of simulated tables (ten: 56%); Holm over the k - 1
    comparisons actually made still 9% (the leader is selected); over all pairs about 1.5%.

    ``compare`` (with ``value``): another paired comparison with :func:`paired_bootstrap`'s signature and keys
    (``difference``, ``ci``, ``p_value``, ``significant``) and the figure of an item's records; tuned rows with
    replicates are ranked with :func:`pipeline.metrics.replicates.replicated_records_comparison`.

    Returns, best first: ``[{"name", "rank", "mAA<tau>", "shared": bool (rank shared with the rank's leader),
    "comparison": paired_bootstrap overall figures against that leader (None for the first), "note": str}, ...]``."""
    tau = int(tau)
    named = [_item(it) for it in items]
    n_pairs_of_methods = max(1, len(named) * (len(named) - 1) // 2)
    level_each, alpha, resamples_each = bonferroni(level, n_pairs_of_methods, n_resamples)  # every pair (docstring)
    bags = bool(named) and all(is_bag_records(recs) for _, recs in named)
    if compare is None:
        compare = paired_bags if bags else paired_bootstrap
        value = _bag_value if bags else _pair_value
    vals = [value(recs, tau) for _, recs in named]
    order = sorted(range(len(named)), key=lambda i: -vals[i])
    out: list[dict] = []
    for pos, i in enumerate(order):
        name, recs = named[i]
        row = {"name": name, "rank": pos + 1, f"mAA{tau}": vals[i], "shared": False, "comparison": None, "note": ""}
        if out:
            lead = next(k for k, r in enumerate(out) if r["rank"] == out[-1]["rank"])  # the rank's leader
            above = out[lead]
            try:
                cmp = compare(named[order[lead]][1], recs, tau=tau, n_resamples=resamples_each, seed=seed,
                              level=level_each)
            except ValueError:  # evaluated on different pairs: nothing to pair, never a shared rank
                row["note"] = f"not compared with {above['name']}: no common {'bags' if bags else 'pairs'}"
                out.append(row)
                continue
            cmp = {k: v for k, v in cmp.items() if k != "scenes"}
            row["comparison"] = cmp
            lo, hi = cmp["ci"]
            how = (f"{100 * level_each:.3g}% CI, p={format_p(cmp['p_value'], alpha)}" if n_pairs_of_methods == 1 else
                   f"{100 * level_each:.3g}% CI, p={format_p(cmp['p_value'], alpha)} against {alpha:.2g}: Bonferroni "
                   f"over the "
                   f"{n_pairs_of_methods} pairs of {len(named)} methods")
            if not cmp["significant"]:
                row["rank"], row["shared"] = above["rank"], True
                row["note"] = (f"rank shared with {above['name']}: difference {cmp['difference']:+.4f} "
                               f"[{lo:+.4f}, {hi:+.4f}] not significant ({how})")
            else:
                row["note"] = (f"below {above['name']}: difference {cmp['difference']:+.4f} "
                               f"[{lo:+.4f}, {hi:+.4f}] ({how})")
        out.append(row)
    return out



def _pair_value(records: Sequence[Mapping], tau: int) -> float:
    """The stereo mAA(tau) of pair records (runs averaged per pair): the mean over scenes of the scenes' means."""
    by_scene: dict = {}
    for (scene, _), v in _mean_scores(records, tau).items():
        by_scene.setdefault(scene, []).append(v)
    return float(np.mean([np.mean(v) for v in by_scene.values()])) if by_scene else 0.0



def _bag_value(records: Sequence[Mapping], tau: int) -> float:
    """The multiview mAA(tau) of bag records (runs averaged per bag), weighted as the task averages: the mean over
    each (scene, size) stratum's bags, over a scene's sizes, then over the scenes."""
    acc: dict = {}
    for r in records:
        acc.setdefault(_bag_unit(r), []).append(maa_from_errors(r["errors"], tau))
    w = _bag_weights((k[0] for k in acc), _scene_order(records, None))
    return float(sum(wst * np.mean([np.mean(v) for k, v in acc.items() if k[0] == st]) for st, wst in w.items()))



def rank_by_intervals(items: Sequence[Mapping], key: str = "mAA10") -> list[dict]:
    """Rank with ties when only intervals are known (no pair records to pair): each method shares the
    rank above it when its ``<key>_ci`` interval overlaps that of the rank's leader (as :func:`rank_with_ties`).
    Conservative (overlapping 95% intervals can still hide a significant paired difference: two methods on the same pairs are
    positively correlated, which only the paired test uses). items: ``{"name", key, key + "_ci"}``;
    an item without an interval never shares. Same return shape as :func:`rank_with_ties`
    (``comparison`` is None)."""
    order = sorted(range(len(items)), key=lambda i: -float(items[i][key]))
    out: list[dict] = []
    for pos, i in enumerate(order):
        it = items[i]
        row = {"name": str(it["name"]), "rank": pos + 1, key: float(it[key]), "shared": False, "comparison": None,
               "note": ""}
        if out:
            lead = next(k for k, r in enumerate(out) if r["rank"] == out[-1]["rank"])  # the rank's leader
            above = items[order[lead]]
            ci, ci_above = it.get(f"{key}_ci"), above.get(f"{key}_ci")
            if ci and ci_above and ci[1] >= ci_above[0]:
                row["rank"], row["shared"] = out[-1]["rank"], True
                row["note"] = f"rank shared with {above['name']}: 95% intervals overlap (unpaired comparison)"
        out.append(row)
    return out
