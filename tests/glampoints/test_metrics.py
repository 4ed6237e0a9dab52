"""The paper's metrics and failure rules against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from glampoints.metrics import (
    failure_reason,
    matching_score,
    registration_class,
    repeatability,
    six_fixed_points,
    true_positive_mask,
    warp_points,
)


def _T(tx: float, ty: float) -> np.ndarray:
    return np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1]], dtype=np.float64)


GRID = np.stack(np.meshgrid(np.arange(10, 100, 20), np.arange(10, 80, 20)), -1).reshape(-1, 2)
GRID = GRID.astype(np.float32)  # 20 well-separated points in a 100x90 image
SHAPE = (90, 100)


def test_warp_points():
    H = np.array([[2, 0, 5], [0, 3, -1], [0, 0, 1]], dtype=np.float64)
    xy = np.array([[0, 0], [1, 2]], dtype=np.float32)
    np.testing.assert_allclose(warp_points(H, xy), [[5, -1], [7, 5]])
    P = np.array([[1, 0, 0], [0, 1, 0], [0.01, 0, 1]])
    np.testing.assert_allclose(warp_points(P, [[100, 50]]), [[50, 25]])
    assert warp_points(H, np.zeros((0, 2))).shape == (0, 2)


def test_repeatability_identity_and_known_shifts():
    assert repeatability(GRID, GRID, np.eye(3), SHAPE, SHAPE) == 1.0
    # all points displaced 5 px with identity H: nothing repeated at eps = 3
    assert repeatability(GRID, GRID + np.array([5, 0]), np.eye(3), SHAPE, SHAPE) == 0.0
    # 2.5 px is inside eps = 3
    assert repeatability(GRID, GRID + np.array([0, 2.5]), np.eye(3), SHAPE, SHAPE) == 1.0
    # half of the second set moved far away: 10 + 10 repeated of 20 + 20
    moved = GRID.copy()
    moved[::2] += 9
    assert repeatability(GRID, moved, np.eye(3), SHAPE, SHAPE) == pytest.approx(0.5)
    assert repeatability(np.zeros((0, 2)), np.zeros((0, 2)), np.eye(3), SHAPE, SHAPE) == 0.0


def test_repeatability_counts_only_the_common_region():
    # image 2 is image 1 shifted left by 40 px: points with x < 40 leave the view
    H = _T(-40, 0)
    xy2 = warp_points(H, GRID)
    inside = xy2[:, 0] >= 0
    # only the 12 points with x >= 40 count, all of them repeated
    assert repeatability(GRID, xy2[inside], H, SHAPE, SHAPE) == 1.0
    # an extra unmatched point of image 2 in the common region lowers it to 24 / 25
    extra = np.vstack([xy2[inside], [[5, 5]]])
    assert repeatability(GRID, extra, H, SHAPE, SHAPE) == pytest.approx(24 / 25)


def test_true_positive_mask_threshold():
    H = _T(10, 0)
    xy1 = np.array([[0, 0], [0, 0], [0, 0], [5, 5]], dtype=np.float32)
    xy2 = np.array([[10, 0], [12.9, 0], [13.1, 0], [15, 8]], dtype=np.float32)
    np.testing.assert_array_equal(true_positive_mask(xy1, xy2, H), [True, True, False, True])
    assert true_positive_mask(xy1, xy2, H, eps=2.0).tolist() == [True, False, False, False]


def test_matching_score():
    H = np.eye(3)
    xy2 = GRID.copy()
    # 5 correct + 3 wrong matches among 20 keypoints per image
    m1 = GRID[:8]
    m2 = GRID[:8].copy()
    m2[5:] += 20
    assert matching_score(GRID, xy2, m1, m2, H, SHAPE, SHAPE) == pytest.approx(5 / 20)
    # image 2 has 10 keypoints: 0.5 * 5 * (1/20 + 1/10)
    assert matching_score(GRID, xy2[:10], m1, m2, H, SHAPE, SHAPE) == pytest.approx(0.375)


@pytest.mark.parametrize(
    ("H", "n", "expect"),
    [
        (np.eye(3), 3, "too few matches"),
        (None, 10, "no homography"),
        (np.full((3, 3), np.nan), 10, "non-finite"),
        (np.diag([-1.0, 1.0, 1.0]), 10, "reflection"),
        (np.diag([4.5, 4.5, 1.0]), 10, "scale"),
        (np.diag([5.0, 1.0, 1.0]), 10, "scale"),  # anisotropic: largest singular value > 4
        (np.diag([0.05, 0.05, 1.0]), 10, "scale"),
        (np.diag([-2.0, -2.0, -1.0]), 10, None),  # same as diag(2, 2, 1): no flip
        (np.diag([3.9, 0.11, 1.0]), 4, None),
    ],
)
def test_failure_reason(H, n, expect):
    reason = failure_reason(H, n)
    if expect is None:
        assert reason is None
    else:
        assert reason is not None and expect in reason


def test_rotation_is_not_a_failure():
    a = np.deg2rad(170)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    assert failure_reason(R, 50) is None


def test_six_fixed_points():
    p = six_fixed_points(600, 400)
    assert p.shape == (6, 2) and p.dtype == np.float32
    np.testing.assert_allclose(sorted(set(p[:, 0])), [100, 300, 500])
    np.testing.assert_allclose(sorted(set(p[:, 1])), [100, 300])


def test_registration_class_known_errors():
    pts = six_fixed_points(600, 400)
    H_gt = _T(20, -10)
    assert registration_class(H_gt, H_gt, pts, 50) == ("acceptable", 0.0, 0.0)
    cls, mee, mae = registration_class(_T(23, -6), H_gt, pts, 50)  # 5 px error everywhere
    assert cls == "acceptable" and mee == pytest.approx(5) and mae == pytest.approx(5)
    cls, mee, mae = registration_class(_T(32, -10), H_gt, pts, 50)  # 12 px: MEE too big
    assert cls == "inaccurate" and mee == pytest.approx(12) and mae == pytest.approx(12)
    # scale about point (100, 100): errors 0, 200*0.2, 400*0.2, ... -> MAE > 30
    S = _T(100, 100) @ np.diag([1.2, 1.2, 1]) @ _T(-100, -100)
    cls, mee, mae = registration_class(S @ H_gt, H_gt, pts, 50)
    err = np.linalg.norm((pts + np.array([20, -10]) - 100) * 0.2, axis=1)
    assert cls == "inaccurate"
    assert mee == pytest.approx(np.median(err), rel=1e-5)
    assert mae == pytest.approx(err.max(), rel=1e-5)
    cls, mee, mae = registration_class(H_gt, H_gt, pts, 3)
    assert cls == "failed" and math.isnan(mee) and math.isnan(mae)
    assert registration_class(None, H_gt, pts, 10)[0] == "failed"
