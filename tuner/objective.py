"""The objective: trial parameters -> PipelineConfig -> stereo evaluation of the validation scenes ->
mAA(10 deg), to maximise (:class:`MultiviewObjective`: the same for the multiview task).

The validation pairs are evaluated in fixed chunks (``chunk_pairs`` pairs, the same order in every
trial); after each chunk the running mAA(10) is reported as an intermediate value so the pruner can
stop a hopeless trial early. Features and k-NN tables come from the cache (warmed once by
:meth:`ValidationSet.prepare`), so a trial costs the ratio test, the estimator runs and pose recovery.

Each trial records, as user attributes: ``mAA5``, ``mAA10``, ``NF`` (features per image), ``NM``
(tentative matches per pair), ``NI`` (inliers per pair), ``ransac_seconds_median`` /
``ransac_seconds_p90`` (estimator seconds per pair), ``match_seconds`` (matching seconds per pair),
``scenes`` (per-scene mAA5, mAA10, pairs, failed, accuracy, covisibility), ``accuracy`` (at 1..10 deg) and
``covisibility`` (the breakdown by co-visibility bin; the plots' source), ``failed`` and ``failed_pairs`` (pairs with
error infinity), ``feasible``, and ``timing`` (pairs, budget B, ``ransac_seconds_total`` and
``evaluate_seconds`` of the trial, for the overhead benchmark). Feasibility is an Optuna constraint
(``trial.set_constraint("budget", median - B)``, Optuna 5's replacement of TPE's deprecated
``constraints_func``): a trial whose median estimator time per pair exceeds B is infeasible — TPE
treats it so, and it is never frozen.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from dataclasses import dataclass, field

import numpy as np

from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError

BUDGET_CONSTRAINT = "budget"
MAX_FAILED_LISTED = 50


def data_fingerprint(scenes_pairs, min_covisibility) -> str:
    """SHA-1 (16 hex) of the evaluation data: per scene its name, every used image's file digest and
    ground-truth K, R, t, and the selected pair list (with co-visibility)."""
    from pipeline.cache import file_digest
    h = hashlib.sha1()
    h.update(repr(min_covisibility).encode())
    for scene, pairs in sorted(scenes_pairs, key=lambda sp: sp[0].name):
        h.update(b"scene:" + scene.name.encode())
        names = sorted({p.i for p in pairs} | {p.j for p in pairs})
        for n in names:
            info = scene.images[n]
            h.update(n.encode())
            h.update(file_digest(info.path).encode())
            for a in (info.K, info.R, info.t):
                if a is not None:
                    h.update(np.round(np.asarray(a, np.float64), 9).tobytes())
        for p in pairs:
            h.update(p.key.encode())
            h.update(repr(None if p.covisibility is None else round(float(p.covisibility), 6)).encode())
            for a in (p.R, p.t, p.K_i, p.K_j):
                if a is not None:
                    h.update(np.round(np.asarray(a, np.float64), 9).tobytes())
    return h.hexdigest()[:16]


def subsample_pairs(pairs: list, max_pairs: int | None) -> list:
    """At most ``max_pairs`` pairs, evenly spread (deterministic); None / 0 = all."""
    if not max_pairs or len(pairs) <= max_pairs:
        return list(pairs)
    idx = np.unique(np.linspace(0, len(pairs) - 1, max_pairs).round().astype(int))
    return [pairs[i] for i in idx]


@dataclass
class ValidationSet:
    """Scenes and their selected pairs, split into evaluation chunks.

    scenes: [(Scene, [Pair, ...])]; chunks: Scene copies holding ``chunk_pairs`` pairs each, named
    ``<scene>#<k>`` (evaluated in order; each chunk is one pruning step)."""
    scenes: list
    min_covisibility: float | None = 0.1
    chunk_pairs: int = 12
    chunks: list = field(default_factory=list)
    chunk_scene: dict = field(default_factory=dict)  # chunk name -> scene name
    nf: dict = field(default_factory=dict)  # scene name -> mean features per image (set by prepare)
    fingerprint: str = ""

    @classmethod
    def from_scenes(cls, scene_objs, min_covisibility: float | None = 0.1, max_pairs: int | None = None,
                    chunk_pairs: int = 12) -> "ValidationSet":
        sp = []
        for s in scene_objs:
            pairs = subsample_pairs(s.select_pairs(min_covisibility), max_pairs)
            if not pairs:
                raise ImtuneError(f"scene {s.name}: no evaluation pairs (co-visibility >= {min_covisibility})")
            sp.append((s, pairs))
        vs = cls(scenes=sp, min_covisibility=min_covisibility, chunk_pairs=max(1, int(chunk_pairs)))
        for s, pairs in sp:
            for k in range(0, len(pairs), vs.chunk_pairs):
                name = f"{s.name}#{k // vs.chunk_pairs}"
                vs.chunks.append(dataclasses.replace(s, name=name, pairs=pairs[k:k + vs.chunk_pairs]))
                vs.chunk_scene[name] = s.name
        vs.fingerprint = data_fingerprint(sp, min_covisibility)
        return vs

    @property
    def scene_names(self) -> list[str]:
        return [s.name for s, _ in self.scenes]

    @property
    def n_pairs(self) -> int:
        return sum(len(p) for _, p in self.scenes)

    def prepare(self, conf: PipelineConfig, cache, progress: bool = False) -> None:
        """Extract features and k-NN tables of every pair once (cached), and record NF per scene."""
        from pipeline.tasks.stereo import prepare_scene
        for s, pairs in self.scenes:
            feats, _ = prepare_scene(s, conf, cache, pairs, progress=progress)
            self.nf[s.name] = float(np.mean([len(f.keypoints) for f in feats.values()])) if feats else 0.0


