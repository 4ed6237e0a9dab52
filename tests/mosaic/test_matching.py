import numpy as np

from mosaic.config import MatchingConfig
from mosaic.matching import distance_matrix, match_descriptors


def test_cross_check_recovers_a_permutation():
    rng = np.random.default_rng(0)
    a = rng.random((50, 128), dtype=np.float32)
    perm = rng.permutation(50)
    b = a[perm] + rng.normal(0, 1e-3, (50, 128)).astype(np.float32)
    m = match_descriptors(a, b, MatchingConfig())
    assert len(m) == 50
    np.testing.assert_array_equal(perm[m.idx_b], m.idx_a)


def test_cross_check_drops_non_mutual_matches():
    a = np.array([[0.0, 0.0], [0.1, 0.0]], np.float32)  # both nearest to b[0]
    b = np.array([[0.05, 0.0], [5.0, 5.0]], np.float32)
    mutual = match_descriptors(a, b, MatchingConfig(cross_check=True))
    assert len(mutual) == 1
    oneway = match_descriptors(a, b, MatchingConfig(cross_check=False))
    assert len(oneway) == 2


def test_ratio_test_drops_ambiguous_matches():
    a = np.array([[0.0, 0.0], [10.0, 0.0]], np.float32)
    b = np.array([[1.0, 0.0], [-1.1, 0.0], [10.0, 0.5]], np.float32)  # a[0] is ambiguous
    m = match_descriptors(a, b, MatchingConfig(cross_check=False, ratio=0.8))
    assert m.idx_a.tolist() == [1]
    assert m.idx_b.tolist() == [2]


def test_hamming_distance_for_binary_descriptors():
    a = np.array([[0b00000000], [0b11111111]], np.uint8)
    b = np.array([[0b00000111]], np.uint8)
    np.testing.assert_allclose(distance_matrix(a, b), [[3.0], [5.0]])


def test_l2_distance_matches_direct_computation():
    rng = np.random.default_rng(2)
    a, b = rng.random((7, 16)), rng.random((5, 16))
    direct = np.linalg.norm(a[:, None] - b[None], axis=2)
    np.testing.assert_allclose(distance_matrix(a, b), direct, atol=1e-5)


def test_empty_inputs():
    m = match_descriptors(
        np.zeros((0, 128), np.float32), np.ones((3, 128), np.float32), MatchingConfig()
    )
    assert len(m) == 0


def test_matches_equal_a_brute_force_on_true_distances():
    """Squared distances inside must not change a match, a ratio decision or a distance."""
    rng = np.random.default_rng(5)
    a = rng.random((300, 32)).astype(np.float32)
    b = np.concatenate([a[:200] + rng.normal(0, 0.05, (200, 32)), rng.random((150, 32))])
    b = b.astype(np.float32)
    direct = np.linalg.norm(a[:, None].astype(np.float64) - b[None], axis=2)
    nn = direct.argmin(axis=1)
    second = np.sort(direct, axis=1)[:, 1]
    best = direct[np.arange(300), nn]
    for cfg in (MatchingConfig(), MatchingConfig(cross_check=False, ratio=0.8)):
        m = match_descriptors(a, b, cfg)
        keep = np.ones(300, bool)
        if cfg.cross_check:
            keep &= direct.argmin(axis=0)[nn] == np.arange(300)
        if cfg.ratio < 1:
            keep &= best < cfg.ratio * second
        np.testing.assert_array_equal(m.idx_a, np.flatnonzero(keep))
        np.testing.assert_array_equal(m.idx_b, nn[keep])
        np.testing.assert_allclose(m.distance, best[keep], atol=1e-4)


def test_cross_check_with_ties_keeps_the_first_row_as_argmax_does():
    """Duplicate descriptors tie in a column: only the first of them is mutual, as with
    `argmax(axis=0)`, on both the unit-norm (similarity) and the distance path."""
    rng = np.random.default_rng(3)
    a = rng.random((40, 16)).astype(np.float32)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = a[rng.permutation(40)[:30]].copy()
    a[7] = a[5]  # rows 5 and 7 tie for the same column
    b[3] = b[1]  # columns 1 and 3 tie for the same row
    for cfg, unit in ((MatchingConfig(), True), (MatchingConfig(ratio=0.99), False)):
        m = match_descriptors(a, b, cfg)
        s = a @ b.T if unit else -(distance_matrix(a, b) ** 2)
        nn = s.argmax(axis=1)
        keep = s.argmax(axis=0)[nn] == np.arange(40)
        if not unit:
            d = distance_matrix(a, b)
            second = np.sort(d, axis=1)[:, 1]
            keep &= d[np.arange(40), nn] ** 2 < 0.99**2 * second**2
        np.testing.assert_array_equal(m.idx_a, np.flatnonzero(keep))
        np.testing.assert_array_equal(m.idx_b, nn[keep])
        assert 7 not in m.idx_a.tolist()
