"""Benchmark: seconds per image of every available feature at the 2k and 8k budgets (IMC working resolution).

    python benchmarks/features.py                                  # every available feature, 2 images
    python benchmarks/features.py --features dog-tfeat,keynet+affnet+mkd,aliked --images 3
    python benchmarks/features.py --kornia-only --budgets 2048     # the learned / affine ones only

For each feature: one untimed warm-up call (loads the network weights and warms torch / OpenCV), then
each image (fountain-P11 from ../shared/data/strecha, resized to the working resolution, long side
1024 px) extracted once per budget; printed: features found (NF, mean) and median seconds per image at
each budget, and the ratio to OpenCV SIFT measured in the same run (this machine is shared and its
absolute times drift by 50%: read the ratios). torch threads: the CPUs available to this process (the
extractors set them); OpenCV's own threading is left as it is. Unavailable features are listed with the
reason (e.g. missing weights) and skipped.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("TORCH_HOME", str((ROOT.parent / "shared" / "weights" / "torch").resolve()))

from pipeline.config import FeatureConfig  # noqa: E402
from pipeline.data.resize import load_image  # noqa: E402
from pipeline.errors import ImtuneError, UnavailableError  # noqa: E402
from pipeline.features import EXTRACTORS, get_extractor, resolve_feature  # noqa: E402

EXTRA = ["keynet+affnet+mkd", "hessian-laplace+baumberg+sift", "harris-laplace+tfeat"]
DATA = ROOT.parent / "shared" / "data" / "strecha" / "fountain-P11" / "images"


def feature_names(args) -> list[str]:
    if args.features:
        return [f.strip() for f in args.features.split(",") if f.strip()]
    names = [n for n in EXTRACTORS.names() if n != "custom"]
    if args.kornia_only:
        names = [n for n in names if getattr(EXTRACTORS.get(n), "learned", False)]
    return names + [e for e in EXTRA if e not in names]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--features", default=None, help="comma-separated names (default: every registered one + a few composed)")
    ap.add_argument("--kornia-only", action="store_true", help="only the kornia (learned / affine) features")
    ap.add_argument("--images", type=int, default=2, help="images of fountain-P11 to time (default 2)")
    ap.add_argument("--budgets", default="2048,8000", help="keypoint budgets (default 2048,8000)")
    ap.add_argument("--data", default=str(DATA), help="folder of images")
    args = ap.parse_args()
    paths = sorted(Path(args.data).glob("*.jpg"))[: args.images]
    if not paths:
        print(f"no images in {args.data}", file=sys.stderr)
        return 1
    images = [load_image(p, max_side=1024)[0] for p in paths]
    budgets = [int(b) for b in args.budgets.split(",")]
    h, w = images[0].shape
    try:
        import torch
        threads = f"torch threads {torch.get_num_threads()} -> set per extractor"
    except ImportError:
        threads = "no torch"
    print(f"{len(images)} image(s) {w}x{h} from {args.data}; budgets {budgets}; os.cpu_count() {os.cpu_count()}; "
          f"{threads}; load average {os.getloadavg()[0]:.1f}")
    names = feature_names(args)
    if "sift" not in names:
        names = ["sift"] + names
    rows, skipped = [], []
    for name in names:
        try:
            resolve_feature(name).check_available()
        except UnavailableError as e:
            skipped.append((name, str(e)))
            continue
        except ImtuneError as e:
            skipped.append((name, str(e)))
            continue
        row = {"name": name}
        for k in budgets:
            ext = get_extractor(FeatureConfig(name=name, num_features=k))
            t0 = time.perf_counter()
            ext.extract(images[0])  # warm-up: weights, torch kernels
            row[f"warm{k}"] = time.perf_counter() - t0
            secs, nf = [], []
            for img in images:
                t0 = time.perf_counter()
                f = ext.extract(img)
                secs.append(time.perf_counter() - t0)
                nf.append(len(f))
            row[f"s{k}"] = statistics.median(secs)
            row[f"nf{k}"] = sum(nf) / len(nf)
        rows.append(row)
        print(f"  {name:34s} " + "  ".join(f"{k}: NF {row[f'nf{k}']:6.0f}  {row[f's{k}']:6.2f} s/img"
                                            for k in budgets), flush=True)
    ref = next(r for r in rows if r["name"] == "sift")
    head = "| feature | " + " | ".join(f"NF@{k} | s/img@{k} | x SIFT@{k}" for k in budgets) + " |"
    print()
    print(head)
    print("|" + "---|" * (1 + 3 * len(budgets)))
    for r in rows:
        cells = []
        for k in budgets:
            cells += [f"{r[f'nf{k}']:.0f}", f"{r[f's{k}']:.2f}", f"{r[f's{k}'] / max(ref[f's{k}'], 1e-9):.1f}"]
        print(f"| {r['name']} | " + " | ".join(cells) + " |")
    for name, why in skipped:
        print(f"skipped {name}: {why}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