def summarize_records(records: list[dict], vs: ValidationSet, chunk_names: bool = True) -> dict:
    """Overall summary (mean over scenes, as the benchmark averages) and per-scene summaries."""
    from pipeline.tasks.stereo import combine, summarize
    by_scene: dict[str, list] = {}
    for r in records:
        name = vs.chunk_scene.get(r["scene"], r["scene"]) if chunk_names else r["scene"]
        by_scene.setdefault(name, []).append(r)
    summaries = {name: summarize(recs, vs.nf.get(name, 0.0)) for name, recs in by_scene.items()}
    overall = combine(summaries, records)
    overall["scenes"] = summaries
    return overall


def config_for(base: PipelineConfig, params: dict, fixed: dict | None = None, seed: int | None = None) -> PipelineConfig:
    """The pipeline configuration of one trial: ``base`` with the fixed, then the searched values."""
    v = {**(fixed or {}), **params}
    m = base.matching
    g = base.geometry
    mkw = {}
    if "ratio" in v:
        mkw["ratio"] = float(v["ratio"])
    if "strategy" in v:
        mkw["strategy"] = str(v["strategy"])
    gkw = {}
    if "threshold" in v:
        gkw["threshold"] = float(v["threshold"])
    if "max_iters" in v:
        gkw["max_iters"] = int(v["max_iters"])
    if seed is not None:
        gkw["seed"] = int(seed)
    return dataclasses.replace(base, matching=dataclasses.replace(m, **mkw), geometry=dataclasses.replace(g, **gkw))


def set_budget_constraint(trial, value: float) -> None:
    """``trial.set_constraint("budget", value)`` (> 0: infeasible). A retried trial (the parameters of
    a killed worker's trial, re-enqueued) inherits the dead trial's system attributes; its own
    measurement replaces the inherited value."""
    key = f"constraints:{BUDGET_CONSTRAINT}"
    if key in trial.storage.get_trial_system_attrs(trial._trial_id):
        trial.storage.set_trial_system_attr(trial._trial_id, key, float(value))
    else:
        trial.set_constraint(BUDGET_CONSTRAINT, float(value))


