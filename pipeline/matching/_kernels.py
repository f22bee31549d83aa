"""numba kernels behind :func:`pipeline.matching.knn.knn_tables` (private; see knn.py for the design).

Conventions shared by every kernel here:

- A block ``H`` (m, N2) float32 holds ``-2 a_i . b_j`` (the GEMM is run on ``-2 A``, an exact scaling), so the
  squared distance of row ``row0 + ii`` and column ``j`` is ``d = (na[row0 + ii] + nb[j]) + H[ii, j]``, always
  evaluated with that exact expression and order (no FMA contraction, no reassociation) so every pass over the
  same block sees bit-identical values. For Hamming blocks ``na = nb = 0`` and ``H`` holds the bit counts.
- Distances are ranked through an order-preserving int32 key of their float32 bits (``okey``): integer
  ``min`` reductions vectorise where float ones do not (numba emits no fast-math flags on ``select``), and the
  key also ranks the slightly negative values the expansion ``|a|^2 + |b|^2 - 2ab`` can produce.
  ``KEY_NONE`` (int32 max, above every finite or infinite distance's key) marks "no neighbour".
- Ties are broken by the smaller index: rows are scanned in increasing j, columns in increasing i, and an
  entry only displaces another on a strict ``<``.
- Every kernel is serial and ``nogil`` except ``top2_block_parallel`` (opt-in); see knn.py "Threads" for why.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic

# no 'contract' (FMA) and no 'reassoc': the distance expression must evaluate identically in every loop.
# 'nnan' lets the integer-key loops vectorise; inputs are checked finite before any kernel runs.
_FM = {"nnan", "nsz"}
_OPTS: dict[str, Any] = dict(fastmath=_FM, boundscheck=False, nogil=True, cache=True)  # njit keyword options

I32 = np.int32
KEY_NONE = I32(2**31 - 1)
_IMAX = I32(2**31 - 1)
_MASK = I32(0x7FFFFFFF)


@intrinsic
def _f32_bits(typingctx, x):
    """Reinterpret a float32's bits as int32."""
    if isinstance(x, types.Float) and x.bitwidth == 32:
        def codegen(context, builder, sig, args):
            return builder.bitcast(args[0], ir.IntType(32))
        return types.int32(types.float32), codegen
    return None


@intrinsic
def _popcount64(typingctx, x):
    """Population count of a uint64 (llvm.ctpop: POPCNT / VPOPCNTQ)."""
    if isinstance(x, types.Integer) and x.bitwidth == 64:
        def codegen(context, builder, sig, args):
            return builder.ctpop(args[0])
        return types.uint64(x), codegen
    return None


@njit(inline="always", **_OPTS)
def okey(d):
    """Order-preserving int32 key of a float32 (sign-magnitude -> two's complement)."""
    k = _f32_bits(d)
    return I32(k ^ I32(I32(k >> I32(31)) & _MASK))


def key_to_sq(keys: np.ndarray) -> np.ndarray:
    """Inverse of ``okey`` over an array (``KEY_NONE`` -> inf)."""
    k = np.asarray(keys, np.int32)
    out = (k ^ ((k >> 31) & 0x7FFFFFFF)).view(np.float32).copy()
    out[k == KEY_NONE] = np.inf
    return out


# --------------------------------------------------------------------------------------------- k = 2

@njit(inline="always", **_OPTS)
def _col_upd(k, r, p1, p2, q1, q2):
    m1 = k < p1
    m2 = k < p2
    t = r if m2 else q2
    nq2 = q1 if m1 else t
    nq1 = r if m1 else q1
    np2 = min(p2, max(p1, k))
    np1 = min(p1, k)
    return np1, np2, nq1, nq2


@njit(**_OPTS)
def _row_second(h, a, nb, n, v1):
    """Given a row's minimum key v1: (index of the first minimum, second key, its index)."""
    i1 = _IMAX
    cnt = I32(0)
    v2 = _IMAX
    for j in range(n):
        x = okey((a + nb[j]) + h[j])
        e = x == v1
        i1 = min(i1, I32(j) if e else _IMAX)
        cnt += I32(e)
        v2 = min(v2, _IMAX if e else x)
    if n == 0:
        return I32(-1), KEY_NONE, I32(-1)
    if cnt >= 2:  # exact tie for the first place: the second neighbour is the next index with the same key
        for j in range(i1 + 1, n):
            if okey((a + nb[j]) + h[j]) == v1:
                return i1, v1, I32(j)
    if v2 == _IMAX:
        return i1, KEY_NONE, I32(-1)
    i2 = _IMAX
    for j in range(n):
        i2 = min(i2, I32(j) if okey((a + nb[j]) + h[j]) == v2 else _IMAX)
    return i1, v2, i2


