import numpy as np
import pytest

from mosaic.config import Config, FeaturesConfig, with_overrides
from mosaic.errors import ConfigError
from mosaic.features import DETECTORS, FeatureExtractor
from mosaic.pipeline import register_pair
from mosaic.preprocess import prepare
from tests.helpers import corner_error, crop_pair, similarity

CLASSICAL = [name for name in DETECTORS if name != "glampoints"]


@pytest.fixture(scope="module")
def pair(fundus):
    H_b_to_a = similarity(8.0, 1.05, 25.0, -15.0, center=(240, 160))
    a, b = crop_pair(fundus, H_b_to_a, origin=(450, 500), size=(480, 320))
    return a, b, H_b_to_a


@pytest.mark.parametrize("name", CLASSICAL)
def test_detectors_return_float_xy_inside_the_mask(fundus, name):
    frame = fundus[300:900, 300:1100]
    prepared = prepare(frame, Config().preprocess)
    prepared.mask[:, :200] = 0  # forbid the left part
    config = FeaturesConfig(detector=name, max_keypoints=300)
    features = FeatureExtractor(config)(prepared)
    assert features.xy.dtype == np.float32 and features.xy.shape[1] == 2
    assert 30 <= len(features) <= 300
    assert features.xy[:, 0].min() >= 200 - 1
    assert features.descriptors.shape == (len(features), 128)
    norms = np.linalg.norm(features.descriptors, axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-3)  # root-SIFT rows have unit L2 norm


@pytest.mark.parametrize(
    ("name", "dtype"), [("orb", np.uint8), ("brisk", np.uint8), ("sift", np.float32)]
)
def test_native_descriptors(fundus, name, dtype):
    prepared = prepare(fundus[300:900, 300:1100], Config().preprocess)
    features = FeatureExtractor(FeaturesConfig(detector=name, descriptor="native"))(prepared)
    assert features.descriptors.dtype == dtype
    assert len(features.descriptors) == len(features.xy) > 30


def test_learned_and_grid_detectors_have_no_native_descriptor():
    with pytest.raises(ConfigError, match="rootsift"):
        FeatureExtractor(FeaturesConfig(detector="random-grid", descriptor="native"))


def test_random_grid_is_spread_uniformly(fundus):
    prepared = prepare(fundus[400:800, 400:1000], Config().preprocess)
    features = FeatureExtractor(FeaturesConfig(detector="random-grid", max_keypoints=200))(prepared)
    assert 150 <= len(features) <= 200
    # Nearest-neighbour spacing is close to the grid spacing sqrt(area / n).
    d = np.linalg.norm(features.xy[:, None] - features.xy[None], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = np.sqrt(400 * 600 / 200)
    assert 0.4 * spacing < np.median(d.min(axis=1)) < 1.2 * spacing


@pytest.mark.parametrize(
    ("name", "descriptor", "max_error_px"),
    [
        ("sift", "rootsift", 2.0),
        ("akaze", "rootsift", 2.0),
        ("orb", "native", 2.0),
        (
            "random-grid",
            "rootsift",
            10.0,
        ),  # grid points are not repeatable: the paper's "acceptable"
    ],
)
def test_register_pair_recovers_the_known_homography(pair, name, descriptor, max_error_px):
    a, b, H_b_to_a = pair
    config = with_overrides(Config(), features={"detector": name, "descriptor": descriptor})
    reg = register_pair(a, b, config, FeatureExtractor(config.features))
    assert reg.ok, reg.reason
    assert reg.n_inliers >= 20
    assert corner_error(reg.H_cur_to_prev, H_b_to_a, (480, 320)) < max_error_px
