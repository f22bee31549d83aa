"""Benchmark: exact bidirectional k=2 matching vs the SGEMM floor, OpenCV BFMatcher and torch.

    python benchmarks/matching.py --n 8000 --dim 128 --repeats 3
    python benchmarks/matching.py --binary --n 8000 --dim 32     # ORB-like 256-bit descriptors (Hamming)

Prints, side by side from one run (the methods are interleaved inside every repeat, so load from other
processes hits them alike), the median seconds per pair of:
  (a) a bare numpy SGEMM ``A @ B.T`` of the same shape (the arithmetic floor of exact matching), and the
      same SGEMM into a preallocated output (no page faults for the 256 MB result: the arithmetic alone);
  (b) ours: ``knn_tables(k=2)`` both directions + ``filter_matches`` (ratio 0.8, strategy both);
  (c) OpenCV ``BFMatcher.knnMatch(k=2)`` both ways + conversion to tables + the same filter;
  (d) torch ``cdist`` + ``topk(2)`` both ways + the same filter (skip with --no-torch);
then the ratios ours / SGEMM and OpenCV / ours, and how far our matches agree with OpenCV's.
With --binary: (a) is the SGEMM of the unpacked bits (n x n x 8*dim), which the alternative exact Hamming
path (unpack to 0/1 float32 + SGEMM) would need; (c) uses NORM_HAMMING; (d) is the unpack + float path.
Figures are reported as measured, in whatever environment this runs (e.g. OPENBLAS_CORETYPE is printed,
not changed).
"""
from __future__ import annotations

import argparse
import ctypes
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.config import MatchConfig  # noqa: E402
from pipeline.matching import KnnTables, filter_matches, knn_tables, warmup  # noqa: E402

CONF = MatchConfig(ratio=0.8, strategy="both")


def sift_like(n: int, dim: int, rng) -> np.ndarray:
    """Non-negative, L2-normalised, clipped at 0.2 and renormalised (like SIFT), float32."""
    x = rng.gamma(0.6, size=(n, dim)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    np.minimum(x, 0.2, out=x)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


def make_pair(n: int, dim: int, binary: bool, seed: int = 0, inlier_fraction: float = 0.4):
    """Two descriptor sets where a fraction of image 2 are noisy copies of image 1 (so matching is not
    trivial: some pass the ratio test, most random ones do not)."""
    rng = np.random.default_rng(seed)
    if binary:
        A = rng.integers(0, 256, (n, dim), dtype=np.uint8)
        B = rng.integers(0, 256, (n, dim), dtype=np.uint8)
        m = int(n * inlier_fraction)
        src = rng.permutation(n)[:m]
        flips = np.packbits(rng.random((m, dim * 8)) < 0.08, axis=1)
        B[:m] = A[src] ^ flips
    else:
        A = sift_like(n, dim, rng)
        B = sift_like(n, dim, rng)
        m = int(n * inlier_fraction)
        src = rng.permutation(n)[:m]
        noisy = A[src] + rng.normal(0, 0.03, (m, dim)).astype(np.float32)
        np.maximum(noisy, 0, out=noisy)
        B[:m] = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
    perm = rng.permutation(n)
    return A, B[perm]


# ----------------------------------------------------------------------------------------- threads

def _openblas_runtime() -> str:
    """Threads and core type of the OpenBLAS numpy loaded (via its exported getters), if it is OpenBLAS."""
    try:
        with open("/proc/self/maps") as fh:
            libs = {ln.split()[-1] for ln in fh if "openblas" in ln.lower() and ".so" in ln}
    except OSError:
        return ""
    for path in sorted(libs):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix in (("scipy_openblas_", "64_"), ("openblas_", "64_"), ("openblas_", "")):
            try:
                nt = getattr(lib, f"{prefix}get_num_threads{suffix}")
                cn = getattr(lib, f"{prefix}get_corename{suffix}")
            except AttributeError:
                continue
            nt.restype = ctypes.c_int
            cn.restype = ctypes.c_char_p
            return f"OpenBLAS runtime: {nt()} threads, core {cn().decode()} ({Path(path).name})"
    return ""


def thread_config() -> list[str]:
    import numba
    lines = []
    env = {k: os.environ[k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                      "OPENBLAS_CORETYPE", "NUMBA_NUM_THREADS", "NUMBA_THREADING_LAYER")
           if k in os.environ}
    lines.append(f"cpus: {os.cpu_count()}; env: {env or '(no thread variables set)'}")
    try:
        from threadpoolctl import threadpool_info
        for p in threadpool_info():
            lines.append(f"threadpoolctl: {p.get('internal_api')} {p.get('version')} threads={p.get('num_threads')} "
                         f"core={p.get('architecture')}")
    except ImportError:
        try:
            blas = np.__config__.CONFIG["Build Dependencies"]["blas"]
            lines.append(f"numpy BLAS (threadpoolctl not installed): {blas.get('name')} {blas.get('version')}; "
                         f"{' '.join(str(blas.get('openblas configuration', '')).split())}")
        except Exception:  # noqa: BLE001 - informational only
            lines.append("numpy BLAS: unknown (threadpoolctl not installed)")
        rt = _openblas_runtime()
        if rt:
            lines.append(rt)
    lines.append(f"numba {numba.__version__}: {numba.get_num_threads()} threads available "
                 f"(our kernels are serial; the SGEMM uses the BLAS threads)")
    try:
        import cv2
        lines.append(f"OpenCV {cv2.__version__}: {cv2.getNumThreads()} threads")
    except ImportError:
        pass
    return lines


# ----------------------------------------------------------------------------------------- methods

def ours(A, B, binary):
    tab = knn_tables(A, B, binary=binary, k=2)
    return filter_matches(tab, CONF)


def ours_k10(A, B, binary):
    rng = np.random.default_rng(1)
    k1 = rng.random((len(A), 2), dtype=np.float32) * 1000
    k2 = rng.random((len(B), 2), dtype=np.float32) * 1000
    tab = knn_tables(A, B, binary=binary, k=10)
    return filter_matches(tab, MatchConfig(ratio=0.8, strategy="both", fginn=True, fginn_px=10), k1, k2)


def opencv_bf(A, B, binary):
    import cv2
    bf = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2)

    def table(Q, T):
        res = bf.knnMatch(Q, T, k=2)
        idx = np.full((len(Q), 2), -1, np.int32)
        dist = np.full((len(Q), 2), np.inf, np.float32)
        for row in res:
            for q, m in enumerate(row):
                idx[m.queryIdx, q] = m.trainIdx
                dist[m.queryIdx, q] = m.distance
        return idx, dist

    i12, d12 = table(A, B)
    i21, d21 = table(B, A)
    return filter_matches(KnnTables(i12, d12, i21, d21), CONF)


