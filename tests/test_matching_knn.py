"""k-NN tables: exact against a brute-force float64 / popcount reference, both directions, edge cases, FLANN."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import ImtuneError
from pipeline.matching import knn as knn_mod
from pipeline.matching.knn import KnnTables, knn_tables


def _ref_l2(A, B):
    A = A.astype(np.float64)
    B = B.astype(np.float64)
    return np.sqrt(np.maximum(((A[:, None, :] - B[None, :, :]) ** 2).sum(-1), 0))


def _ref_hamming(A, B):
    return np.unpackbits(A[:, None, :] ^ B[None, :, :], axis=-1).sum(-1).astype(np.float64)


def _ref_knn(D, k):
    """(idx, dist) of the k nearest per row, ties by index; padded with -1 / inf."""
    n1, n2 = D.shape
    order = np.argsort(D, axis=1, kind="stable")[:, :k]
    dist = np.take_along_axis(D, order, 1)
    idx = np.full((n1, k), -1, np.int64)
    d = np.full((n1, k), np.inf)
    idx[:, :order.shape[1]] = order
    d[:, :order.shape[1]] = dist
    return idx, d


def _sift_like(rng, n, dim):
    x = rng.gamma(0.6, size=(n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _check_float_direction(idx, dist, D, k, tol=2e-6):
    """Exact up to float rounding: reported distances are the true ones of the reported neighbours, equal the
    reference's k smallest, and indices agree wherever the reference has no near-tie at that rank."""
    ref_idx, ref_d = _ref_knn(D, k)
    assert idx.shape == ref_idx.shape and dist.shape == ref_d.shape
    assert idx.dtype == np.int32 and dist.dtype == np.float32
    missing = ref_idx < 0
    assert (idx[missing] == -1).all() and np.isinf(dist[missing]).all()
    ok = ~missing
    np.testing.assert_allclose(dist[ok], ref_d[ok], rtol=0, atol=tol)
    true_d = np.take_along_axis(D, np.maximum(idx, 0), 1)
    np.testing.assert_allclose(dist[ok], true_d[ok], rtol=0, atol=tol)
    srt = np.sort(D, axis=1)
    for q in range(min(k, D.shape[1])):
        gap = np.full(D.shape[0], np.inf)
        if q > 0:
            gap = np.minimum(gap, srt[:, q] - srt[:, q - 1])
        if q + 1 < D.shape[1]:
            gap = np.minimum(gap, srt[:, q + 1] - srt[:, q])
        clear = gap > 1e-5
        assert (idx[clear, q] == ref_idx[clear, q]).all()
        assert clear.mean() > 0.95


@pytest.mark.parametrize("k", [2, 10])
@pytest.mark.parametrize("n1,n2,dim", [(300, 257, 128), (257, 300, 64), (13, 9, 3)])
def test_float_exact_both_directions(k, n1, n2, dim):
    rng = np.random.default_rng(n1 * 7 + n2 + k)
    A, B = _sift_like(rng, n1, dim), _sift_like(rng, n2, dim)
    tab = knn_tables(A, B, binary=False, k=k)
    assert isinstance(tab, KnnTables) and tab.k == k and tab.n1 == n1 and tab.n2 == n2
    D = _ref_l2(A, B)
    _check_float_direction(tab.idx12, tab.dist12, D, k)
    _check_float_direction(tab.idx21, tab.dist21, D.T, k)


@pytest.mark.parametrize("k", [2, 3, 10])
def test_float_many_small_blocks(monkeypatch, k):
    """Block boundaries (and 4-row groups with remainders) do not change the result."""
    rng = np.random.default_rng(5)
    A, B = _sift_like(rng, 203, 32), _sift_like(rng, 150, 32)
    ref = knn_tables(A, B, binary=False, k=k)
    monkeypatch.setattr(knn_mod, "BLOCK_ROWS", 7)
    tab = knn_tables(A, B, binary=False, k=k)
    for name in ("idx12", "dist12", "idx21", "dist21"):
        np.testing.assert_array_equal(getattr(tab, name), getattr(ref, name))
    D = _ref_l2(A, B)
    _check_float_direction(tab.idx12, tab.dist12, D, k)
    _check_float_direction(tab.idx21, tab.dist21, D.T, k)


