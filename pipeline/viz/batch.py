"""Rendering sets of figures into a folder, and their gallery entries (what `tune viz` runs).

    from pipeline.viz.batch import VizOptions, render_pairs, render_compare, render_bags, gallery_entries
    results = render_pairs(scenes, conf, "out/", worst=2, best=2, random=2)     # evaluate, select, draw
    results = render_pairs(scenes, conf, "out/", pairs=["0000.jpg|0004.jpg"])   # named pairs only
    results = render_compare(scenes, [(conf_a, "A"), (conf_b, "B")], "out/")    # same pairs, two configs
    results = render_bags(scenes, conf, MultiviewConfig(), "out/")               # one bag per size
    write_gallery("out/gallery.html", gallery_entries(results, "out/"))

Each result is a JSON-able dict (the figure's numbers and its PNG path). Figures are named after the scene,
the pair (or bag) and a short hash of the configuration, so re-running overwrites the same files.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.config import PipelineConfig, config_hash
from pipeline.data.scene import Scene
from pipeline.errors import ImtuneError


@dataclass(frozen=True)
class VizOptions:
    """How figures are drawn. width: figure width in px (a comparison: each panel half of it); max_lines: at most
    this many match lines per figure; layout: "horizontal" | "vertical" for single-configuration figures;
    use_depth: use depth maps where the scene has them; seed: of the random subset of lines drawn;
    panel_width: width of each image in a multiview montage."""
    width: int = 1600
    max_lines: int = 200
    layout: str = "horizontal"
    use_depth: bool = True
    seed: int = 0
    panel_width: int = 520


def _slug(text: str) -> str:
    s = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in str(text))
    return s.strip("._") or "x"


def _stem(name: str) -> str:
    """An image name without its extension, folders kept ("scene0707_00/color/15.jpg" -> "scene0707_00_color_15"):
    the file name alone made the figures of two pairs one PNG, the first overwritten."""
    return _slug(str(Path(name).with_suffix("")))


def _png_path(out_dir: Path, prefix: str, sc, pair, tag: str, used: dict) -> Path:
    """``<prefix><scene>_<image i>_<image j>_<tag>.png`` in ``out_dir``, numbered (-2, -3, ...) where another pair of
    this run already has that name (names alike once slugged: "a b.jpg" / "a_b.jpg", "1.jpg" / "1.png")."""
    base = f"{prefix}{_slug(sc.name)}_{_stem(pair.i)}_{_stem(pair.j)}_{tag}"
    png, k = out_dir / f"{base}.png", 1
    while used.setdefault(png, (sc.name, pair.key)) != (sc.name, pair.key):
        k += 1
        png = out_dir / f"{base}-{k}.png"
    return png


def _num(v):
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if not math.isfinite(v):
            return None if math.isnan(v) else "inf"
    if isinstance(v, np.integer):
        return int(v)
    return v


def _clean(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        if k == "figure":
            continue
        out[k] = _clean(v) if isinstance(v, dict) else _num(v)
    return out


def _progress(it, desc: str, progress: bool, total=None):
    from tqdm.auto import tqdm
    return tqdm(it, desc=desc, total=total, disable=not progress, leave=False)


def _require_ground_truth(scenes: list[Scene]) -> None:
    """Choosing pairs by pose error needs ground truth: a one-line error naming the first scene without it."""
    from pipeline.viz.stereo import has_ground_truth
    for sc in scenes:
        bad = next((p for p in sc.pairs if not has_ground_truth(sc, p)), None)
        if bad is not None:
            raise ImtuneError(f"scene {sc.name} has no ground truth for pair {bad.key} (intrinsics and poses), so "
                              f"pairs cannot be chosen by pose error: build it with `tune data build-gt --scenes "
                              f"{sc.name}`, or name the pairs to draw with --pairs")


def render_pairs(scenes: list[Scene], conf: PipelineConfig, out_dir: str | Path, *, cache=None,
                 pairs: list[str] | None = None, worst: int = 2, best: int = 2, random: int = 2,
                 sample_seed: int = 0, min_covisibility: float | None = 0.1, label: str | None = None,
                 opts: VizOptions = VizOptions(), progress: bool = False) -> list[dict]:
    """Stereo figures of one configuration into ``out_dir``.

    pairs: pair specs (``"i|j"`` or ``"scene:i|j"``; see :func:`pipeline.viz.select.find_pair`) -> those
    pairs only (section "chosen"), without evaluating the rest. Otherwise the scenes are evaluated (stereo
    task, cached stages) and the ``worst``, ``best`` and ``random`` pairs drawn (sections of those names).
    Returns one dict per figure: section, scene, pair, png, NM, NI, err, err_R, err_t (deg), failure,
    error_kind, stats, label, config (hash)."""
    from pipeline.cache import H5Cache
    from pipeline.config_files import config_label
    from pipeline.viz.select import find_pair, select_records
    from pipeline.viz.stereo import render_pair
    cache = cache if cache is not None else H5Cache()
    out_dir = Path(out_dir)
    label = label or config_label(conf)
    h = config_hash(conf, 8)
    if pairs:
        todo: list[tuple] = [(*find_pair(scenes, spec), "chosen") for spec in pairs]
    else:
        from pipeline.tasks.stereo import evaluate_stereo
        _require_ground_truth(scenes)
        res = evaluate_stereo(scenes, conf, cache, min_covisibility=min_covisibility, progress=progress,
                              keep_pairs=True)  # the figures draw these results: no second estimator run
        if not res.records:
            raise ImtuneError(f"no evaluation pairs in {', '.join(s.name for s in scenes)} "
                              f"(co-visibility >= {min_covisibility})")
        by = {s.name: s for s in scenes}
        todo = []
        for rec, reason in select_records(res.records, worst, best, random, sample_seed):
            sc = by[rec["scene"]]
            pair = next(p for p in sc.pairs if p.key == rec["pair"])
            todo.append((sc, pair, reason, res.pairs.get((sc.name, pair.key))))
    results: list[dict] = []
    used: dict[Path, tuple[str, str]] = {}  # png -> (scene, pair) that took the name
    for sc, pair, reason, *pm in _progress(todo, "figures", progress):
        png = _png_path(out_dir, "", sc, pair, h, used)
        r = render_pair(sc, pair, conf, cache, png, width=opts.width, max_lines=opts.max_lines, layout=opts.layout,
                        label=label, use_depth=opts.use_depth, seed=opts.seed, pm=pm[0] if pm else None)
        r = _clean(r)
        r.update(section=reason, label=label, config=h)
        results.append(r)
    return results


def render_compare(scenes: list[Scene], confs: list[tuple[PipelineConfig, str]], out_dir: str | Path, *, cache=None,
                   pairs: list[str] | None = None, n: int = 3, min_covisibility: float | None = 0.1,
                   opts: VizOptions = VizOptions(), progress: bool = False) -> list[dict]:
    """The same pairs drawn for two (or more) configurations, side by side (each panel: image 1 above image
    2). pairs: pair specs; default: the ``n`` pairs on which the configurations' pose errors differ most
    (both are evaluated on the scenes). confs: [(config, label), ...]. Returns one dict per figure (section
    "compare", png, and per configuration its label and numbers under "panels")."""
    from pipeline.cache import H5Cache
    from pipeline.viz.compose import side_by_side
    from pipeline.viz.select import disagreements, find_pair
    from pipeline.viz.stereo import render_pair, save_png
    if len(confs) < 2:
        raise ImtuneError("a comparison needs two configurations")
    cache = cache if cache is not None else H5Cache()
    out_dir = Path(out_dir)
    if pairs:
        todo = [find_pair(scenes, spec) for spec in pairs]
    else:
        from pipeline.tasks.stereo import evaluate_stereo
        _require_ground_truth(scenes)
        evals = [evaluate_stereo(scenes, c, cache, min_covisibility=min_covisibility, progress=progress,
                                 keep_pairs=True) for c, _ in confs]
        recs = [e.records for e in evals[:2]]
        by = {s.name: s for s in scenes}
        todo = []
        for scene_name, key in disagreements(recs[0], recs[1], n):
            sc = by[scene_name]
            todo.append((sc, next(p for p in sc.pairs if p.key == key)))
        if not todo:
            raise ImtuneError(f"no evaluation pairs in {', '.join(s.name for s in scenes)} to compare")
    hashes = [config_hash(c, 8) for c, _ in confs]
    panel_w = max(320, (opts.width - 16 * (len(confs) - 1)) // len(confs))
    results: list[dict] = []
    used: dict[Path, tuple[str, str]] = {}  # png -> (scene, pair) that took the name
    for sc, pair in _progress(todo, "comparisons", progress):
        panels, figs = [], []
        for k, ((c, lab), hsh) in enumerate(zip(confs, hashes)):
            pm = evals[k].pairs.get((sc.name, pair.key)) if not pairs else None
            r = render_pair(sc, pair, c, cache, None, width=panel_w, max_lines=opts.max_lines, layout="vertical",
                            label=lab, use_depth=opts.use_depth, seed=opts.seed, pm=pm)
            figs.append(r["figure"].image)
            panels.append(dict(_clean(r), label=lab, config=hsh))
        img = side_by_side(figs, gap=16)
        png = _png_path(out_dir, "compare_", sc, pair, "_".join(hashes), used)
        save_png(img, png)
        results.append({"section": "compare", "scene": sc.name, "pair": pair.key, "png": str(png), "panels": panels,
                        "config": "_".join(hashes)})
    return results


def _select_jobs(jobs: list, bags: list[tuple[int, int]] | None, per_size: int) -> list:
    if bags:
        out = []
        sizes = sorted({j.size for j in jobs})
        for size, index in bags:
            hit = [j for j in jobs if (j.size == size or (size > max(sizes) and j.size == max(sizes)))
                   and j.index == index]
            if not hit:
                have = ", ".join(f"{s}: {sum(1 for j in jobs if j.size == s)} bags" for s in sizes)
                raise ImtuneError(f"scene {jobs[0].scene if jobs else '?'}: no bag of size {size} with index {index} "
                                  f"(sampled: {have or 'none'})")
            out.append(hit[0])
        return out
    out = []
    for size in sorted({j.size for j in jobs}):
        out.extend([j for j in jobs if j.size == size][:max(1, per_size)])
    return out


def render_bags(scenes: list[Scene], conf: PipelineConfig, mv, out_dir: str | Path, *, cache=None,
                bags: list[tuple[int, int]] | None = None, per_size: int = 1, label: str | None = None,
                opts: VizOptions = VizOptions(), progress: bool = False) -> list[dict]:
    """Multiview figures: bags of each scene (sampled as the multiview task samples them, with ``mv`` a
    ``MultiviewConfig``) reconstructed and drawn. bags: [(size, index), ...] (a failed one raises
    ImtuneError); default: the first ``per_size`` bags of each size, where a failed bag is reported in its
    result (``failure``) and the others are still drawn. Returns one dict per bag."""
    import tempfile

    from pipeline.cache import H5Cache
    from pipeline.config_files import config_label
    from pipeline.metrics.pose import mean_average_accuracy
    from pipeline.tasks.multiview import scene_jobs
    from pipeline.viz.multiview import bag_stats, draw_bag, reconstruct_bag
    from pipeline.viz.stereo import save_png
    cache = cache if cache is not None else H5Cache()
    out_dir = Path(out_dir)
    label = label or config_label(conf)
    h = config_hash({"conf": conf.to_dict(), "mv": dataclasses.asdict(mv)}, 8)
    results = []
    with tempfile.TemporaryDirectory(prefix="imtune-viz-jobs-") as tmp:
        for sc in scenes:
            jobs = _select_jobs(scene_jobs(sc, conf, mv, cache, tmp, progress=progress), bags, per_size)
            for job in _progress(jobs, f"{sc.name}: bags", progress):
                base = {"section": "multiview", "scene": sc.name, "bag_size": job.size, "bag": job.index,
                        "images": list(job.names), "label": label, "config": h}
                try:
                    bag = reconstruct_bag(job, max_side=conf.feature.max_side)
                except ImtuneError as e:
                    if bags:
                        raise
                    results.append(dict(base, png=None, failure=str(e)))
                    continue
                img = draw_bag(bag, label=label, panel_width=opts.panel_width)
                png = save_png(img, out_dir / f"bag_{_slug(sc.name)}_{job.size}-{job.index:03d}_{h}.png")
                rec = bag.record
                results.append(dict(base, png=str(png), failure=None, registered=list(rec.get("registered", [])),
                                    NL=_num(rec.get("NL")), TL=_num(rec.get("TL")),
                                    mAA10=_num(mean_average_accuracy(rec.get("errors", []), 10)),
                                    ATE=_num(rec.get("ATE")), per_image=bag_stats(bag)))
    return results


def _fmt_deg(v) -> str:
    if v is None or v == "inf":
        return "∞"
    return f"{float(v):.2f}°"


def gallery_entries(results: list[dict], gallery_dir: str | Path) -> list:
    """Gallery entries (PNG paths relative to ``gallery_dir``) for results of the render functions; results
    without a PNG (failed bags) are skipped."""
    from pipeline.viz.gallery import GalleryEntry
    gallery_dir = Path(gallery_dir).resolve()
    out = []
    for r in results:
        if not r.get("png"):
            continue
        rel = os.path.relpath(Path(r["png"]).resolve(), gallery_dir)
        sec = r["section"]
        if sec == "compare":
            lines = []
            for k, p in enumerate(r["panels"]):
                state = f"FAILED ({p['failure']})" if p.get("failure") else \
                    f"R {_fmt_deg(p.get('err_R'))}, t {_fmt_deg(p.get('err_t'))}"
                lines.append(f"{'ABCDEFGH'[k]}: {p['label']} — NI {p.get('NI')}, {state}")
            out.append(GalleryEntry(png=rel, section=sec, title=f"{r['scene']}: {r['pair']}", lines=lines,
                                    scope=r.get("config", ""), data=r))
        elif sec == "multiview":
            lines = [f"registered {len(r.get('registered', []))}/{len(r.get('images', []))}, NL {r.get('NL')}, "
                     f"TL {float(r.get('TL') or 0):.2f}, mAA(10°) {float(r.get('mAA10') or 0):.3f}", r.get("label", "")]
            out.append(GalleryEntry(png=rel, section=sec, title=f"{r['scene']}: bag of {r['bag_size']} (#{r['bag']})",
                                    lines=lines, scope=r.get("config", ""), data=r))
        else:
            state = f"FAILED ({r['failure']})" if r.get("failure") else "no ground truth" if r.get("no_ground_truth") \
                else f"pose error R {_fmt_deg(r.get('err_R'))}, t {_fmt_deg(r.get('err_t'))}"
            lines = [f"NI {r.get('NI')} of NM {r.get('NM')}; {state}; error: {r.get('error_kind')}", r.get("label", "")]
            out.append(GalleryEntry(png=rel, section=sec, title=f"{r['scene']}: {r['pair']}", lines=lines,
                                    scope=r.get("config", ""), data=r))
    return out


# ---------------------------------------------------------------------------------------------- per task

def _stereo_figures(scenes, conf, out_dir, *, cache=None, pairs=None, worst=2, best=2, random=2, sample_seed=0,
                    min_covisibility=0.1, label=None, opts=VizOptions(), progress=False, **_) -> tuple[list, set]:
    res = render_pairs(scenes, conf, out_dir, cache=cache, pairs=pairs, worst=worst, best=best, random=random,
                       sample_seed=sample_seed, min_covisibility=min_covisibility, label=label, opts=opts,
                       progress=progress)
    return res, (set() if pairs else {"worst", "best", "random"})


def _multiview_figures(scenes, conf, out_dir, *, cache=None, mv=None, bags=None, label=None, opts=VizOptions(),
                       progress=False, **_) -> tuple[list, set]:
    from pipeline.tasks.multiview import MultiviewConfig
    return render_bags(scenes, conf, mv or MultiviewConfig(), out_dir, cache=cache, bags=bags, label=label,
                       opts=opts, progress=progress), set()


#: the figures of each task (a task without an entry has none): name -> fn(scenes, conf, out_dir, **options)
#: returning (figure dicts, gallery sections they replace)
TASK_FIGURES = {"stereo": _stereo_figures, "multiview": _multiview_figures}


def render_task(task: str, scenes, conf, out_dir, **options) -> tuple[list[dict], set]:
    """The figures of ``task`` (see :data:`TASK_FIGURES`; options: cache, pairs, worst, best, random, sample_seed,
    min_covisibility, label, opts, progress for stereo; mv, bags for multiview)."""
    if task not in TASK_FIGURES:
        raise ImtuneError(f"no figures for task {task!r} (figures exist for {', '.join(TASK_FIGURES)})")
    return TASK_FIGURES[task](scenes, conf, out_dir, **options)
