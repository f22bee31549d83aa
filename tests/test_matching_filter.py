"""filter_matches: ratio test, strategies, mutual check, distance threshold, FGINN — against hand-built tables
and a loop-by-loop transcription of the official IMC benchmark's rules."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import MatchConfig
from pipeline.errors import ImtuneError
from pipeline.matching import KnnTables, filter_matches, knn_tables, match_descriptors


def _tables(idx12, dist12, idx21, dist21) -> KnnTables:
    return KnnTables(np.asarray(idx12, np.int32), np.asarray(dist12, np.float32),
                     np.asarray(idx21, np.int32), np.asarray(dist21, np.float32))


def _pairs(m) -> set:
    return {(int(i), int(j)) for i, j in m}


@pytest.fixture(scope="module")
def random_pair():
    rng = np.random.default_rng(0)
    n = 400
    A = rng.gamma(0.6, size=(n, 64)).astype(np.float32)
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    perm = rng.permutation(n)
    B = np.maximum(A[perm] + rng.normal(0, 0.04, (n, 64)).astype(np.float32), 0)
    B[: n // 3] = rng.gamma(0.6, size=(n // 3, 64))
    B /= np.linalg.norm(B, axis=1, keepdims=True)
    k1 = rng.random((n, 2)) * 200
    k2 = rng.random((n, 2)) * 200
    return A, B, k1, k2


# ------------------------------------------------------------------ reference (official nn.py, loop by loop)

def _ref_one_way(idx, dist, conf, kpts_target):
    out = []
    for q in range(idx.shape[0]):
        row = [(int(j), float(d)) for j, d in zip(idx[q], dist[q]) if j >= 0]
        if not row:
            continue
        j1, d1 = row[0]
        if conf.fginn:
            ok = False
            if len(row) == 1:
                ok = True  # no second neighbour at all
            for j2, d2 in row[1:]:
                if d1 <= conf.ratio * d2:
                    ok = True
                    break
                if np.hypot(*(kpts_target[j2] - kpts_target[j1])) > conf.fginn_px:
                    break
        elif conf.ratio >= 1.0 or len(row) == 1:
            ok = True
        else:
            ok = d1 <= conf.ratio * row[1][1]
        if ok and (conf.distance_threshold is None or d1 <= conf.distance_threshold):
            out.append((q, j1))
    return out


def _reference(tab, conf, k1=None, k2=None):
    m12 = _ref_one_way(tab.idx12, tab.dist12, conf, k2)
    if conf.strategy == "uni":
        return set(m12)
    m21 = {(i, j) for j, i in _ref_one_way(tab.idx21, tab.dist21, conf, k1)}
    if conf.strategy == "both":
        return set(m12) & m21
    return set(m12) | m21


@pytest.mark.parametrize("strategy", ["both", "either", "uni"])
@pytest.mark.parametrize("ratio", [1.0, 0.95, 0.8, 0.6])
@pytest.mark.parametrize("thr", [None, 0.35])
def test_matches_reference_rules(random_pair, strategy, ratio, thr):
    A, B, _, _ = random_pair
    tab = knn_tables(A, B, binary=False, k=2)
    conf = MatchConfig(ratio=ratio, strategy=strategy, distance_threshold=thr)
    m, d = filter_matches(tab, conf)
    assert m.dtype == np.int32 and m.shape[1] == 2 and d.dtype == np.float32 and len(d) == len(m)
    assert _pairs(m) == _reference(tab, conf)
    assert len(_pairs(m)) == len(m)  # no duplicates
    # deterministic order: by i, then j
    assert (np.lexsort((m[:, 1], m[:, 0])) == np.arange(len(m))).all()
    # the distance reported is the pair's descriptor distance
    np.testing.assert_allclose(d, np.linalg.norm(A[m[:, 0]] - B[m[:, 1]], axis=1), atol=1e-5)


@pytest.mark.parametrize("ratio", [1.0, 0.9, 0.8])
@pytest.mark.parametrize("px", [10.0, 40.0])
@pytest.mark.parametrize("strategy", ["both", "either", "uni"])
def test_fginn_matches_reference_rules(random_pair, ratio, px, strategy):
    A, B, k1, k2 = random_pair
    tab = knn_tables(A, B, binary=False, k=10)
    conf = MatchConfig(ratio=ratio, strategy=strategy, fginn=True, fginn_px=px)
    m, _ = filter_matches(tab, conf, k1, k2)
    assert _pairs(m) == _reference(tab, conf, k1, k2)


def test_ratio_semantics_and_nesting(random_pair):
    A, B, _, _ = random_pair
    tab = knn_tables(A, B, binary=False, k=2)
    n1 = len(A)
    # r = 1 is no test: every descriptor keeps its nearest neighbour
    m, _ = filter_matches(tab, MatchConfig(ratio=1.0, strategy="uni"))
    np.testing.assert_array_equal(m[:, 0], np.arange(n1))
    np.testing.assert_array_equal(m[:, 1], tab.idx12[:, 0])
    prev = None
    for r in (1.0, 0.95, 0.9, 0.8, 0.7, 0.5):
        sets = {s: _pairs(filter_matches(tab, MatchConfig(ratio=r, strategy=s))[0]) for s in ("both", "either", "uni")}
        assert sets["both"] <= sets["uni"] <= sets["either"]
        if prev is not None:  # a smaller r keeps a subset
            for s in sets:
                assert sets[s] <= prev[s]
        prev = sets
    assert 0 < len(prev["uni"]) < len(m)


def test_ratio_boundary_is_inclusive():
    # d1 / d2 = 0.75 exactly (representable): kept at r = 0.75, dropped just below
    tab = _tables([[0, 1]], [[0.75, 1.0]], [[0, -1], [0, -1]], [[0.75, np.inf], [1.0, np.inf]])
    assert len(filter_matches(tab, MatchConfig(ratio=0.75, strategy="uni"))[0]) == 1
    assert len(filter_matches(tab, MatchConfig(ratio=0.7499, strategy="uni"))[0]) == 0
    # no second neighbour (inf) passes any ratio
    assert len(filter_matches(tab, MatchConfig(ratio=0.1, strategy="both"))[0]) == 0  # 1->2 fails at 0.1
    tab1 = _tables([[0, -1]], [[0.75, np.inf]], [[0, -1]], [[0.75, np.inf]])
    m, d = filter_matches(tab1, MatchConfig(ratio=0.1, strategy="both"))
    assert m.tolist() == [[0, 0]] and d.tolist() == [0.75]
    # equal first and second distance (duplicate descriptor) fails every r < 1, passes r = 1
    tie = _tables([[0, 1]], [[0.5, 0.5]], [[0, -1], [0, -1]], [[0.5, np.inf], [0.5, np.inf]])
    assert len(filter_matches(tie, MatchConfig(ratio=0.99, strategy="uni"))[0]) == 0
    assert len(filter_matches(tie, MatchConfig(ratio=1.0, strategy="uni"))[0]) == 1


def test_mutual_check_and_union():
    # 1->2: 0->0, 1->0, 2->1 ; 2->1: 0->1, 1->2 (so 0->0 is not mutual, 1->0 and 2->1 are)
    idx12 = [[0, 1], [0, 1], [1, 0]]
    dist12 = [[0.1, 0.9], [0.2, 0.9], [0.3, 0.9]]
    idx21 = [[1, 0], [2, 0]]
    dist21 = [[0.2, 0.9], [0.3, 0.9]]
    tab = _tables(idx12, dist12, idx21, dist21)
    both, d = filter_matches(tab, MatchConfig(ratio=1.0, strategy="both"))
    assert both.tolist() == [[1, 0], [2, 1]]
    np.testing.assert_allclose(d, [0.2, 0.3])
    either, d = filter_matches(tab, MatchConfig(ratio=1.0, strategy="either"))
    assert either.tolist() == [[0, 0], [1, 0], [2, 1]]  # mutual pairs appear once
    np.testing.assert_allclose(d, [0.1, 0.2, 0.3])
    uni, _ = filter_matches(tab, MatchConfig(ratio=1.0, strategy="uni"))
    assert uni.tolist() == [[0, 0], [1, 0], [2, 1]]
    # a match only the 2->1 direction finds is in "either" only
    idx21b = [[1, 0], [2, 0], [0, 1]]  # image 2 now has 3 descriptors; 2 -> 0
    dist21b = [[0.2, 0.9], [0.3, 0.9], [0.4, 0.9]]
    tab = _tables(idx12, dist12, idx21b, dist21b)
    either, _ = filter_matches(tab, MatchConfig(ratio=1.0, strategy="either"))
    assert [0, 2] in either.tolist()
    assert [0, 2] not in filter_matches(tab, MatchConfig(ratio=1.0, strategy="both"))[0].tolist()
    # ratio applies in both directions for "both": 2->1 of image-2 descriptor 1 now fails it
    dist21c = [[0.2, 0.9], [0.3, 0.31]]
    tab = _tables(idx12, dist12, idx21, dist21c)
    assert filter_matches(tab, MatchConfig(ratio=0.8, strategy="both"))[0].tolist() == [[1, 0]]


def test_distance_threshold():
    idx12 = [[0, 1], [1, 0], [2, 1]]
    dist12 = [[0.1, 0.9], [0.25, 0.9], [0.5, 0.9]]
    idx21 = [[0, 1], [1, 0], [2, 0]]
    dist21 = [[0.1, 0.9], [0.25, 0.9], [0.5, 0.9]]
    tab = _tables(idx12, dist12, idx21, dist21)
    for strategy in ("both", "either", "uni"):
        m, d = filter_matches(tab, MatchConfig(strategy=strategy, distance_threshold=0.25))
        assert m.tolist() == [[0, 0], [1, 1]]
        assert (d <= 0.25).all()
        assert len(filter_matches(tab, MatchConfig(strategy=strategy, distance_threshold=0.0))[0]) == 0


def test_fginn_constructed_case():
    """The 2nd descriptor neighbour sits 3 px from the 1st: plain ratio rejects, FGINN skips it and keeps."""
    # image 2: descriptor 0 at (100, 100) (nearest), 1 at (103, 100) (near, d=1.01), 2 at (150, 100) (far, d=2)
    kp2 = np.array([[100, 100], [103, 100], [150, 100]], np.float32)
    kp1 = np.array([[10, 10]], np.float32)
    tab = _tables([[0, 1, 2]], [[1.0, 1.01, 2.0]],
                  [[0, -1, -1], [0, -1, -1], [0, -1, -1]], [[1.0, np.inf, np.inf], [1.01, np.inf, np.inf],
                                                            [2.0, np.inf, np.inf]])
    plain = MatchConfig(ratio=0.8, strategy="uni")
    assert len(filter_matches(tab, plain)[0]) == 0
    fg = MatchConfig(ratio=0.8, strategy="uni", fginn=True, fginn_px=10)
    m, d = filter_matches(tab, fg, kp1, kp2)
    assert m.tolist() == [[0, 0]] and d.tolist() == [1.0]
    # ... but when the far neighbour is too close in descriptor space, FGINN rejects too
    tab_close = _tables([[0, 1, 2]], [[1.0, 1.01, 1.1]], tab.idx21, tab.dist21)
    assert len(filter_matches(tab_close, fg, kp1, kp2)[0]) == 0
    # a radius larger than every spread: no far neighbour, the last listed one is the reference (2.0)
    assert len(filter_matches(tab, MatchConfig(ratio=0.8, strategy="uni", fginn=True, fginn_px=100), kp1, kp2)[0]) == 1
    assert len(filter_matches(tab, MatchConfig(ratio=0.4, strategy="uni", fginn=True, fginn_px=100), kp1, kp2)[0]) == 0
    # "both": the reverse direction uses image 1's keypoints
    m, _ = filter_matches(tab, MatchConfig(ratio=0.8, strategy="both", fginn=True), kp1, kp2)
    assert m.tolist() == [[0, 0]]


def test_fginn_needs_k_and_keypoints(random_pair):
    A, B, k1, k2 = random_pair
    conf = MatchConfig(ratio=0.8, fginn=True)
    with pytest.raises(ImtuneError, match="k > 2"):
        filter_matches(knn_tables(A, B, binary=False, k=2), conf, k1, k2)
    tab = knn_tables(A, B, binary=False, k=10)
    with pytest.raises(ImtuneError, match="keypoints"):
        filter_matches(tab, conf)
    with pytest.raises(ImtuneError, match="keypoints of image 2"):
        filter_matches(tab, conf, k1, k2[:10])


def test_empty_tables_and_convenience(random_pair):
    A, B, k1, k2 = random_pair
    for n1, n2 in [(0, 0), (0, 5), (5, 0)]:
        tab = knn_tables(A[:n1], B[:n2], binary=False, k=2)
        for s in ("both", "either", "uni"):
            m, d = filter_matches(tab, MatchConfig(ratio=0.8, strategy=s))
            assert m.shape == (0, 2) and m.dtype == np.int32 and d.shape == (0,)
    # one descriptor each: no second neighbour, the ratio test passes
    m, _ = filter_matches(knn_tables(A[:1], B[:1], binary=False), MatchConfig(ratio=0.5))
    assert m.tolist() == [[0, 0]]
    conf = MatchConfig(ratio=0.8, strategy="both", fginn=True)
    m, _ = match_descriptors(A, B, conf, kpts1=k1, kpts2=k2)
    ref, _ = filter_matches(knn_tables(A, B, binary=False, k=10), conf, k1, k2)
    np.testing.assert_array_equal(m, ref)


def test_binary_tables_filter(random_pair):
    rng = np.random.default_rng(9)
    A = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    B = A[rng.permutation(300)] ^ np.packbits(rng.random((300, 256)) < 0.1, axis=1)
    tab = knn_tables(A, B, binary=True, k=2)
    for s in ("both", "either", "uni"):
        conf = MatchConfig(ratio=0.8, strategy=s, distance_threshold=40)
        m, d = filter_matches(tab, conf)
        assert _pairs(m) == _reference(tab, conf)
        assert (d <= 40).all()