@njit(**_OPTS)
def top2_block(H, na, nb, row0, rk1, rk2, ri1, ri2, c1k, c2k, c1i, c2i):
    """Fused row and column top-2 of one distance block.

    Rows ``row0 .. row0 + m`` get their final (key, index) top-2 in ``rk1/ri1, rk2/ri2`` (N1,). The column
    running top-2 ``c1k/c1i, c2k/c2i`` (N2,) is updated in place. Four rows share one pass over the column
    state (its loads and stores amortised); each row's minimum is an integer min-reduction in that pass,
    and its argmin / second place come from one or two more vectorised passes over the (cache-resident) row.
    """
    m, n = H.shape
    ii = 0
    while ii + 4 <= m:
        g0 = H[ii]
        g1 = H[ii + 1]
        g2 = H[ii + 2]
        g3 = H[ii + 3]
        i0 = row0 + ii
        a0 = na[i0]
        a1 = na[i0 + 1]
        a2 = na[i0 + 2]
        a3 = na[i0 + 3]
        r0 = I32(i0)
        r1 = I32(i0 + 1)
        r2 = I32(i0 + 2)
        r3 = I32(i0 + 3)
        v0 = _IMAX
        v1 = _IMAX
        v2 = _IMAX
        v3 = _IMAX
        for j in range(n):
            nj = nb[j]
            k0 = okey((a0 + nj) + g0[j])
            k1 = okey((a1 + nj) + g1[j])
            k2 = okey((a2 + nj) + g2[j])
            k3 = okey((a3 + nj) + g3[j])
            v0 = min(v0, k0)
            v1 = min(v1, k1)
            v2 = min(v2, k2)
            v3 = min(v3, k3)
            p1 = c1k[j]
            p2 = c2k[j]
            q1 = c1i[j]
            q2 = c2i[j]
            p1, p2, q1, q2 = _col_upd(k0, r0, p1, p2, q1, q2)
            p1, p2, q1, q2 = _col_upd(k1, r1, p1, p2, q1, q2)
            p1, p2, q1, q2 = _col_upd(k2, r2, p1, p2, q1, q2)
            p1, p2, q1, q2 = _col_upd(k3, r3, p1, p2, q1, q2)
            c1k[j] = p1
            c2k[j] = p2
            c1i[j] = q1
            c2i[j] = q2
        a, b, c = _row_second(g0, a0, nb, n, v0)
        rk1[i0] = v0 if n > 0 else KEY_NONE
        ri1[i0] = a
        rk2[i0] = b
        ri2[i0] = c
        a, b, c = _row_second(g1, a1, nb, n, v1)
        rk1[i0 + 1] = v1 if n > 0 else KEY_NONE
        ri1[i0 + 1] = a
        rk2[i0 + 1] = b
        ri2[i0 + 1] = c
        a, b, c = _row_second(g2, a2, nb, n, v2)
        rk1[i0 + 2] = v2 if n > 0 else KEY_NONE
        ri1[i0 + 2] = a
        rk2[i0 + 2] = b
        ri2[i0 + 2] = c
        a, b, c = _row_second(g3, a3, nb, n, v3)
        rk1[i0 + 3] = v3 if n > 0 else KEY_NONE
        ri1[i0 + 3] = a
        rk2[i0 + 3] = b
        ri2[i0 + 3] = c
        ii += 4
    while ii < m:
        g0 = H[ii]
        i0 = row0 + ii
        a0 = na[i0]
        r0 = I32(i0)
        v0 = _IMAX
        for j in range(n):
            k0 = okey((a0 + nb[j]) + g0[j])
            v0 = min(v0, k0)
            p1, p2, q1, q2 = _col_upd(k0, r0, c1k[j], c2k[j], c1i[j], c2i[j])
            c1k[j] = p1
            c2k[j] = p2
            c1i[j] = q1
            c2i[j] = q2
        a, b, c = _row_second(g0, a0, nb, n, v0)
        rk1[i0] = v0 if n > 0 else KEY_NONE
        ri1[i0] = a
        rk2[i0] = b
        ri2[i0] = c
        ii += 1


@njit(parallel=True, fastmath=_FM, boundscheck=False, nogil=True, cache=True)
def top2_block_parallel(H, na, nb, row0, rk1, rk2, ri1, ri2, C1K, C2K, C1I, C2I):
    """``top2_block`` on T row slices of the block at once (numba threads), thread t keeping its own column
    state ``C*[t]`` (T, N2); merge them with ``merge_columns`` at the end. Not the default: see knn.py."""
    m = H.shape[0]
    T = C1K.shape[0]
    for t in prange(T):
        lo = (t * m) // T
        hi = ((t + 1) * m) // T
        if hi > lo:
            top2_block(H[lo:hi], na, nb, row0 + lo, rk1, rk2, ri1, ri2, C1K[t], C2K[t], C1I[t], C2I[t])


