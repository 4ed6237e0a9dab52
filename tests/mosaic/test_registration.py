import numpy as np
import pytest

from mosaic.config import RegistrationConfig
from mosaic.registration import estimate_homography
from tests.helpers import corner_error, similarity


def _project(H, xy):
    p = np.hstack([xy, np.ones((len(xy), 1))]) @ H.T
    return (p[:, :2] / p[:, 2:]).astype(np.float32)


@pytest.mark.parametrize("method", ["ransac", "usac_magsac", "usac_default"])
def test_recovers_known_homography_despite_outliers(method):
    rng = np.random.default_rng(0)
    H_true = similarity(7.0, 1.05, 12.0, -8.0, center=(330, 175))
    H_true[2, :2] = [1e-5, -2e-5]
    cur = rng.uniform([0, 0], [660, 350], (200, 2)).astype(np.float32)
    prev = _project(H_true, cur) + rng.normal(0, 0.3, (200, 2)).astype(np.float32)
    prev[:60] = rng.uniform([0, 0], [660, 350], (60, 2))  # 30 % outliers
    reg = estimate_homography(cur, prev, RegistrationConfig(method=method))
    assert reg.ok
    assert reg.n_matches == 200
    assert 130 <= reg.n_inliers <= 145
    assert not reg.inliers[:60].any() or reg.inliers[:60].sum() <= 2
    assert corner_error(reg.H_cur_to_prev, H_true, (660, 350)) < 1.0
    assert reg.reproj_error_px < 1.0


def test_too_few_matches_fails():
    xy = np.zeros((3, 2), np.float32)
    reg = estimate_homography(xy, xy, RegistrationConfig())
    assert not reg.ok and reg.H_cur_to_prev is None
    assert "few" in reg.reason


def test_reflection_fails():
    rng = np.random.default_rng(1)
    cur = rng.uniform(0, 300, (50, 2)).astype(np.float32)
    prev = cur * np.array([-1.0, 1.0], np.float32) + 400
    reg = estimate_homography(cur, prev, RegistrationConfig())
    assert not reg.ok
    assert "reflection" in reg.reason


def test_extreme_scale_fails():
    rng = np.random.default_rng(2)
    cur = rng.uniform(0, 300, (50, 2)).astype(np.float32)
    reg = estimate_homography(cur, cur * 5.0, RegistrationConfig())
    assert not reg.ok
    assert "scale" in reg.reason


def test_min_inliers_from_config():
    rng = np.random.default_rng(3)
    cur = rng.uniform(0, 300, (12, 2)).astype(np.float32)
    prev = cur + 5
    assert estimate_homography(cur, prev, RegistrationConfig(min_inliers=8)).ok
    reg = estimate_homography(cur, prev, RegistrationConfig(min_inliers=20))
    assert not reg.ok and "inliers" in reg.reason
