import cv2
import numpy as np
import pytest

from mosaic.config import Config, FeaturesConfig, with_overrides
from mosaic.errors import ConfigError, DetectorWeightsError, MosaicError
from mosaic.features import (
    CONTRAST_WINDOW_PX,
    DETECTORS,
    MAX_DETECTOR_SIZE_PX,
    MIN_LOCAL_CONTRAST,
    FeatureExtractor,
    _textured,
    resolve_precision,
)
from mosaic.pairs import register_pair
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
    assert corner_error(reg.H_moving_to_fixed, H_b_to_a, (480, 320)) < max_error_px


def test_detect_scale_maps_points_back_to_frame_pixels():
    """Blobs at known places: found at half resolution, reported at full-resolution positions."""
    import cv2

    rng = np.random.default_rng(4)
    centres = np.stack([rng.uniform(30, 370, 40), rng.uniform(30, 270, 40)], 1).astype(np.float32)
    image = np.full((300, 400), 40, np.uint8)
    for x, y in centres:
        cv2.circle(image, (round(float(x) * 16), round(float(y) * 16)), 5 * 16, 220, -1, shift=4)
    image = cv2.GaussianBlur(image, (0, 0), 2.0)
    prepared = prepare(np.dstack([image] * 3), Config().preprocess)
    prepared.mask[:, 300:] = 0  # the mask is honoured at full resolution
    full = FeatureExtractor(FeaturesConfig(detector="sift")).detect(prepared)
    half = FeatureExtractor(FeaturesConfig(detector="sift", detect_scale=0.5)).detect(prepared)
    assert half.xy[:, 0].max() < 300
    inside = centres[centres[:, 0] < 290]
    for features, tol in ((full, 1.0), (half, 1.5)):
        d = np.linalg.norm(inside[:, None] - features.xy[None], axis=2).min(axis=1)
        assert np.median(d) < tol, np.sort(d)

    # sizes are in frame pixels too: the same blobs have about the same diameter
    def sizes_at_blobs(f):
        return f.sizes[np.linalg.norm(f.xy[:, None] - inside[None], axis=2).min(axis=1) < 2]

    assert 0.7 < np.median(sizes_at_blobs(half)) / np.median(sizes_at_blobs(full)) < 1.4


def test_glampoints_on_a_missing_gpu_is_a_clear_config_error():
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    with pytest.raises(ConfigError, match='device = "cuda"'):
        FeatureExtractor(FeaturesConfig(detector="glampoints", device="cuda"))


def test_glampoints_weights_that_cannot_load_are_the_apps_own_error(tmp_path):
    """The adapter turns glampoints' WeightsError into DetectorWeightsError (a MosaicError,
    what the CLI, batch, evaluate and bench catch), its message kept."""
    missing = tmp_path / "missing.pt"
    with pytest.raises(DetectorWeightsError, match="GLAMpoints weights file not found") as error:
        FeatureExtractor(FeaturesConfig(detector="glampoints", weights=str(missing)))
    assert isinstance(error.value, MosaicError)
    assert type(error.value.__cause__).__name__ == "WeightsError"


def test_glampoints_extra_scale_adds_coarse_points_described_larger(fundus):
    prepared = prepare(fundus[300:900, 300:1100], Config().preprocess)
    prepared.mask[:, :200] = 0
    plain = FeatureExtractor(FeaturesConfig(detector="glampoints")).detect(prepared)
    both = FeatureExtractor(FeaturesConfig(detector="glampoints", extra_scale=0.7)).detect(prepared)
    n = len(plain)
    # the frame's own points come first, unchanged, at the configured descriptor size
    np.testing.assert_array_equal(both.xy[:n], plain.xy)
    size = FeaturesConfig().descriptor_size_px
    np.testing.assert_allclose(both.sizes[:n], size)
    extra = both.xy[n:]
    assert len(extra) > 0.3 * n  # the 0.7x copy has about half the area: fewer points
    np.testing.assert_allclose(both.sizes[n:], size / 0.7, rtol=1e-5)
    assert extra[:, 0].min() >= 200 - 2  # the mask holds for them too (to a pixel)
    # coarse points sit where the fine map also responds: most have a fine point within 3 px
    d = np.linalg.norm(extra[:, None] - plain.xy[None], axis=2).min(axis=1)
    assert np.median(d) < 3.0, np.median(d)


