"""Evaluation metrics (NNDR AUC, coverage, registration errors, FIRE AUC) on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from glampoints.metrics import (
    class_error_stats,
    classify_errors,
    coverage_fraction,
    fire_auc,
    fire_auc_integral,
    mean_auc,
    nearest_neighbour_ratios,
    nndr_auc,
    point_errors,
    rmse,
    success_curve,
    true_positive_mask,
)


def test_point_errors_identity_and_known_shift():
    xy = np.array([[0, 0], [10, 5], [99, 80]], np.float32)
    np.testing.assert_allclose(point_errors(np.eye(3), xy, xy), 0.0)
    shift = np.array([[1, 0, 3], [0, 1, 4], [0, 0, 1]], np.float64)  # a 3-4-5 triangle
    np.testing.assert_allclose(point_errors(shift, xy, xy), 5.0)
    to_infinity = np.array([[1, 0, 0], [0, 1, 0], [1, 0, 0]], np.float64)  # w = x
    assert point_errors(to_infinity, [[0, 3]], [[0, 3]])[0] == math.inf


def test_classify_errors_uses_median_and_max():
    assert classify_errors(np.array([1.0, 2.0, 3.0])) == ("acceptable", 2.0, 3.0)
    assert classify_errors(np.array([1.0, 2.0, 30.0]))[0] == "inaccurate"  # MAE not < 30
    assert classify_errors(np.array([10.0, 10.0, 10.0]))[0] == "inaccurate"  # MEE not < 10
    assert classify_errors(np.array([9.9, 9.9, 29.9]))[0] == "acceptable"
    assert rmse(np.array([3.0, 4.0])) == pytest.approx(math.sqrt(12.5))
    assert math.isnan(rmse(np.zeros(0)))


def test_nearest_neighbour_ratios_by_hand():
    d = np.array([[1.0, 2.0, 4.0], [3.0, 3.0, 5.0], [0.0, 0.0, 1.0]])
    nearest, ratio = nearest_neighbour_ratios(d)
    np.testing.assert_array_equal(nearest, [0, 0, 0])
    np.testing.assert_allclose(ratio, [0.5, 1.0, 1.0])  # equal distances: ambiguous, ratio 1
    nearest, ratio = nearest_neighbour_ratios(np.array([[2.0], [1.0]]))
    np.testing.assert_allclose(ratio, [0.0, 0.0])  # no second neighbour
    assert nearest_neighbour_ratios(np.zeros((0, 3)))[1].shape == (0,)


def test_nndr_auc_by_hand():
    # pairs (correct, wrong): (0.2, 0.4) ok, (0.2, 0.8) ok, (0.6, 0.4) wrong, (0.6, 0.8) ok
    assert nndr_auc([0.2, 0.4, 0.6, 0.8], [True, False, True, False]) == pytest.approx(0.75)
    assert nndr_auc([0.1, 0.2, 0.9], [True, True, False]) == 1.0
    assert nndr_auc([0.9, 0.1], [True, False]) == 0.0
    assert nndr_auc([0.5, 0.5], [True, False]) == 0.5  # a tie counts half
    assert math.isnan(nndr_auc([0.1, 0.2], [True, True]))  # no wrong match: undefined


def test_nndr_auc_of_an_identity_pair_is_perfect():
    """Same points, same descriptors (plus noise); 5 extra points of image 1 have no partner."""
    rng = np.random.default_rng(0)
    xy = np.stack(np.meshgrid(np.arange(10, 100, 20), np.arange(10, 80, 20)), -1).reshape(-1, 2)
    xy1 = np.vstack([xy, rng.uniform(0, 90, (5, 2))]).astype(np.float32)
    desc2 = rng.normal(size=(len(xy), 32))
    desc1 = np.vstack([desc2 + rng.normal(scale=0.01, size=desc2.shape), rng.normal(size=(5, 32))])
    d = np.linalg.norm(desc1[:, None] - desc2[None], axis=2)
    nearest, ratio = nearest_neighbour_ratios(d)
    correct = true_positive_mask(xy1, xy[nearest], np.eye(3))
    assert correct.sum() == len(xy)  # every point with a partner finds it
    assert nndr_auc(ratio, correct) == 1.0


def test_coverage_fraction_counts_pixels_in_disks():
    # lattice points with x^2 + y^2 <= 25^2: 1961 (Gauss circle problem, r = 25)
    shape = (101, 101)
    assert coverage_fraction([[50, 50]], shape) == pytest.approx(1961 / 101**2)
    # a duplicate point adds nothing; a disjoint one doubles it
    assert coverage_fraction([[50, 50], [50, 50]], shape) == pytest.approx(1961 / 101**2)
    wide = (101, 301)
    assert coverage_fraction([[50, 50], [200, 50]], wide) == pytest.approx(2 * 1961 / (101 * 301))
    # a corner keeps the quadrant: (1961 - 1 - 4 * 25) / 4 inside + 2 * 25 on the axes + 1
    assert coverage_fraction([[0, 0]], shape) == pytest.approx(516 / 101**2)
    # whole image covered; empty set covers nothing
    assert coverage_fraction([[5, 5]], (10, 10)) == 1.0
    assert coverage_fraction(np.zeros((0, 2)), shape) == 0.0
    # with a mask: the fraction of the masked area (x >= 50 holds (1961 - 51) / 2 + 51 = 1006)
    mask = np.zeros(shape, np.uint8)
    mask[:, 50:] = 1
    assert coverage_fraction([[50, 50]], shape, mask=mask) == pytest.approx(1006 / (101 * 51))


def test_fire_auc_on_a_made_up_error_list():
    errors = np.array([0.5, 3.0, 10.0, np.inf])  # inf: a failed pair
    # fraction with error < t: t = 1: 1/4; t = 2, 3: 1/4; t = 4..10: 2/4; t = 11..25: 3/4
    expected = (1 * 0.25 + 2 * 0.25 + 7 * 0.5 + 15 * 0.75) / 25
    assert fire_auc(errors) == pytest.approx(expected)
    assert fire_auc(errors) == pytest.approx(0.62)
    np.testing.assert_allclose(
        success_curve(errors, [0, 1, 3, 3.5, 100]), [0, 0.25, 0.25, 0.5, 0.75]
    )
    # the 0..25 integral: mean of clip(1 - e / 25, 0, 1) = (0.98 + 0.88 + 0.6 + 0) / 4
    assert fire_auc_integral(errors) == pytest.approx(0.615)
    assert fire_auc(np.zeros(5)) == 1.0
    assert fire_auc(np.full(3, np.inf)) == 0.0


def test_mean_auc_over_categories():
    by_category = {"S": np.array([0.5]), "P": np.array([np.inf]), "A": np.array([3.0])}
    # S: 1 for every t; P: 0; A: error 3 is under t = 4..25, 22 of 25 thresholds
    assert mean_auc(by_category) == pytest.approx((1.0 + 0.0 + 22 / 25) / 3)
    assert math.isnan(mean_auc({}))


def test_class_error_stats():
    classes = np.array(["acceptable", "acceptable", "inaccurate", "failed"])
    stats = class_error_stats(classes, [1.0, 3.0, 20.0, np.nan], [2.0, 4.0, 30.0, np.nan])
    assert stats["acceptable"] == {
        "n": 2.0,
        "mee_mean": 2.0,
        "mee_std": 1.0,
        "rmse_mean": 3.0,
        "rmse_std": 1.0,
    }
    assert stats["inaccurate"]["mee_mean"] == 20.0
    assert stats["non_failed"]["n"] == 3.0
    assert stats["non_failed"]["mee_mean"] == pytest.approx(8.0)
    assert stats["non_failed"]["rmse_mean"] == pytest.approx(12.0)
    assert math.isnan(
        class_error_stats(np.array(["failed"]), [np.nan], [np.nan])["acceptable"]["mee_mean"]
    )
