"""Posed scenes written into the IMC 2024/2025 layout, several scenes mixed into one dataset (`tune data to-imc`).

Any scene imtune loads with poses (Strecha's laser-scan cameras, a COLMAP model, IMC 2022, IMC-PT) becomes one
ground-truth scene of the dataset; scenes named as ``outliers`` give outlier images (no pose). Image names are
prefixed with their scene (``<scene>_<image>``) so that names never collide. Poses keep the scene's own units (metres
on Strecha); the thresholds are the challenge's six (0.025 ... 1.0 m) times ``threshold_scale``. K is written as
IMC 2024's ``calibration_matrix`` where every image of a scene has one (the task may then use ``--intrinsics prior``).
"""
from __future__ import annotations

import csv
import os
import shutil
from pathlib import Path

import numpy as np

from pipeline.data.imc2025 import LABELS, OUTLIERS, THRESHOLDS
from pipeline.errors import ImtuneError

CHALLENGE_THRESHOLDS = (0.025, 0.05, 0.1, 0.2, 0.5, 1.0)


def _fmt(a) -> str:
    return ";".join(repr(float(x)) for x in np.asarray(a, float).reshape(-1))


def _append(path: Path, header: list[str], rows: list[list[str]], dataset: str) -> None:
    """Rows of ``dataset`` replace that dataset's earlier rows; other datasets' rows are kept (atomic write)."""
    kept: list[list[str]] = []
    if path.is_file():
        with open(path, newline="") as f:
            r = csv.reader(f)
            old_header = next(r, None)
            if old_header and old_header != header:
                raise ImtuneError(f"{path}: another layout (columns {', '.join(old_header)}); write to a new --out")
            kept = [row for row in r if row and row[0] != dataset]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        w.writerows(kept + rows)
    os.replace(tmp, path)


def export_imc(data_root, scenes: list[str], out, dataset: str, outliers: list[str] | tuple = (),
               threshold_scale: float = 1.0, copy: bool = False, every: int = 1,
               max_outliers: int | None = None) -> dict:
    """Write ``scenes`` (posed) and ``outliers`` (their images as outliers) of ``data_root`` as dataset ``dataset`` of
    the IMC folder ``out``. ``every`` k: a sparse subset, every k-th image of each scene in name order (wider
    baselines, fewer images: harder to register); ``max_outliers``: at most this many outlier images, spread evenly
    over the outlier scenes' images in name order. Returns a summary dict. One-line ImtuneError for a scene without
    poses, a name given twice, an output inside the data folder, ``every`` < 1 or ``max_outliers`` < 0."""
    from pipeline.data import load_scene
    out = Path(out).resolve()
    data_root = Path(data_root).resolve()
    if out == data_root or data_root in out.parents:
        raise ImtuneError(f"--out {out} is inside the data folder {data_root}: write the IMC copy elsewhere")
    if not dataset or any(c in dataset for c in "/\\,"):
        raise ImtuneError(f"--dataset {dataset!r}: give a plain name (no '/', '\\\\' or ',')")
    if not scenes:
        raise ImtuneError("--scenes: give at least one posed scene")
    both = set(scenes) & set(outliers)
    if both:
        raise ImtuneError(f"scene {sorted(both)[0]!r} is named both as a scene and as outliers")
    if not (threshold_scale > 0 and np.isfinite(threshold_scale)):
        raise ImtuneError(f"--threshold-scale must be > 0, got {threshold_scale}")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ImtuneError(f"--every must be an integer >= 1 (1: every image), got {every!r}")
    if max_outliers is not None and (isinstance(max_outliers, bool) or not isinstance(max_outliers, int)
                                     or max_outliers < 0):
        raise ImtuneError(f"--max-outliers must be an integer >= 0, got {max_outliers!r}")
    loaded = [(load_scene(data_root, s), False) for s in scenes] + [(load_scene(data_root, s), True) for s in outliers]
    for sc, is_out in loaded:
        if not is_out:
            missing = [n for n, im in sc.images.items() if im.R is None or im.t is None]
            if missing:
                raise ImtuneError(f"scene {sc.name} has no pose for image {missing[0]}: only posed scenes can be "
                                  "written (or name it with --outliers)")
    img_dir = out / "train" / dataset
    if img_dir.exists():
        shutil.rmtree(img_dir)
    img_dir.mkdir(parents=True)
    with_K = all(im.K is not None for sc, is_out in loaded if not is_out for im in sc.images.values())
    header = ["dataset", "scene", "image", "rotation_matrix", "translation_vector"] + (["calibration_matrix"]
                                                                                       if with_K else [])
    rows: list[list[str]] = []
    counts: dict[str, int] = {}
    n_out = 0
    out_names = [(sc.name, n) for sc, is_out in loaded if is_out for n in sorted(sc.images)]
    if max_outliers is not None and len(out_names) > max_outliers:
        pick: list[int] = (np.linspace(0, len(out_names) - 1, max_outliers).round().astype(int).tolist()
                           if max_outliers else [])
        out_names = [out_names[i] for i in sorted(set(pick))]
    keep_out = set(out_names)
    for sc, is_out in loaded:
        names = sorted(sc.images)
        chosen = [n for n in names if (sc.name, n) in keep_out] if is_out else names[::every]
        for n in [n for n in sc.images if n in set(chosen)]:
            im = sc.images[n]
            name = f"{sc.name}_{Path(n).name}"
            dst = img_dir / name
            if copy:
                shutil.copyfile(im.path, dst)
            else:
                os.symlink(Path(im.path).resolve(), dst)
            if is_out:
                row = [dataset, OUTLIERS, name, ";".join(["nan"] * 9), ";".join(["nan"] * 3)]
                n_out += 1
            else:
                row = [dataset, sc.name, name, _fmt(im.R), _fmt(im.t)]
                counts[sc.name] = counts.get(sc.name, 0) + 1
            if with_K:
                row.append(";".join(["nan"] * 9) if is_out or im.K is None else _fmt(im.K))
            rows.append(row)
    existing = out / LABELS
    if existing.is_file():  # another dataset's columns decide; keep the common IMC 2025 form when they differ
        with open(existing, newline="") as f:
            old = next(csv.reader(f), None) or header
        if old != header:
            header = old
            rows = [r[:len(old)] + [";".join(["nan"] * 9)] * (len(old) - len(r)) for r in rows]
    _append(existing, header, rows, dataset)
    th = ";".join(repr(round(float(x) * threshold_scale, 12)) for x in CHALLENGE_THRESHOLDS)
    _append(out / THRESHOLDS, ["dataset", "scene", "thresholds"], [[dataset, s, th] for s in counts], dataset)
    return {"out": str(out), "dataset": dataset, "images": len(rows), "scenes": counts, "outliers": n_out,
            "every": every,
            "intrinsics": with_K, "thresholds": th}