@pytest.mark.both_precisions
def test_glampoints_extra_scale_registers_a_zoomed_pair(fundus):
    """Views 1.6x apart in magnification: the coarse points carry the registration."""
    H_b_to_a = similarity(3.0, 1.6, 10.0, -5.0, center=(240, 160))
    a, b = crop_pair(fundus, H_b_to_a, origin=(450, 500), size=(480, 320))
    regs = {}
    for extra in (0.0, 0.7):
        config = with_overrides(Config(), features={"detector": "glampoints", "extra_scale": extra})
        regs[extra] = register_pair(a, b, config, FeatureExtractor(config.features))
    assert regs[0.7].ok, regs[0.7].reason
    assert corner_error(regs[0.7].H_moving_to_fixed, H_b_to_a, (480, 320)) < 3.0
    assert regs[0.7].n_inliers > 2 * regs[0.0].n_inliers  # measured: 200 vs 59


def test_detector_scales_are_kept_up_to_a_cap_whatever_the_scale_free_size(fundus):
    """SIFT describes at its own scales (capped at MAX_DETECTOR_SIZE_PX); the configured size
    is only for detectors without a scale, so changing it leaves SIFT's features alone."""
    prepared = prepare(fundus[300:900, 300:1100], Config().preprocess)
    small = FeatureExtractor(FeaturesConfig(detector="sift", descriptor_size_px=4.0))(prepared)
    large = FeatureExtractor(FeaturesConfig(detector="sift", descriptor_size_px=30.0))(prepared)
    np.testing.assert_array_equal(small.sizes, large.sizes)
    np.testing.assert_array_equal(small.descriptors, large.descriptors)
    assert small.sizes.max() <= MAX_DETECTOR_SIZE_PX
    assert np.ptp(small.sizes) > 2.0  # real scales, not one value


@pytest.mark.parametrize(
    ("precision", "device", "native", "expected"),
    [
        ("auto", "cpu", True, "bfloat16"),
        ("auto", "cpu", False, "float32"),  # emulated bfloat16 is slower than float32
        ("auto", "cuda", True, "float32"),
        ("float32", "cpu", True, "float32"),
        ("bfloat16", "cpu", False, "bfloat16"),  # asked for explicitly: honoured
    ],
)
def test_glampoints_precision_auto_takes_bfloat16_only_where_the_cpu_has_it(
    precision, device, native, expected
):
    config = FeaturesConfig(detector="glampoints", precision=precision, device=device)
    assert resolve_precision(config, native) == expected


def test_glampoints_precision_reaches_the_network():
    extractor = FeatureExtractor(FeaturesConfig(detector="glampoints", precision="bfloat16"))
    assert extractor.detector._model.precision == "bfloat16"


def test_register_pair_of_large_images_answers_in_full_size_pixels(pair):
    """Images larger than the working size register downscaled; the homography is still the
    full-size one (here: both images 2x, registered at 0.5)."""
    a, b, H_b_to_a = pair
    big_a, big_b = (cv2.resize(x, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC) for x in (a, b))
    S = np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])  # small -> big pixel centres
    H_big = S @ H_b_to_a @ np.linalg.inv(S)
    config = with_overrides(
        Config(), features={"detector": "sift"}, preprocess={"max_side_px": 480}
    )
    reg = register_pair(big_a, big_b, config, FeatureExtractor(config.features))
    assert reg.ok, reg.reason
    assert corner_error(reg.H_moving_to_fixed, H_big, (960, 640)) < 4.0  # 2 px at the small size


@pytest.mark.parametrize("name", ["glampoints", "random-grid"])
def test_blank_images_do_not_register(fundus, name):
    """A flat image has nothing to match: two of them (or one and a retina) must fail, not
    "register" with the identity through their identical descriptors of quantisation noise."""
    config = with_overrides(Config(), features={"detector": name})
    extractor = FeatureExtractor(config.features)
    black = np.zeros((300, 300, 3), np.uint8)
    grey = np.full((300, 300, 3), 128, np.uint8)
    assert len(extractor(prepare(black, config.preprocess))) == 0
    assert len(extractor(prepare(grey, config.preprocess))) == 0
    for a, b, blank in (
        (black, black, "fixed and moving images"),
        (grey, black, "fixed and moving images"),
        (fundus, grey, "moving image"),
    ):
        registration = register_pair(a, b, config, extractor)
        assert not registration.ok and registration.H_moving_to_fixed is None
        assert registration.reason == f"no textured keypoints in the {blank}"
    # the retina itself keeps its points
    assert len(extractor(prepare(fundus, config.preprocess))) > 100