def torch_cdist(A, B, binary):
    import torch
    if binary:
        a = torch.from_numpy(np.unpackbits(A, axis=1).astype(np.float32))
        b = torch.from_numpy(np.unpackbits(B, axis=1).astype(np.float32))
    else:
        a, b = torch.from_numpy(A), torch.from_numpy(B)
    with torch.no_grad():
        D = torch.cdist(a, b)
        if binary:
            D = D.square().round()
        d12, i12 = torch.topk(D, 2, dim=1, largest=False)
        d21, i21 = torch.topk(D, 2, dim=0, largest=False)
    tab = KnnTables(i12.numpy().astype(np.int32), d12.numpy(), i21.T.numpy().astype(np.int32).copy(),
                    d21.T.numpy().copy())
    return filter_matches(tab, CONF)


def unpack_float(A, B, binary):
    """The alternative exact Hamming path: bits -> 0/1 float32, SGEMM-based float search (squared L2 = Hamming)."""
    a = np.unpackbits(A, axis=1).astype(np.float32)
    b = np.unpackbits(B, axis=1).astype(np.float32)
    tab = knn_tables(a, b, binary=False, k=2)
    tab = KnnTables(tab.idx12, np.square(tab.dist12).round(), tab.idx21, np.square(tab.dist21).round())
    return filter_matches(tab, CONF)


def sgemm(A, B, binary):
    if binary:
        A = np.unpackbits(A, axis=1).astype(np.float32)
        B = np.unpackbits(B, axis=1).astype(np.float32)
    return A @ B.T


_OUT = {}


def sgemm_out(A, B, binary):
    """The same SGEMM into a preallocated (already faulted-in) output: the arithmetic alone, without the
    page faults of a fresh 256 MB result that ``A @ B.T`` pays on every call."""
    if binary:
        A = np.unpackbits(A, axis=1).astype(np.float32)
        B = np.unpackbits(B, axis=1).astype(np.float32)
    out = _OUT.get((A.shape[0], B.shape[0]))
    if out is None:
        out = _OUT[(A.shape[0], B.shape[0])] = np.ones((A.shape[0], B.shape[0]), np.float32)
    return np.matmul(A, B.T, out=out)