class Objective:
    """Callable for ``study.optimize``: one trial = one stereo evaluation of the validation set.

    base: the study's fixed pipeline configuration; space: the (resolved) search space; vs: the
    prepared validation set; cache: an H5Cache (shared by all trials of this process); budget: B in
    seconds per pair (median estimator time); prune_over_budget: stop a trial early once its running
    median exceeds this multiple of B (it is infeasible whatever the rest gives)."""

    def __init__(self, base: PipelineConfig, space, vs: ValidationSet, cache, budget: float,
                 prune_over_budget: float = 2.0):
        self.base = base
        self.space = space
        self.vs = vs
        self.cache = cache
        self.budget = float(budget)
        self.prune_over_budget = prune_over_budget
        self.trials_run: list[int] = []

    def __call__(self, trial) -> float:
        import optuna
        from pipeline.tasks.stereo import evaluate_stereo
        t0 = time.perf_counter()
        params = self.space.suggest(trial)
        conf = config_for(self.base, params, self.space.fixed)
        self.trials_run.append(trial.number)
        done: list[dict] = []

        def on_scene(idx, name, summary):
            value = float(summary["mAA10"])
            trial.report(value, idx)
            med = float(summary.get("ransac_seconds_median", 0.0))
            if idx + 1 >= len(self.vs.chunks):
                return  # the last chunk: the trial is complete, never pruned after all the work is done
            over = bool(self.prune_over_budget) and med > self.prune_over_budget * self.budget
            if over or trial.should_prune():
                done.append(summary)
                set_budget_constraint(trial, med - self.budget)
                trial.set_user_attr("pruned_at_pairs", int(summary.get("pairs", 0)))
                trial.set_user_attr("ransac_seconds_median", med)
                trial.set_user_attr("feasible", bool(med <= self.budget))
                n = int(summary.get("pairs", 0))
                trial.set_user_attr("timing", {"pairs": n, "budget": self.budget,
                                               "ransac_seconds_total": float(summary.get("ransac_seconds", 0.0)) * n,
                                               "evaluate_seconds": time.perf_counter() - t0})
                if over:
                    trial.set_user_attr("pruned_reason", f"over budget: median {med:.3f} s > "
                                                         f"{self.prune_over_budget:g} x {self.budget:g} s")
                raise optuna.TrialPruned()

        res = evaluate_stereo(self.vs.chunks, conf, self.cache, min_covisibility=None, progress=False,
                              on_scene=on_scene)
        s = summarize_records(res.records, self.vs)
        med = float(s["ransac_seconds_median"])
        set_budget_constraint(trial, med - self.budget)
        failed = [r["pair"] if len(self.vs.scenes) == 1 else f"{self.vs.chunk_scene.get(r['scene'], r['scene'])}:{r['pair']}"
                  for r in res.records if not math.isfinite(r["err"])]
        attrs = {
            "mAA5": s["mAA5"], "mAA10": s["mAA10"], "NF": s["NF"], "NM": s["NM"], "NI": s["NI"],
            "ransac_seconds_median": med, "ransac_seconds_p90": float(s["ransac_seconds_p90"]),
            "match_seconds": s["match_seconds"],
            "scenes": {k: {"mAA5": v["mAA5"], "mAA10": v["mAA10"], "pairs": v["pairs"], "failed": v["failed"],
                           "accuracy": v.get("accuracy"), "covisibility": v.get("covisibility")}
                       for k, v in s["scenes"].items()},
            "accuracy": s.get("accuracy"), "covisibility": s.get("covisibility"),
            "failed": s["failed"], "failed_pairs": failed[:MAX_FAILED_LISTED],
            "feasible": bool(med <= self.budget),
        }
        attrs["timing"] = {"pairs": s["pairs"], "budget": self.budget,
                           "ransac_seconds_total": float(sum(r["ransac_seconds"] for r in res.records)),
                           "evaluate_seconds": time.perf_counter() - t0}
        for k, v in attrs.items():
            trial.set_user_attr(k, v)
        return float(s["mAA10"])


MULTIVIEW_ATTRS = ("SR", "RC", "NL", "TL", "mAA5", "mAA10", "ATE", "NM", "bags", "failed")


def multiview_attrs(summary: dict, scenes: dict) -> dict:
    """The user attributes of a multiview trial: the overall figures, accuracy at 1..10 deg, the per-bag-size
    figures and, per scene, the same (``scenes``)."""
    def part(s):
        d = {k: s.get(k) for k in MULTIVIEW_ATTRS}
        d["accuracy"] = s.get("accuracy")
        d["by_size"] = {size: {k: v.get(k) for k in MULTIVIEW_ATTRS} for size, v in (s.get("by_size") or {}).items()}
        return d
    out = part(summary)
    out["scenes"] = {name: part(s) for name, s in scenes.items()}
    return out


class MultiviewObjective:
    """Callable for ``study.optimize`` on the multiview task: one trial = the multiview evaluation
    (bags reconstructed by COLMAP from the trial's tentative matches) of the validation scenes ->
    mAA(10). After each scene the running mAA(10) is reported for the pruner. Only the matching is
    searched (COLMAP runs its own RANSAC), so there is no estimator budget: every trial is feasible.

    workers: bag processes (None: the task's default, all available CPUs; trials run one at a time
    per tuner process)."""

    def __init__(self, base: PipelineConfig, space, scenes: list, cache, mv, workers: int | None = None):
        self.base = base
        self.space = space
        self.scenes = list(scenes)
        self.cache = cache
        self.mv = mv
        self.workers = workers
        self.trials_run: list[int] = []

    def __call__(self, trial) -> float:
        import optuna
        from pipeline.tasks.multiview import evaluate_multiview
        t0 = time.perf_counter()
        params = self.space.suggest(trial)
        conf = config_for(self.base, params, self.space.fixed)
        self.trials_run.append(trial.number)

        def on_scene(idx, name, summary):
            trial.report(float(summary["mAA10"]), idx)
            if idx + 1 < len(self.scenes) and trial.should_prune():
                trial.set_user_attr("pruned_at_scene", name)
                raise optuna.TrialPruned()

        res = evaluate_multiview(self.scenes, conf, self.mv, self.cache, workers=self.workers, on_scene=on_scene)
        attrs = multiview_attrs(res.summary, res.scenes)
        attrs["feasible"] = True
        attrs["timing"] = {"bags": int(res.summary.get("bags", 0)), "evaluate_seconds": time.perf_counter() - t0,
                           **{f"{k}_seconds": float(v) for k, v in res.seconds.items()}}
        for k, v in attrs.items():
            trial.set_user_attr(k, v)
        return float(res.summary["mAA10"])