@pytest.mark.parametrize("shape", [(350, 660), (40, 33), (5, 5), (1, 7)])
def test_textured_equals_the_variance_of_the_blurred_float_image(shape):
    """`_textured` sums the window in integers; it must decide exactly as the float32 local
    variance `blur(g^2) - blur(g)^2` (cv2.blur, reflected borders) that it replaces."""
    rng = np.random.default_rng(sum(shape))
    gray = rng.integers(0, 256, shape, dtype=np.uint8)
    gray[: shape[0] // 2] //= 64  # low-contrast rows: variances near the threshold
    gray[:, : shape[1] // 3] = 255  # a flat, saturated band
    h, w = shape
    xy = np.stack([rng.uniform(-2, w + 1, 500), rng.uniform(-2, h + 1, 500)], 1).astype("f4")
    g = gray.astype(np.float32)
    k = (CONTRAST_WINDOW_PX, CONTRAST_WINDOW_PX)
    var = cv2.blur(g * g, k) - cv2.blur(g, k) ** 2
    ix = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
    iy = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
    expected = var[iy, ix] >= MIN_LOCAL_CONTRAST**2
    assert 0 < expected.sum() < len(xy) or min(shape) < 100  # both sides of the threshold
    np.testing.assert_array_equal(_textured(gray, xy), expected)


@pytest.mark.both_precisions
def test_keypoints_keep_off_the_view_border_that_is_fixed_to_the_camera(fundus):
    """A faint, blurred view of the retina moved 11 px under a fixed aperture: the structure
    that matches best is the aperture's border, which has not moved. Keypoints up to the
    border (margin 0) give matches that stand still and registrations pulled towards zero
    motion; with the default margin no keypoint lies within 12 px of the mask's edge, the
    still matches are at most half as many and the registrations follow the retina.

    The scene is faint on purpose, so one noise draw's registration swings by pixels with the
    CPU and precision: the claims are over six draws. "Pulled" and "follows" are measured
    against half the motion (11 px): nearer the border's zero motion or the retina's. The
    points are dropped after detection: those left are the margin-0 points, not weaker ones."""
    from mosaic.matching import match_descriptors
    from mosaic.registration import estimate_motion

    big = cv2.resize(fundus, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_CUBIC)
    a, b = crop_pair(big, similarity(0.0, 1.0, 11.0, -5.0), origin=(900, 1100), size=(660, 350))
    aperture = np.zeros(a.shape[:2], np.uint8)
    cv2.ellipse(aperture, (330, 175), (320, 170), 0, 0, 360, 255, -1)
    config = Config()
    margins = (0.0, config.features.border_margin_px)
    extractors = {
        m: FeatureExtractor(with_overrides(config, features={"border_margin_px": m}).features)
        for m in margins
    }
    errors: dict[float, list[float]] = {m: [] for m in margins}
    still: dict[float, int] = dict.fromkeys(margins, 0)
    for draw in range(6):
        views = []
        for seed, image in enumerate((a, b)):
            g = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 4.5) * 0.3
            g += np.random.default_rng(2 * draw + seed).normal(0, 4, g.shape)
            g[aperture == 0] = 4
            views.append(prepare(np.clip(g, 0, 255).astype(np.uint8), config.preprocess))
        for margin, extractor in extractors.items():
            fa, fb = extractor(views[0]), extractor(views[1])
            m = match_descriptors(fa.descriptors, fb.descriptors, config.matching)
            still[margin] += int(
                (np.linalg.norm(fa.xy[m.idx_a] - fb.xy[m.idx_b], axis=1) < 2).sum()
            )
            reg = estimate_motion(fb.xy[m.idx_b], fa.xy[m.idx_a], config.registration, (350, 660))
            # refused by the failure rules: not pulled (nan, left out of the mean)
            error = np.abs(reg.H_moving_to_fixed[:2, 2] - [11.0, -5.0]).max() if reg.ok else np.nan
            errors[margin].append(float(error))
            if draw == 0:
                if margin == 0:
                    fa_0 = fa
                else:
                    inside = cv2.distanceTransform(np.pad(views[0].mask, 1), cv2.DIST_L2, 5)
                    xi, yi = np.round(fa.xy).astype(int).T
                    # no point within the margin of the mask's edge (a pixel's rounding)
                    assert inside[1:-1, 1:-1][yi, xi].min() >= margin - 1
                    # dropped after detection: the same strongest points, not weaker ones
                    kept = (np.abs(fa.xy[:, None] - fa_0.xy[None]).max(axis=2) == 0).any(axis=1)
                    assert kept.all() and len(fa) < len(fa_0)
    half = 11.0 / 2
    assert np.nanmean(errors[0.0]) > half, errors  # without the margin: pulled to the border
    assert np.isfinite(errors[margins[1]]).sum() >= 3, errors  # with it: mostly registered,
    assert np.nanmean(errors[margins[1]]) < half, errors  # and following the retina
    assert still[margins[1]] <= still[0.0] / 2, still
