"""Points and transforms (`mosaic.geometry`) against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from mosaic.geometry import corner_error, relative_homographies, reweighted_rounds, view_error


def test_corner_error_and_relative_homographies():
    T = np.array([[1, 0, 3.0], [0, 1, 4.0], [0, 0, 1]])
    assert corner_error(T, np.eye(3), (100, 50)) == pytest.approx(5.0)
    G = [np.diag([2.0, 2.0, 1.0]), np.diag([2.0, 2.0, 1.0]) @ T]
    rel = relative_homographies(G)
    np.testing.assert_allclose(rel[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rel[1], T, atol=1e-12)


def test_view_error_takes_a_misplacement_apart_at_the_frame_centre():
    """A frame misplaced by a zoom, a roll about its centre and then a shift, under a tilted
    (perspective) truth: the three come back as they were made."""
    w, h = 660, 350
    c = np.array([[1, 0, (w - 1) / 2], [0, 1, (h - 1) / 2], [0, 0, 1.0]])
    zoom, roll, shift = 1.02, np.deg2rad(0.7), np.array([3.0, -4.0])
    S = np.diag([zoom, zoom, 1.0])
    S[:2, :2] = zoom * np.array([[np.cos(roll), -np.sin(roll)], [np.sin(roll), np.cos(roll)]])
    S[:2, 2] = shift
    error = c @ S @ np.linalg.inv(c)  # in frame pixels: about the centre, then shifted
    H_gt = np.array([[0.9, 0.05, 120.0], [-0.04, 1.1, -30.0], [2e-5, -3e-5, 1.0]])
    got = view_error(H_gt @ error, H_gt, (w, h))
    assert got == pytest.approx((5.0, np.log(zoom), roll), abs=1e-9)
    assert view_error(H_gt, H_gt, (w, h)) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)


def _shift_data(seed: int):
    """80 points moved by (3, -2) with 0.1 px noise and 20 moved 30-50 px anywhere else."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 100, (100, 2))
    b = a + np.array([3.0, -2.0]) + rng.normal(0, 0.1, a.shape)
    angle = rng.uniform(0, 2 * np.pi, 20)
    b[80:] = a[80:] + rng.uniform(30, 50, (20, 1)) * np.column_stack([np.cos(angle), np.sin(angle)])
    return a, b


def _mean_shift(a, b):
    """The weighted least-squares translation, and the fit's errors."""

    def fit(_round, _previous, inliers, weights):
        w = weights[inliers]
        return (w[:, None] * (b[inliers] - a[inliers])).sum(0) / w.sum()

    return fit, lambda t: np.linalg.norm(a + t - b, axis=1)


@pytest.mark.parametrize("seed", range(5))
def test_reweighted_rounds_leave_the_outliers_out(seed):
    a, b = _shift_data(seed)
    fit, errors = _mean_shift(a, b)
    t, inliers, weights, err = reweighted_rounds(
        fit,
        errors,
        np.ones(100, bool),
        np.ones(100),
        rounds=3,
        threshold=3.0,
        huber_k=1.0,
        min_points=4,
    )
    # the first round's mean is off by at most 0.2 x 50 = 10 px; the outliers, 30 px away,
    # leave at once where it is under 27 px: the mean of 80 points, 0.1 / sqrt(80) = 0.011 px
    # per axis, so 0.05 is over four standard errors
    assert np.abs(t - [3.0, -2.0]).max() < 0.05
    assert inliers[:80].all() and not inliers[80:].any()
    # Huber's: 1 within k = 1 px of the fit, k / r beyond (the outliers are over 25 px off)
    np.testing.assert_array_equal(weights[:80], np.ones(80))
    assert weights[80:].max() < 1 / 25
    np.testing.assert_allclose(err, errors(t))


def test_reweighted_rounds_stop_on_a_failed_fit_or_too_few_points():
    a, b = _shift_data(0)
    fit, errors = _mean_shift(a, b)
    calls = []

    def failing(round_, previous, inliers, weights):
        calls.append(round_)
        return None if round_ == 1 else fit(round_, previous, inliers, weights)

    kw = dict(rounds=3, threshold=3.0, huber_k=1.0, min_points=4)
    assert reweighted_rounds(failing, errors, np.ones(100, bool), np.ones(100), **kw)[0] is None
    assert calls == [0, 1]
    few = np.zeros(100, bool)
    few[:3] = True
    t, inliers, _, err = reweighted_rounds(fit, errors, few, np.ones(100), **kw)
    assert t is None and err is None and inliers.sum() == 3