@pytest.mark.parametrize("k", [2, 10])
@pytest.mark.parametrize("n1,n2,nbytes", [(300, 257, 32), (130, 141, 20), (9, 13, 1)])
def test_hamming_exact_both_directions(k, n1, n2, nbytes):
    """Hamming is integer-exact, ties included (broken by the smaller index)."""
    rng = np.random.default_rng(n1 + n2 + nbytes + k)
    A = rng.integers(0, 256, (n1, nbytes), dtype=np.uint8)
    B = rng.integers(0, 256, (n2, nbytes), dtype=np.uint8)
    tab = knn_tables(A, B, binary=True, k=k)
    D = _ref_hamming(A, B)
    for idx, dist, DD in ((tab.idx12, tab.dist12, D), (tab.idx21, tab.dist21, D.T)):
        ref_idx, ref_d = _ref_knn(DD, k)
        assert idx.dtype == np.int32 and dist.dtype == np.float32
        np.testing.assert_array_equal(idx, ref_idx)
        np.testing.assert_array_equal(dist, ref_d.astype(np.float32))


def test_duplicates_zero_distance_and_ties():
    """Self-matching gives exactly 0 (distances are recomputed exactly); duplicates tie by smaller index."""
    rng = np.random.default_rng(1)
    A = _sift_like(rng, 50, 128)
    B = np.concatenate([A, A[:5]])  # descriptors 50..54 duplicate 0..4
    tab = knn_tables(A, B, binary=False, k=2)
    np.testing.assert_array_equal(tab.idx12[:, 0], np.arange(50))
    assert (tab.dist12[:, 0] == 0).all()
    np.testing.assert_array_equal(tab.idx12[:5, 1], np.arange(50, 55))
    assert (tab.dist12[:5, 1] == 0).all()
    np.testing.assert_array_equal(tab.idx21[50:, 0], np.arange(5))
    np.testing.assert_array_equal(tab.idx21[:50, 0], np.arange(50))


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("k", [1, 2, 10])
def test_empty_and_tiny_inputs(binary, k):
    rng = np.random.default_rng(0)

    def make(n):
        if binary:
            return rng.integers(0, 256, (n, 32), dtype=np.uint8)
        return _sift_like(rng, n, 128) if n else np.zeros((0, 128), np.float32)

    for n1, n2 in [(0, 0), (0, 5), (5, 0), (1, 1), (1, 5), (5, 1), (3, 2)]:
        A, B = make(n1), make(n2)
        tab = knn_tables(A, B, binary=binary, k=k)
        assert tab.idx12.shape == (n1, k) and tab.dist12.shape == (n1, k)
        assert tab.idx21.shape == (n2, k) and tab.dist21.shape == (n2, k)
        # neighbours that do not exist: -1 and inf
        assert (tab.idx12[:, min(k, n2):] == -1).all() and np.isinf(tab.dist12[:, min(k, n2):]).all()
        assert (tab.idx21[:, min(k, n1):] == -1).all() and np.isinf(tab.dist21[:, min(k, n1):]).all()
        if n1 and n2:
            D = _ref_hamming(A, B) if binary else _ref_l2(A, B)
            ref_idx, _ = _ref_knn(D, k)
            np.testing.assert_array_equal(tab.idx12, ref_idx)
            ref_idx, _ = _ref_knn(D.T, k)
            np.testing.assert_array_equal(tab.idx21, ref_idx)
    # a flat empty array is accepted too
    tab = knn_tables(np.zeros(0, np.float32), make(4), binary=binary, k=k)
    assert tab.idx12.shape == (0, k) and (tab.idx21 == -1).all()


def test_input_conversion_and_errors():
    rng = np.random.default_rng(2)
    A = _sift_like(rng, 40, 16).astype(np.float64)
    B = np.asfortranarray(_sift_like(rng, 30, 16))
    tab = knn_tables(A, B, binary=False)
    ref = knn_tables(A.astype(np.float32), np.ascontiguousarray(B), binary=False)
    np.testing.assert_array_equal(tab.idx12, ref.idx12)
    with pytest.raises(ImtuneError, match="sizes differ"):
        knn_tables(A, _sift_like(rng, 30, 8), binary=False)
    bad = A.copy()
    bad[3, 2] = np.nan
    with pytest.raises(ImtuneError, match="NaN"):
        knn_tables(bad, B, binary=False)
    with pytest.raises(ImtuneError, match="uint8"):
        knn_tables(A, B, binary=True)
    with pytest.raises(ImtuneError, match="positive"):
        knn_tables(A, B, binary=False, k=0)
    with pytest.raises(ImtuneError, match="matcher"):
        knn_tables(A, B, binary=False, method="faiss")
    with pytest.raises(ImtuneError, match="2-D"):
        knn_tables(np.zeros((2, 3, 4), np.float32), B, binary=False)