def agreement(m_ours, m_ref) -> tuple[float, float]:
    """(% of the reference's matches we return, Jaccard % of the two match sets)."""
    a = {(int(i), int(j)) for i, j in m_ours}
    b = {(int(i), int(j)) for i, j in m_ref}
    if not a and not b:
        return 100.0, 100.0
    return 100.0 * len(a & b) / max(len(b), 1), 100.0 * len(a & b) / len(a | b)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=8000, help="descriptors per image (default 8000)")
    ap.add_argument("--dim", type=int, default=128, help="descriptor size: floats, or bytes with --binary")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats; the median is reported")
    ap.add_argument("--binary", action="store_true", help="uint8 packed-bit descriptors, Hamming distance")
    ap.add_argument("--no-torch", action="store_true", help="skip torch cdist + topk")
    ap.add_argument("--kernel-threads", type=int, default=None,
                    help="numba threads of our k=2 kernel (default: the library's, 1 = serial)")
    ap.add_argument("--with-k10", action="store_true",
                    help="also time ours with k=10 tables + the FGINN filter (random keypoints)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    from pipeline.matching import knn as knn_mod
    if args.kernel_threads is not None:
        knn_mod.KERNEL_THREADS = args.kernel_threads

    kind = f"binary {args.dim * 8} bits (Hamming)" if args.binary else f"float32 x {args.dim} (L2, SIFT-like)"
    print(f"matching benchmark: {args.n} x {args.n} descriptors, {kind}, k=2 both ways, "
          f"ratio {CONF.ratio}, strategy {CONF.strategy}, median of {args.repeats}")
    for line in thread_config():
        print("  " + line)
    print(f"  our k=2 kernel: {knn_mod.KERNEL_THREADS} numba thread(s); block {knn_mod.BLOCK_BYTES >> 20} MB")
    A, B = make_pair(args.n, args.dim, args.binary, args.seed)

    methods = [("sgemm", "(a) numpy SGEMM A @ B.T" + (" (unpacked bits)" if args.binary else ""), sgemm),
               ("sgemm_out", "    same SGEMM into a preallocated output", sgemm_out),
               ("ours", "(b) ours: knn_tables + filter_matches", ours),
               ("opencv", "(c) OpenCV BFMatcher.knnMatch k=2 both ways + filter", opencv_bf)]
    if args.binary:
        methods.append(("unpack", "(d) unpack bits + float search + filter", unpack_float))
    if not args.binary and not args.no_torch:
        try:
            import torch
            torch.set_num_threads(os.cpu_count() or 1)
            methods.append(("torch", "(d) torch cdist + topk both ways + filter", torch_cdist))
        except ImportError:
            print("  torch not installed: (d) skipped")
    if args.with_k10:
        methods.append(("k10", "(e) ours: knn_tables(k=10) + FGINN filter", ours_k10))

    t0 = time.perf_counter()
    warmup()  # numba JIT (or its on-disk cache) excluded from the timings
    print(f"  numba warm-up (compile or cache load): {time.perf_counter() - t0:.2f} s")
    small_a, small_b = A[:256], B[:256]
    for key, _, f in methods:  # first-call costs of every library, outside the timings
        f(small_a, small_b, args.binary)
        if key == "sgemm_out":
            f(A, B, args.binary)  # fault in the preallocated output

    times = {key: [] for key, _, _ in methods}
    results = {}
    for _ in range(args.repeats):
        for key, _, f in methods:
            t = time.perf_counter()
            out = f(A, B, args.binary)
            times[key].append(time.perf_counter() - t)
            results[key] = None if key.startswith("sgemm") else out  # don't keep a 256 MB product alive
            del out

    med = {k: float(np.median(v)) for k, v in times.items()}
    print()
    for key, label, _ in methods:
        extra = f"  {len(results[key][0])} matches" if not key.startswith("sgemm") else ""
        print(f"  {label:<58s} {med[key]:8.3f} s/pair  (runs: {', '.join(f'{t:.3f}' for t in times[key])}){extra}")
    print()
    print(f"  ours / SGEMM  = {med['ours'] / med['sgemm']:.2f} x   (target <= 1.5; "
          f"{med['ours'] / med['sgemm_out']:.2f} x the SGEMM into a preallocated output)")
    print(f"  OpenCV / ours = {med['opencv'] / med['ours']:.2f} x   (target >= 3)")
    for key in ("torch", "unpack"):
        if key in med:
            print(f"  {key} / ours = {med[key] / med['ours']:.2f} x")
    if "k10" in med:
        print(f"  ours k=10 / ours k=2 = {med['k10'] / med['ours']:.2f} x")
    found, jac = agreement(results["ours"][0], results["opencv"][0])
    print(f"  agreement with OpenCV: {found:.2f}% of OpenCV's {len(results['opencv'][0])} matches returned, "
          f"Jaccard {jac:.2f}% (ours {len(results['ours'][0])})")
    for key in ("torch", "unpack"):
        if key in results:
            found, jac = agreement(results["ours"][0], results[key][0])
            print(f"  agreement with {key}: {found:.2f}% returned, Jaccard {jac:.2f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
