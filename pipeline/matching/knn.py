"""Exact (and FLANN) k-nearest-neighbour tables of a descriptor pair, both directions in one pass.

    from pipeline.matching.knn import knn_tables
    tab = knn_tables(desc1, desc2, binary=False, k=2)       # KnnTables: idx12, dist12, idx21, dist21
    tab.idx12[i, 0]        # nearest neighbour in image 2 of descriptor i of image 1 (-1 if none)
    tab.dist21[j, 1]       # distance of descriptor j of image 2 to its second neighbour in image 1 (inf if none)

Distances are true L2 distances (the square root, as OpenCV's ``NORM_L2``) for float descriptors and bit
counts (Hamming) for binary ones (uint8, packed bits). Rows of every table are sorted by (distance, index);
missing neighbours (fewer than k descriptors on the other side) have index -1 and distance inf.

How the exact search works (float descriptors)
----------------------------------------------
The distance matrix is never materialised. Rows of image 1 are taken in blocks of ``BLOCK_BYTES`` (32 MB =
1024 rows at 8000 descriptors); for each block one BLAS SGEMM ``(-2 A_blk) B^T`` goes into a reused buffer,
then one fused numba pass over the block (``_kernels.top2_block``) adds the squared norms
(``d^2 = |a|^2 + |b|^2 - 2ab``) and, in the same pass, extracts each row's top-2 and updates the running
column top-2 (image 2 -> image 1); nothing is sorted. The expansion only ranks neighbours: the distances kept
are then recomputed exactly from the descriptors (``||a - b||``, float64 accumulation, ~2 ms for 8k x 2 x 2)
and each row re-sorted by them, so a duplicate descriptor has distance exactly 0 and the distance filter sees
the values OpenCV's ``NORM_L2`` would report.

Binary descriptors (Hamming) use a numba popcount kernel (64-bit words, ``llvm.ctpop`` -> VPOPCNTQ/POPCNT)
that writes Hamming blocks the same top-2 kernel consumes (exact integers). Measured on 8000 x 8000 x 256 bits
(``benchmarks/matching.py --binary --dim 32``): 3.3-3.7x faster than the alternative exact path of unpacking the
bits to 0/1 float32 and running the float search (a 256-wide SGEMM; also exact, ``|a| + |b| - 2 a.b`` is an
integer < 2^24), and 0.4-0.5x the time of that SGEMM alone.

k > 2 (FGINN needs ~10) uses ``_kernels.topk_block``: the same blocks and one pass, with a scalar insertion
into the row list and the column lists (rare after the first rows, so well predicted): ~1.5 ns per distance
instead of ~0.4; 1.2-1.6x the k = 2 total at 8000 x 8000 (``--with-k10``).

Threads
-------
The SGEMM uses numpy's BLAS threads (all cores); the numba kernels are serial (``KERNEL_THREADS = 1``), which
measured faster on the 2-core target than the alternatives: a ``parallel=True`` kernel with per-thread column
arrays merged after (``KERNEL_THREADS = 2``; kept as an option, tested identical) lost 10-25% overall,
because OpenBLAS's workers keep spinning after each SGEMM call and numba's OpenMP workers after each kernel,
each stealing the other's cores; running the kernel in a second Python thread overlapped with the next SGEMM
oversubscribed the cores the same way. The serial kernel costs ~0.4-0.5 ns of CPU per distance (0.03 s for
8000 x 8000, against 0.09-0.10 s for the SGEMM on an idle machine). No thread setting is changed here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.errors import ImtuneError

#: bytes of one distance block (rows of image 1 x all of image 2, float32). The kernel's cost per distance
#: measured the same from 128 to 2048 rows (at 8000 columns), while each SGEMM call costs a wake-up and a
#: barrier of the BLAS threads: with other processes loading the cores, 128-row blocks made the whole search
#: 2x slower than 1024-row ones. 32 MB = 1024 rows at 8000 descriptors (the full matrix would be 256 MB).
BLOCK_BYTES = 32 << 20
#: fixed rows per block instead of BLOCK_BYTES (None = derive from BLOCK_BYTES); for tests and experiments.
BLOCK_ROWS: int | None = None
#: numba threads of the k = 2 kernel. 1 (default): serial kernel between the multi-threaded SGEMMs (see
#: "Threads" above for the measurements); > 1: ``top2_block_parallel`` with per-thread column state.
KERNEL_THREADS = 1
#: FLANN parameters (the official IMC benchmark's: 4 randomised KD-trees, 128 checks; LSH for binary).
FLANN_KDTREE = dict(algorithm=1, trees=4)
FLANN_LSH = dict(algorithm=6, table_number=12, key_size=20, multi_probe_level=2)
FLANN_SEARCH = dict(checks=128)


@dataclass
class KnnTables:
    """k-NN tables of a pair, both directions (see the module docstring for the conventions).

    idx12 (N1, k) int32: neighbours in image 2 of each descriptor of image 1, nearest first; -1 = none.
    dist12 (N1, k) float32: their distances (L2, or Hamming bit counts); inf where idx12 is -1.
    idx21 (N2, k) int32, dist21 (N2, k) float32: the same from image 2 to image 1.
    """
    idx12: np.ndarray
    dist12: np.ndarray
    idx21: np.ndarray
    dist21: np.ndarray

    @property
    def k(self) -> int:
        return int(np.asarray(self.idx12).shape[1]) if np.asarray(self.idx12).ndim == 2 else 0

    @property
    def n1(self) -> int:
        return int(np.asarray(self.idx12).shape[0])

    @property
    def n2(self) -> int:
        return int(np.asarray(self.idx21).shape[0])


def _empty_tables(n1: int, n2: int, k: int) -> KnnTables:
    return KnnTables(np.full((n1, k), -1, np.int32), np.full((n1, k), np.inf, np.float32),
                     np.full((n2, k), -1, np.int32), np.full((n2, k), np.inf, np.float32))


def _as_descriptors(d, binary: bool, which: str) -> np.ndarray:
    d = np.asarray(d)
    if d.ndim == 1 and d.size == 0:
        d = d.reshape(0, 0)
    if d.ndim != 2:
        raise ImtuneError(f"{which}: descriptors must be a 2-D array (N, D), got shape {d.shape}")
    if d.shape[0] == 0:  # no keypoints: whatever dtype the empty array was stored with
        return np.zeros(d.shape, np.uint8 if binary else np.float32)
    if binary:
        if d.dtype == np.bool_ or not np.issubdtype(d.dtype, np.integer):
            raise ImtuneError(f"{which}: binary descriptors must be uint8 packed bits, got {d.dtype}")
        if d.dtype != np.uint8:
            if d.size and (d.min() < 0 or d.max() > 255):
                raise ImtuneError(f"{which}: binary descriptors must be uint8 packed bits (values 0..255)")
            d = d.astype(np.uint8)
        return np.ascontiguousarray(d)
    if not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
        raise ImtuneError(f"{which}: float descriptors expected, got {d.dtype}")
    d = np.ascontiguousarray(d, dtype=np.float32)
    if d.size and not np.isfinite(d).all():
        raise ImtuneError(f"{which}: descriptors contain NaN or infinite values")
    return d


def knn_tables(desc1, desc2, binary: bool, k: int = 2, method: str = "exact") -> KnnTables:
    """Both-direction k-NN tables of two descriptor sets, from one pass over one distance matrix.

    desc1 (N1, D), desc2 (N2, D): float descriptors (any real dtype, used as float32; L2), or uint8 packed bits
    when ``binary`` (Hamming). k: neighbours kept per descriptor (2 for the ratio test, ~10 for FGINN).
    method: "exact" (brute force, default) or "flann" (approximate: KD-trees for float, LSH for binary).
    Empty inputs are fine: the tables then have 0 rows, or all-missing (-1 / inf) entries.
    """
    if int(k) != k or k < 1:
        raise ImtuneError(f"k must be a positive integer, got {k}")
    k = int(k)
    if method not in ("exact", "flann"):
        raise ImtuneError(f"unknown matcher {method!r} (choose exact or flann)")
    A = _as_descriptors(desc1, binary, "image 1")
    B = _as_descriptors(desc2, binary, "image 2")
    n1, n2 = A.shape[0], B.shape[0]
    if n1 == 0 or n2 == 0:
        return _empty_tables(n1, n2, k)
    if A.shape[1] != B.shape[1]:
        raise ImtuneError(f"descriptor sizes differ: {A.shape[1]} (image 1) vs {B.shape[1]} (image 2)")
    if method == "flann":
        return _flann_tables(A, B, binary, k)
    if binary:
        return _exact_binary(A, B, k)
    return _exact_float(A, B, k)


# ------------------------------------------------------------------------------------------ exact

def _search(blocks, na, nb, n1, n2, k):
    """Run the fused kernel over an iterator of (row0, H block) -> key/index tables, both directions."""
    from pipeline.matching import _kernels as K
    if k == 2:
        rk1, rk2, ri1, ri2 = (np.empty(n1, np.int32) for _ in range(4))
        c1k = np.full(n2, K.KEY_NONE, np.int32)
        c2k = np.full(n2, K.KEY_NONE, np.int32)
        c1i = np.full(n2, -1, np.int32)
        c2i = np.full(n2, -1, np.int32)
        T = max(1, int(KERNEL_THREADS))
        if T == 1:
            for row0, H in blocks:
                K.top2_block(H, na, nb, row0, rk1, rk2, ri1, ri2, c1k, c2k, c1i, c2i)
        else:
            C1K = np.full((T, n2), K.KEY_NONE, np.int32)
            C2K = np.full((T, n2), K.KEY_NONE, np.int32)
            C1I = np.full((T, n2), -1, np.int32)
            C2I = np.full((T, n2), -1, np.int32)
            for row0, H in blocks:
                K.top2_block_parallel(H, na, nb, row0, rk1, rk2, ri1, ri2, C1K, C2K, C1I, C2I)
            K.merge_columns(C1K, C2K, C1I, C2I, c1k, c2k, c1i, c2i)
        return (np.stack([rk1, rk2], 1), np.stack([ri1, ri2], 1),
                np.stack([c1k, c2k], 1), np.stack([c1i, c2i], 1))
    rkey = np.empty((n1, k), np.int32)
    ridx = np.empty((n1, k), np.int32)
    ckey = np.full((n2, k), K.KEY_NONE, np.int32)
    cidx = np.full((n2, k), -1, np.int32)
    cworst = np.full(n2, K.KEY_NONE, np.int32)
    rowbuf = np.empty(n2, np.int32)
    for row0, H in blocks:
        K.topk_block(H, na, nb, row0, k, rkey, ridx, ckey, cidx, cworst, rowbuf)
    return rkey, ridx, ckey, cidx


def _block_rows(n1: int, n2: int) -> int:
    if BLOCK_ROWS is not None:
        return max(1, min(int(BLOCK_ROWS), n1))
    rows = max(64, BLOCK_BYTES // (4 * max(n2, 1))) // 4 * 4
    return max(1, min(rows, n1))


def _clip_missing(idx, n_other, k):
    """Neighbours beyond the n_other that exist are missing."""
    if k > n_other:
        idx[:, n_other:] = -1
    return idx


def _exact_float(A, B, k):
    from pipeline.matching import _kernels as K
    n1, n2 = A.shape[0], B.shape[0]
    na = np.einsum("ij,ij->i", A, A)
    nb = np.einsum("ij,ij->i", B, B)
    Am2 = A * np.float32(-2.0)  # exact (power of two): the GEMM yields -2ab directly
    BT = B.T
    bs = _block_rows(n1, n2)
    buf = np.empty((bs, n2), np.float32)

    def blocks():
        for s in range(0, n1, bs):
            e = min(s + bs, n1)
            yield s, np.matmul(Am2[s:e], BT, out=buf[:e - s])

    _, ridx, _, cidx = _search(blocks(), na, nb, n1, n2, k)
    ridx = _clip_missing(ridx, n2, k)
    cidx = _clip_missing(cidx, n1, k)
    d12 = np.empty((n1, k), np.float32)
    d21 = np.empty((n2, k), np.float32)
    K.exact_l2(A, B, ridx, d12)
    K.exact_l2(B, A, cidx, d21)
    K.sort_rows(d12, ridx)
    K.sort_rows(d21, cidx)
    return KnnTables(ridx, d12, cidx, d21)


def _exact_binary(A, B, k):
    from pipeline.matching import _kernels as K
    n1, n2 = A.shape[0], B.shape[0]
    nbytes = A.shape[1]
    W = (nbytes + 7) // 8
    Aw = np.zeros((n1, W * 8), np.uint8)
    Aw[:, :nbytes] = A
    Bw = np.zeros((n2, W * 8), np.uint8)
    Bw[:, :nbytes] = B
    Aw = Aw.view(np.uint64)
    BT = np.ascontiguousarray(Bw.view(np.uint64).T)
    zeros1 = np.zeros(n1, np.float32)
    zeros2 = np.zeros(n2, np.float32)
    bs = _block_rows(n1, n2)
    buf = np.empty((bs, n2), np.float32)

    def blocks():
        for s in range(0, n1, bs):
            e = min(s + bs, n1)
            K.hamming_block(Aw[s:e], BT, buf[:e - s])
            yield s, buf[:e - s]

    rkey, ridx, ckey, cidx = _search(blocks(), zeros1, zeros2, n1, n2, k)
    ridx = _clip_missing(ridx, n2, k)
    cidx = _clip_missing(cidx, n1, k)
    d12 = K.key_to_sq(rkey)
    d21 = K.key_to_sq(ckey)
    d12[ridx < 0] = np.inf
    d21[cidx < 0] = np.inf
    return KnnTables(ridx, d12, cidx, d21)


# ------------------------------------------------------------------------------------------ FLANN

def _flann_tables(A, B, binary, k):
    """cv2.FlannBasedMatcher both ways (approximate); distances recomputed exactly for the kept neighbours."""
    import cv2

    from pipeline.matching import _kernels as K
    params = FLANN_LSH if binary else FLANN_KDTREE

    def one_way(Q, T):
        matcher = cv2.FlannBasedMatcher(dict(params), dict(FLANN_SEARCH))
        kk = min(k, T.shape[0])
        res = matcher.knnMatch(Q, T, k=kk)
        idx = np.full((Q.shape[0], k), -1, np.int32)
        for m in res:
            for q, dm in enumerate(m[:k]):
                idx[dm.queryIdx, q] = dm.trainIdx
        return idx

    i12 = one_way(A, B)
    i21 = one_way(B, A)
    if binary:
        d12 = _hamming_pairs(A, B, i12)
        d21 = _hamming_pairs(B, A, i21)
    else:
        d12 = np.empty(i12.shape, np.float32)
        d21 = np.empty(i21.shape, np.float32)
        K.exact_l2(A, B, i12, d12)
        K.exact_l2(B, A, i21, d21)
    K.sort_rows(d12, i12)
    K.sort_rows(d21, i21)
    return KnnTables(i12, d12, i21, d21)


def _hamming_pairs(X, Y, idx):
    """Hamming distance of X[i] to Y[idx[i, q]] (inf where idx < 0)."""
    safe = np.where(idx < 0, 0, idx)
    x = np.unpackbits(X[:, None, :] ^ Y[safe], axis=-1).sum(-1).astype(np.float32)
    x[idx < 0] = np.inf
    return x


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) every kernel on tiny inputs, so timing excludes the JIT."""
    rng = np.random.default_rng(0)
    a = rng.random((9, 8), dtype=np.float32)
    b = rng.random((7, 8), dtype=np.float32)
    for k in (2, 3):
        knn_tables(a, b, binary=False, k=k)
        knn_tables(rng.integers(0, 256, (9, 4), dtype=np.uint8), rng.integers(0, 256, (7, 4), dtype=np.uint8),
                   binary=True, k=k)