def _noisy_pair(rng, n, dim):
    A = _sift_like(rng, n, dim)
    perm = rng.permutation(n)
    B = A[perm] + rng.normal(0, 0.01, (n, dim)).astype(np.float32)
    return A, np.maximum(B, 0), perm


@pytest.mark.parametrize("k", [2, 10])
def test_flann_agrees_with_exact_float(k):
    from pipeline.config import MatchConfig
    from pipeline.matching.filter import filter_matches
    rng = np.random.default_rng(3)
    A, B, _ = _noisy_pair(rng, 1500, 128)
    B[:500] = _sift_like(rng, 500, 128)  # a third of image 2 has no true partner
    ex = knn_tables(A, B, binary=False, k=k)
    fl = knn_tables(A, B, binary=False, k=k, method="flann")
    assert fl.idx12.shape == ex.idx12.shape and fl.idx21.shape == ex.idx21.shape
    # approximate: on descriptors without a partner the nearest neighbour may differ, but the matches that
    # survive the ratio test (distinctive ones) are nearly all found
    assert (fl.idx12[:, 0] == ex.idx12[:, 0]).mean() > 0.7
    assert (fl.idx21[:, 0] == ex.idx21[:, 0]).mean() > 0.7
    conf = MatchConfig(ratio=0.8, strategy="both")
    m_ex = {tuple(p) for p in filter_matches(ex, conf)[0].tolist()}
    m_fl = {tuple(p) for p in filter_matches(fl, conf)[0].tolist()}
    assert len(m_ex) > 500
    assert len(m_ex & m_fl) / len(m_ex | m_fl) > 0.95
    # FLANN's distances are recomputed exactly: equal to the exact ones wherever the neighbour agrees
    same = fl.idx12[:, 0] == ex.idx12[:, 0]
    np.testing.assert_allclose(fl.dist12[same, 0], ex.dist12[same, 0], atol=1e-6)
    assert (np.diff(fl.dist12, axis=1) >= 0).all()


def test_flann_agrees_with_exact_binary():
    rng = np.random.default_rng(4)
    n = 1500
    A = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    perm = rng.permutation(n)
    flips = np.packbits(rng.random((n, 256)) < 0.05, axis=1)
    B = A[perm] ^ flips
    ex = knn_tables(A, B, binary=True, k=2)
    fl = knn_tables(A, B, binary=True, k=2, method="flann")
    assert (fl.idx12[:, 0] == ex.idx12[:, 0]).mean() > 0.9
    assert (fl.idx21[:, 0] == ex.idx21[:, 0]).mean() > 0.9
    ok = fl.idx12[:, 0] >= 0
    np.testing.assert_array_equal(fl.dist12[ok, 0], _ref_hamming(A, B)[np.flatnonzero(ok), fl.idx12[ok, 0]])


@pytest.mark.parametrize("binary", [False, True])
def test_parallel_kernel_identical(monkeypatch, binary):
    """The opt-in multi-threaded k=2 kernel (per-thread column state, merged) gives the same tables."""
    rng = np.random.default_rng(11)
    if binary:
        A = rng.integers(0, 256, (301, 8), dtype=np.uint8)  # many Hamming ties: exercises the merge order
        B = rng.integers(0, 256, (157, 8), dtype=np.uint8)
    else:
        A, B = _sift_like(rng, 301, 32), _sift_like(rng, 157, 32)
    ref = knn_tables(A, B, binary=binary, k=2)
    monkeypatch.setattr(knn_mod, "BLOCK_ROWS", 50)
    for threads in (2, 3):
        monkeypatch.setattr(knn_mod, "KERNEL_THREADS", threads)
        tab = knn_tables(A, B, binary=binary, k=2)
        for name in ("idx12", "dist12", "idx21", "dist21"):
            np.testing.assert_array_equal(getattr(tab, name), getattr(ref, name))
