import cv2
import numpy as np
import pytest

from mosaic.config import RegistrationConfig
from mosaic.registration import estimate_homography, estimate_motion
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
    assert corner_error(reg.H_moving_to_fixed, H_true, (660, 350)) < 1.0
    assert reg.reproj_error_px < 1.0


def test_too_few_matches_fails():
    xy = np.zeros((3, 2), np.float32)
    reg = estimate_homography(xy, xy, RegistrationConfig())
    assert not reg.ok and reg.H_moving_to_fixed is None
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


def _similarity_pair(rng, n, x_max, perspective=(0.0, 0.0), noise=0.7, angle=3.0, scale=1.02):
    H_true = similarity(angle, scale, 10.0, -6.0, center=(330, 175))
    H_true[2, :2] = perspective
    cur = rng.uniform([0, 0], [x_max, 350], (n, 2)).astype(np.float32)
    prev = _project(H_true, cur) + rng.normal(0, noise, (n, 2)).astype(np.float32)
    prev[: n // 6] = rng.uniform([0, 0], [660, 350], (n // 6, 2))  # outliers
    return cur, prev, H_true


def test_similarity_chosen_when_inliers_cover_a_third_of_the_frame():
    """Vessels on one side, nothing on the other: the homography extrapolates its perspective
    terms into the empty side, the similarity does not."""
    rng = np.random.default_rng(4)
    models, err_auto, err_h = [], [], []
    for _ in range(8):
        cur, prev, H_true = _similarity_pair(rng, 180, 220)
        config = RegistrationConfig(model="auto", perspective_prior=0.0)
        reg = estimate_motion(cur, prev, config, (350, 660))
        assert reg.ok
        models.append(reg.model)
        assert 0.25 < reg.coverage < 0.36
        err_auto.append(corner_error(reg.H_moving_to_fixed, H_true, (660, 350)))
        H_only = estimate_homography(cur, prev, RegistrationConfig()).H_moving_to_fixed
        err_h.append(corner_error(H_only, H_true, (660, 350)))
    assert models.count("similarity") >= 6, models
    assert "homography" not in models, models
    assert np.median(err_auto) < 0.5 and np.median(err_auto) < 0.5 * np.median(err_h)


def test_homography_chosen_for_a_strong_perspective_seen_across_the_frame():
    rng = np.random.default_rng(5)
    for _ in range(4):
        cur, prev, H_true = _similarity_pair(rng, 300, 660, perspective=(2e-4, -1.5e-4))
        reg = estimate_motion(cur, prev, RegistrationConfig(model="auto"), (350, 660))
        assert reg.ok and reg.model == "homography"
        assert reg.coverage > 0.85
        assert corner_error(reg.H_moving_to_fixed, H_true, (660, 350)) < 1.0


@pytest.mark.parametrize("model", ["translation", "similarity", "affine", "homography"])
def test_a_forced_model_is_of_its_class(model):
    rng = np.random.default_rng(6)
    rigid = model == "translation"
    cur, prev, _ = _similarity_pair(rng, 200, 660, angle=0.0 if rigid else 3.0, scale=1.0)
    config = RegistrationConfig(model=model, perspective_prior=0.0)
    reg = estimate_motion(cur, prev, config, (350, 660))
    assert reg.ok and reg.model == model
    H = reg.H_moving_to_fixed
    if model != "homography":
        np.testing.assert_allclose(H[2], [0, 0, 1], atol=1e-12)
    if model in ("translation", "similarity"):
        assert abs(H[0, 0] - H[1, 1]) < 1e-9 and abs(H[0, 1] + H[1, 0]) < 1e-9
    if model == "translation":
        np.testing.assert_allclose(H[:2, :2], np.eye(2), atol=1e-12)


def test_refined_model_keeps_the_true_inliers_and_rejects_the_outliers():
    """The chosen model is refined on every match within the threshold: the inlier set is
    the true one."""
    rng = np.random.default_rng(7)
    cur, prev, _ = _similarity_pair(rng, 240, 660)
    true_inliers = np.arange(240) >= 40
    reg = estimate_motion(cur, prev, RegistrationConfig(model="auto"), (350, 660))
    assert reg.inliers[true_inliers].mean() > 0.97
    assert reg.inliers[~true_inliers].sum() <= 2


def _mean_corner_errors(rng, x_max, prior, perspective=(3e-5, -2e-5), trials=8):
    errors = {"pure": [], "prior": [], "homography": []}
    for _ in range(trials):
        cur, prev, H_true = _similarity_pair(rng, 200, x_max, perspective=perspective)
        for name, config in (
            ("pure", RegistrationConfig(perspective_prior=0.0)),
            ("prior", RegistrationConfig(perspective_prior=prior)),
            ("homography", RegistrationConfig(model="homography")),
        ):
            reg = estimate_motion(cur, prev, config, (350, 660))
            assert reg.ok and reg.model == config.model
            errors[name].append(corner_error(reg.H_moving_to_fixed, H_true, (660, 350)))
    return {k: float(np.median(v)) for k, v in errors.items()}


def test_perspective_prior_recovers_a_mild_perspective_seen_across_the_frame():
    """A few pixels of perspective at the corners: the pure similarity is biased by them, the
    similarity relaxed under the prior follows them."""
    e = _mean_corner_errors(np.random.default_rng(8), 660, prior=0.01)
    assert e["pure"] > 2.0, e
    assert e["prior"] < 0.3 * e["pure"] and e["prior"] < 1.0, e


def test_perspective_prior_keeps_the_simple_model_where_matches_sit_on_one_side():
    """Matches on a third of the frame: the prior holds the perspective terms back from
    extrapolating into the empty side, where the homography's run free."""
    e = _mean_corner_errors(np.random.default_rng(9), 220, prior=0.01, perspective=(0.0, 0.0))
    assert e["prior"] < 0.8 and e["prior"] < 0.75 * e["homography"], e


def test_perspective_evidence_tells_a_similarity_from_a_view_with_perspective():
    """Unrelaxed (`relax=False`), the fit stays a pure similarity and says how much a
    homography would add: 1.03 for a similarity motion with noise, 280 with perspective;
    relaxed, the perspective is found."""
    rng = np.random.default_rng(2)
    shape = (300, 400)
    xy = rng.uniform([0, 0], [400, 300], (300, 2))
    S = np.array([[1.01, -0.02, 6.0], [0.02, 1.01, -4.0], [0, 0, 1.0]])
    P = S.copy()
    P[2, :2] = [4e-5, -3e-5]
    config = RegistrationConfig()
    found = {}
    for name, H in (("similarity", S), ("perspective", P)):
        moved = cv2.perspectiveTransform(xy[None], H)[0] + rng.normal(0, 0.5, xy.shape)
        pure = estimate_motion(xy, moved, config, shape, relax=False)
        assert pure.ok and pure.model == "similarity"
        np.testing.assert_allclose(pure.H_moving_to_fixed[2, :2], 0.0, atol=1e-12)
        found[name] = pure.perspective_evidence
        if name == "perspective":
            relaxed = estimate_motion(xy, moved, config, shape)
            np.testing.assert_allclose(relaxed.H_moving_to_fixed[2, :2], H[2, :2], rtol=0.2)
    assert found["similarity"] < 2.0, found
    assert found["perspective"] > 10.0, found