@njit(**_OPTS)
def merge_columns(C1K, C2K, C1I, C2I, c1k, c2k, c1i, c2i):
    """Merge per-thread column top-2 lists into one, ranking by (key, index)."""
    T, n = C1K.shape
    for j in range(n):
        b1 = KEY_NONE
        x1 = I32(-1)
        b2 = KEY_NONE
        x2 = I32(-1)
        for t in range(T):
            for q in range(2):
                kk = C1K[t, j] if q == 0 else C2K[t, j]
                xx = C1I[t, j] if q == 0 else C2I[t, j]
                if xx < 0:
                    continue
                if x1 < 0 or kk < b1 or (kk == b1 and xx < x1):
                    b2 = b1
                    x2 = x1
                    b1 = kk
                    x1 = xx
                elif x2 < 0 or kk < b2 or (kk == b2 and xx < x2):
                    b2 = kk
                    x2 = xx
        c1k[j] = b1
        c2k[j] = b2
        c1i[j] = x1
        c2i[j] = x2


# --------------------------------------------------------------------------------------------- any k

@njit(inline="always", **_OPTS)
def _insert(keys, idx, k, key, i):
    """Insert (key, i) into the ascending list keys[:k] / idx[:k] (caller checked key < keys[k-1])."""
    p = k - 1
    while p > 0 and keys[p - 1] > key:
        keys[p] = keys[p - 1]
        idx[p] = idx[p - 1]
        p -= 1
    keys[p] = key
    idx[p] = i


@njit(**_OPTS)
def topk_block(H, na, nb, row0, k, rkey, ridx, ckey, cidx, cworst, rowbuf):
    """Row and column top-k of one block in one pass (any k; the simpler path used for k > 2).

    rkey/ridx (N1, k): rows ``row0 .. row0 + m`` are written. ckey/cidx (N2, k) running column lists,
    cworst (N2,) their current k-th key, rowbuf (N2,) int32 scratch. Each row's keys are computed in one
    vectorised pass, then a scalar pass inserts into the row and column lists; insertions are rare after the
    first rows, so the branches predict well (a vectorised per-16-column pre-test measured slower at k = 10).
    """
    m, n = H.shape
    for ii in range(m):
        gi = row0 + ii
        a = na[gi]
        g = H[ii]
        rk = rkey[gi]
        rx = ridx[gi]
        for q in range(k):
            rk[q] = KEY_NONE
            rx[q] = -1
        for j in range(n):
            rowbuf[j] = okey((a + nb[j]) + g[j])
        rw = KEY_NONE
        for j in range(n):
            x = rowbuf[j]
            if x < rw:
                _insert(rk, rx, k, x, I32(j))
                rw = rk[k - 1]
            if x < cworst[j]:
                ck = ckey[j]
                _insert(ck, cidx[j], k, x, I32(gi))
                cworst[j] = ck[k - 1]


# --------------------------------------------------------------------------------------------- helpers

@njit(**_OPTS)
def hamming_block(A, BT, out):
    """out[i, j] = Hamming distance of A[i] (W uint64 words) and column j of BT (W, N2), as float32."""
    m, W = A.shape
    n = BT.shape[1]
    acc = np.empty(n, np.uint64)
    for i in range(m):
        for j in range(n):
            acc[j] = 0
        for w in range(W):
            aw = A[i, w]
            bw = BT[w]
            for j in range(n):
                acc[j] += _popcount64(aw ^ bw[j])
        o = out[i]
        for j in range(n):
            o[j] = np.float32(acc[j])


@njit(fastmath={"nnan", "nsz", "reassoc", "contract"}, boundscheck=False, nogil=True, cache=True)
def exact_l2(X, Y, idx, out):
    """out[i, q] = ||X[i] - Y[idx[i, q]]|| (float64 accumulation), inf where idx < 0."""
    N, k = idx.shape
    D = X.shape[1]
    for i in range(N):
        for q in range(k):
            j = idx[i, q]
            if j < 0:
                out[i, q] = np.inf
                continue
            s = 0.0
            for t in range(D):
                e = np.float64(X[i, t]) - np.float64(Y[j, t])
                s += e * e
            out[i, q] = np.float32(np.sqrt(s))


@njit(boundscheck=False, nogil=True, cache=True)
def sort_rows(dist, idx):
    """Re-sort each row's k entries by (distance, index), missing (-1) last; in place (insertion sort)."""
    N, k = idx.shape
    for i in range(N):
        d = dist[i]
        x = idx[i]
        for p in range(1, k):
            dv = d[p]
            xv = x[p]
            q = p
            while q > 0:
                dq = d[q - 1]
                xq = x[q - 1]
                if xv >= 0 and (xq < 0 or dq > dv or (dq == dv and xq > xv)):
                    d[q] = dq
                    x[q] = xq
                    q -= 1
                else:
                    break
            d[q] = dv
            x[q] = xv
