"""Non-maximum suppression on hand-made score maps with known maxima."""

from __future__ import annotations

import numpy as np
import torch

from glampoints.nms import nms, nms_mask, nms_numpy


def _map(h: int = 40, w: int = 50, peaks=()) -> np.ndarray:
    s = np.zeros((h, w), dtype=np.float32)
    for x, y, v in peaks:
        s[y, x] = v
    return s


def test_returns_exact_maxima_sorted_by_score():
    s = _map(peaks=[(5, 5, 0.5), (30, 20, 0.9), (45, 35, 0.7)])
    xy, scores = nms_numpy(s, window_px=10)
    assert xy.dtype == np.float32 and xy.shape == (3, 2)
    np.testing.assert_array_equal(xy, [[30, 20], [45, 35], [5, 5]])
    np.testing.assert_allclose(scores, [0.9, 0.7, 0.5])


def test_window_suppresses_within_radius_only():
    # window 10 -> radius 5: a weaker peak 4 px away is suppressed, 6 px away survives
    s = _map(peaks=[(20, 20, 0.9), (24, 20, 0.8), (20, 26, 0.7), (14, 14, 0.6)])
    xy, _ = nms_numpy(s, window_px=10)
    np.testing.assert_array_equal(xy, [[20, 20], [20, 26], [14, 14]])
    # with window 14 (radius 7) the 6-px neighbours go too
    xy, _ = nms_numpy(s, window_px=14)
    np.testing.assert_array_equal(xy, [[20, 20]])


def test_top_k_and_threshold():
    s = _map(peaks=[(5, 5, 0.2), (20, 5, 0.4), (35, 5, 0.6), (5, 30, 0.8)])
    xy, sc = nms_numpy(s, window_px=10, top_k=2)
    np.testing.assert_array_equal(xy, [[5, 30], [35, 5]])
    xy, sc = nms_numpy(s, window_px=10, threshold=0.4)
    np.testing.assert_allclose(sc, [0.8, 0.6])  # strictly above the threshold
    xy, sc = nms_numpy(s, window_px=10, top_k=0)
    assert xy.shape == (0, 2) and sc.shape == (0,)


def test_plateau_gives_a_single_point():
    s = _map()
    s[10:16, 20:27] = 0.7  # 6x7 flat plateau, wider than the window radius
    xy, _ = nms_numpy(s, window_px=10)
    np.testing.assert_array_equal(xy, [[20, 10]])  # first pixel in raster order
    # an all-equal map above threshold also yields one point, never a cluster
    xy, _ = nms_numpy(np.full((30, 30), 0.5, np.float32), window_px=4)
    assert len(xy) == 1


def test_kept_points_are_separated_and_are_window_maxima():
    rng = np.random.default_rng(0)
    s = np.round(rng.random((64, 80)), 2).astype(np.float32)  # many ties
    xy, sc = nms_numpy(s, window_px=10)
    assert len(xy) > 10
    d = np.abs(xy[:, None, :] - xy[None, :, :]).max(axis=2)
    np.fill_diagonal(d, 99)
    assert d.min() > 5  # Chebyshev distance > radius
    for (x, y), v in zip(xy.astype(int), sc, strict=True):
        win = s[max(y - 5, 0) : y + 6, max(x - 5, 0) : x + 6]
        assert v == win.max()


def test_batched_torch_version_matches_maxpool_path_and_numpy():
    rng = np.random.default_rng(1)
    s = torch.from_numpy(np.round(rng.random((3, 1, 37, 41)), 1).astype(np.float32))
    fast = nms_mask(s, 6, 0.1, use_cv2=True)
    ref = nms_mask(s, 6, 0.1, use_cv2=False)
    assert torch.equal(fast, ref)
    out = nms(s, 6, 0.1, top_k=7)
    assert len(out) == 3
    for b, (xy, sc) in enumerate(out):
        assert xy.dtype == torch.float32 and len(xy) <= 7
        xy_np, sc_np = nms_numpy(s[b, 0].numpy(), 6, 0.1, 7)
        np.testing.assert_array_equal(xy.numpy(), xy_np)
        np.testing.assert_array_equal(sc.numpy(), sc_np)
