import cv2
import numpy as np
import pytest

from glampoints.synthetic import frame_preprocess
from mosaic.camera_fixed import OverlayMask, ReflexMask, SurroundMask
from mosaic.config import PreprocessConfig
from mosaic.preprocess import (
    Deinterlacer,
    Prepared,
    erode_by_disc,
    field_of_view_mask,
    field_offset,
    first_field,
    invert_in_view,
    inverted_as,
    pair_polarities,
    prepare,
    retina_disc,
    to_working_size,
    vessel_polarity,
    working_scale,
)


def _disc_frame(h=200, w=300, radius=80):
    frame = np.zeros((h, w, 3), np.uint8)
    cv2.circle(frame, (w // 2, h // 2), radius, (40, 120, 200), -1)
    # A dark vessel crossing the disc must stay inside the view.
    cv2.line(frame, (w // 2 - 60, h // 2), (w // 2 + 60, h // 2), (5, 5, 5), 5)
    return frame


def test_fov_mask_is_the_disc_minus_the_erosion_margin():
    frame = _disc_frame()
    mask = field_of_view_mask(frame[:, :, 1], threshold=12, erode_px=6)
    yy, xx = np.mgrid[:200, :300]
    r = np.hypot(xx - 150, yy - 100)
    assert mask[r < 70].min() == 255  # inside, vessel included
    assert mask[r > 78].max() == 0  # border and erosion margin excluded
    assert mask[100, 150] == 255  # on the dark vessel


def test_fov_mask_of_an_under_exposed_view_is_the_view_not_its_vessels():
    """A dark view (a dark photograph at low gain: the retina at grey ~5, its vessels at ~14,
    the black border at ~2, sensor noise) is below the usual border threshold; its mask is
    still the view (its frames were skipped for "too little field of view" although their
    vessels were visible). A blank frame's mask stays as before."""
    rng = np.random.default_rng(1)
    h, w = 200, 300
    frame = np.full((h, w), 2.0, np.float32)
    cv2.circle(frame, (w // 2, h // 2), 80, 5.0, -1)
    for y in (70, 100, 130):  # bright vessels inside the view
        cv2.line(frame, (w // 2 - 60, y), (w // 2 + 60, y + 10), 14.0, 3)
    noisy = np.clip(frame + rng.normal(0, 2.0, frame.shape), 0, 255).astype(np.uint8)
    yy, xx = np.mgrid[:h, :w]
    r = np.hypot(xx - w / 2, yy - h / 2)
    mask = field_of_view_mask(noisy, threshold=12, erode_px=6) > 0
    assert mask[r < 60].mean() > 0.95  # the view, not only its vessels
    assert mask[r > 90].mean() < 0.02  # the border stays out
    blank = np.clip(2.0 + rng.normal(0, 2.0, (h, w)), 0, 255).astype(np.uint8)
    assert field_of_view_mask(blank, threshold=12, erode_px=6).all()  # no view: all, as before


def test_prepare_uses_green_channel_and_enhances():
    frame = _disc_frame()
    config = PreprocessConfig(clahe=False, bilateral=False)
    prepared = prepare(frame, config)
    assert prepared.gray[70, 150] == 120  # green channel of (B, G, R) = (40, 120, 200)
    luma = prepare(frame, PreprocessConfig(green_channel=False, clahe=False, bilateral=False))
    assert luma.gray[70, 150] == round(0.114 * 40 + 0.587 * 120 + 0.299 * 200)


def test_clahe_raises_local_contrast():
    rng = np.random.default_rng(0)
    low = (100 + rng.normal(0, 3, (128, 128))).clip(0, 255).astype(np.uint8)
    frame = np.dstack([low] * 3)
    plain = prepare(frame, PreprocessConfig(clahe=False, bilateral=False, fov_mask=False))
    enhanced = prepare(frame, PreprocessConfig(bilateral=False, fov_mask=False))
    assert enhanced.gray.std() > 2 * plain.gray.std()
    assert plain.mask.min() == 255


def test_bilateral_reduces_noise():
    rng = np.random.default_rng(1)
    noisy = (128 + rng.normal(0, 10, (128, 128))).clip(0, 255).astype(np.uint8)
    frame = np.dstack([noisy] * 3)
    out = prepare(frame, PreprocessConfig(clahe=False, fov_mask=False, bilateral_sigma_color=50.0))
    assert out.gray.astype(float).std() < 0.6 * noisy.astype(float).std()


def test_training_sees_the_apps_default_preprocessing():
    """GLAMpoints is trained on `frame_preprocess` crops: it must equal the app's defaults."""
    rng = np.random.default_rng(3)
    grey = cv2.GaussianBlur(rng.integers(0, 256, (120, 160), dtype=np.uint8), (0, 0), 2.0)
    bgr = np.dstack([grey // 2, grey, grey // 3])
    np.testing.assert_array_equal(prepare(bgr, PreprocessConfig()).gray, frame_preprocess(grey))


def test_overlay_mask_removes_a_static_cross_but_not_a_static_camera():
    rng = np.random.default_rng(0)
    config = PreprocessConfig()
    moving, still = OverlayMask(config), OverlayMask(config)
    base = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), dtype=np.uint8), (0, 0), 3)
    for k in range(OverlayMask.MIN_FRAMES):
        frame = np.roll(base, 3 * k, axis=1)  # the view moves ...
        cv2.rectangle(frame, (150, 90), (170, 150), 0, -1)  # ... a burned-in cross does not
        cv2.rectangle(frame, (130, 110), (190, 130), 0, -1)
        bgr = np.dstack([frame] * 3)
        masked = moving(bgr, prepare(bgr, config))
        unmoved = still(np.dstack([base] * 3), prepare(np.dstack([base] * 3), config))
    cross = np.zeros((240, 320), bool)
    cross[90:151, 150:171] = cross[110:131, 130:191] = True
    assert (masked.mask[cross] == 0).all()  # the cross and its margin are out
    assert (masked.mask[:, :100] == 255).mean() > 0.99  # the moving retina stays in
    ring = cv2.dilate(cross.view(np.uint8), np.ones((25, 25), np.uint8)).astype(bool) & ~cross
    assert 0.2 < (masked.mask[ring] == 0).mean() < 0.8  # a margin of ~6 px, not more
    # a camera that does not move: everything is static, nothing is masked
    np.testing.assert_array_equal(unmoved.mask, prepare(np.dstack([base] * 3), config).mask)


def _retina_and_box(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A random texture standing in for retina (240x320) and a 40x60 box in its middle."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), dtype=np.uint8), (0, 0), 3)
    box = np.zeros((240, 320), bool)
    box[100:140, 140:200] = True
    return base, box


def test_overlay_mask_follows_an_overlay_that_goes_away():
    """Static until frame 9, then the box shows retina: once re-searched, it is no overlay."""
    config = PreprocessConfig()
    overlay = OverlayMask(config)
    base, box = _retina_and_box(1)
    masked_per_frame = []
    for k in range(OverlayMask.MIN_FRAMES + 2 * OverlayMask.REFRESH_FRAMES):
        frame = np.roll(base, 3 * k, axis=1)
        if k < 10:
            frame[box] = 255
        bgr = np.dstack([frame] * 3)
        masked_per_frame.append(bool((overlay(bgr, prepare(bgr, config)).mask[box] == 0).all()))
    assert masked_per_frame[OverlayMask.MIN_FRAMES - 1 : 10] == [True] * (
        11 - OverlayMask.MIN_FRAMES
    )
    assert not any(masked_per_frame[-OverlayMask.REFRESH_FRAMES :])  # re-searched since


def test_overlay_mask_ignores_a_static_patch_that_looks_like_its_surroundings():
    """A flat patch of retina that a slow view has not moved over yet is static too; unlike a
    drawn overlay it has the grey of what surrounds it, so it keeps its keypoints."""
    config = PreprocessConfig()
    overlay = OverlayMask(config)
    base, box = _retina_and_box(2)
    for k in range(OverlayMask.MIN_FRAMES + 1):
        frame = np.roll(base, 3 * k, axis=1)
        frame[box] = round(float(np.mean(base)))  # flat, static, the retina's mean grey
        bgr = np.dstack([frame] * 3)
        prepared = prepare(bgr, config)
        masked = overlay(bgr, prepared)
    np.testing.assert_array_equal(masked.mask, prepared.mask)


def test_working_size_keeps_small_frames_and_maps_pixel_centres_of_large_ones():
    image = np.zeros((300, 400, 3), np.uint8)
    same, H = to_working_size(image, 800)
    assert same is image and H is None
    assert to_working_size(image, 0)[1] is None  # off
    small, H = to_working_size(np.zeros((600, 1000, 3), np.uint8), 500)
    assert small.shape == (300, 500, 3)
    # the centre of pixel (0, 0) and of the last pixel map to the centres of the small ones' span
    corners = np.array([[-0.5, -0.5, 1], [999.5, 599.5, 1]]) @ H.T
    np.testing.assert_allclose(corners[:, :2], [[-0.5, -0.5], [499.5, 299.5]])


def _fundus(h: int, w: int, cx: float, cy: float, r: float, seed: int = 0) -> np.ndarray:
    """A textured bright disc (clipped by the image where it runs out) on black."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(60, 200, (h, w)).astype(np.float32), (0, 0), 3)
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.where(np.hypot(xx - cx, yy - cy) <= r, tex, 0).astype(np.uint8)
    return cv2.merge([img // 2, img, img // 2])


def test_retina_disc_recovers_the_field_of_view_disc_also_clipped_at_top_and_bottom():
    for h, w, cx, cy, r in [(900, 1000, 480.0, 450.0, 400.0), (1100, 1400, 700.0, 550.0, 640.0)]:
        disc = retina_disc(_fundus(h, w, cx, cy, r))
        assert disc is not None
        assert abs(disc[0] - cx) < 0.01 * r and abs(disc[1] - cy) < 0.01 * r
        assert abs(disc[2] - r) < 0.01 * r


def test_retina_disc_of_a_dark_photograph_whose_rim_is_a_few_grey_levels_above_black():
    """An under-exposed photograph (strong vignetting, its rim at grey 7-12 over a black border
    with noise): the disc is still the whole retina, not the brighter middle."""
    h = w = 1000
    img = _fundus(h, w, 500.0, 500.0, 460.0).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    rho = np.hypot(xx - 500, yy - 500) / 460
    dark = img * 0.3 * (1 - 0.75 * np.clip(rho, 0, 1) ** 2)[..., None]
    dark += np.random.default_rng(1).normal(0, 1.5, dark.shape)
    dark = np.clip(dark, 0, 255).astype(np.uint8)
    assert np.median(dark[..., 1][(rho > 0.95) & (rho < 1)]) < 12
    disc = retina_disc(dark)
    assert disc is not None
    assert abs(disc[2] - 460) < 0.02 * 460 and abs(disc[0] - 500) < 0.01 * 460


def test_a_pair_of_the_same_size_shares_the_scale_of_the_one_whole_retina():
    """Two photographs from one camera, the disc of one missed (its border lit on three sides):
    both are brought to the found retina's scale; different sizes keep their own scales."""
    from mosaic.preprocess import pair_working_scales

    a = _fundus(1000, 1000, 500.0, 500.0, 460.0)
    b = _fundus(1000, 1000, 500.0, 500.0, 460.0, seed=1)
    yy, xx = np.mgrid[0:1000, 0:1000]
    outside = (np.hypot(xx - 500, yy - 500) > 460) & (xx < 800)
    b[outside] = 120
    assert retina_disc(a) is not None and retina_disc(b) is None
    s_a, s_b = pair_working_scales(a, b, 800, 512)
    assert s_a == pytest.approx(512 / 920, rel=0.02) and s_b == s_a
    assert pair_working_scales(b, a, 800, 512) == (s_a, s_a)
    small = cv2.resize(b, (700, 700))
    assert pair_working_scales(a, small, 800, 512) == (s_a, 1.0)


def test_retina_disc_is_none_for_frames_bright_to_their_edges_or_showing_a_bit_of_rim():
    rng = np.random.default_rng(0)
    bright = cv2.GaussianBlur(rng.uniform(60, 200, (350, 660)).astype(np.uint8), (0, 0), 3)
    assert retina_disc(bright) is None
    rim = _fundus(350, 660, 330.0, 900.0, 800.0)  # a magnified view near the rim
    assert retina_disc(rim) is None


def test_working_size_brings_the_retina_to_the_trained_diameter_and_else_falls_back():
    big = _fundus(2000, 2000, 1000.0, 1000.0, 900.0)
    assert abs(working_scale(big, 800, 480) - 480 / 1800) < 0.01 * 480 / 1800
    small, S = to_working_size(big, 800, 480)
    assert abs(small.shape[0] - 2000 * 480 / 1800) <= 6 and S is not None
    assert working_scale(big, 800, 0) == 800 / 2000  # rule off: the longer side
    rng = np.random.default_rng(1)
    frame = cv2.GaussianBlur(rng.uniform(60, 200, (700, 1320)).astype(np.uint8), (0, 0), 3)
    assert working_scale(frame, 800, 480) == 800 / 1320  # no disc: max_side_px
    assert working_scale(_fundus(400, 400, 200.0, 200.0, 190.0), 800, 480) == 1.0  # never up


@pytest.mark.parametrize("radius", [1, 6, 8, 17])
def test_erode_by_disc_keeps_what_lies_that_far_inside_the_mask(radius):
    """The pixels kept are those at least `radius` (within a pixel's rounding) from the nearest
    pixel outside the mask, by the exact Euclidean distance; with `edge_counts` the image's
    edge is outside too, without it the mask goes on beyond the edge."""
    h, w = 120, 160
    mask = np.full((h, w), 255, np.uint8)
    cv2.circle(mask, (40, 60), 25, 0, -1)
    cv2.rectangle(mask, (100, 10), (150, 30), 0, -1)
    for edge_counts in (False, True):
        kept = erode_by_disc(mask, radius, edge_counts=edge_counts) > 0
        padded = np.pad(mask, 1, constant_values=0 if edge_counts else 255)
        distance = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
        assert (distance[kept] >= radius - 0.5).all()
        assert kept[distance >= radius + 1.0].all()
    assert (erode_by_disc(mask, 0) == mask).all()
    assert erode_by_disc(np.full((h, w), 255, np.uint8), radius).all()


def test_vessel_polarity_tells_a_colour_photograph_from_its_negative():
    """The shipped colour photograph shows dark vessels (polarity above 1); its negative inside
    the view (an angiogram's bright vessels) below 1. Only a pair of opposite polarities is
    inverted, and then the bright-vessel one; the black border stays black."""
    from tests.conftest import SAMPLE_IMAGE

    photo = cv2.imread(str(SAMPLE_IMAGE), cv2.IMREAD_COLOR)
    negative = invert_in_view(photo)
    assert vessel_polarity(photo) > 1.15 and vessel_polarity(negative) < 0.85
    h, w = photo.shape[:2]
    assert negative[:5, :5].max() <= photo[:5, :5].max()  # the border is not made white
    centre = photo[h // 2 - 5 : h // 2 + 5, w // 2 - 5 : w // 2 + 5]
    assert np.array_equal(negative[h // 2 - 5 : h // 2 + 5, w // 2 - 5 : w // 2 + 5], 255 - centre)
    assert pair_polarities(photo, photo) == (False, False)
    assert pair_polarities(negative, negative) == (False, False)
    assert pair_polarities(photo, negative) == (False, True)
    assert pair_polarities(negative, photo) == (True, False)
    fixed, moving = inverted_as(photo, negative, (False, True))
    assert fixed is photo
    inside = field_of_view_mask(photo[:, :, 1], 15, 0) > 0
    assert np.array_equal(moving[inside], photo[inside])  # the negative made positive again


def _texture(seed: int = 0, shape: tuple[int, int] = (600, 800)) -> np.ndarray:
    """A smooth random texture (BGR uint8): what a frame's fields are compared on."""
    noise = np.random.default_rng(seed).normal(0, 60, shape).astype(np.float32)
    grey = np.clip(cv2.GaussianBlur(noise, (0, 0), 3) + 128, 0, 255).astype(np.uint8)
    return cv2.merge([grey, grey, grey])


def _interlaced(scene: np.ndarray, shift: tuple[float, float], origin=(150, 120), size=(300, 400)):
    """(progressive frame, the same frame interlaced: its odd rows from a view moved by
    `shift` px, as an interlaced camera's second field of a moving view)."""
    (x0, y0), (h, w) = origin, size
    first = np.ascontiguousarray(scene[y0 : y0 + h, x0 : x0 + w])
    move = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])  # content moves by shift
    second = cv2.warpAffine(scene, move, (scene.shape[1], scene.shape[0]))
    combed = first.copy()
    combed[1::2] = second[y0 : y0 + h, x0 : x0 + w][1::2]
    return first, combed


@pytest.mark.parametrize("shift", [(6.0, 4.0), (-3.0, 8.0), (2.5, -1.0), (0.0, 0.0)])
def test_field_offset_measures_the_second_fields_motion(shift):
    first, combed = _interlaced(_texture(), shift)
    np.testing.assert_allclose(field_offset(combed), shift, atol=0.25)
    assert np.hypot(*field_offset(first)) < 0.3  # progressive: the fields agree


def test_field_offset_of_a_large_frame_is_measured_about_its_centre():
    """A 1920x1080 frame's fields are compared on their middle 384x384 (field px) alone: the
    same offset, a fraction of the work."""
    scene = _texture(2, (1200, 2100))
    first, combed = _interlaced(scene, (5.0, -3.0), origin=(90, 60), size=(1080, 1920))
    np.testing.assert_allclose(field_offset(combed), (5.0, -3.0), atol=0.25)
    assert np.hypot(*field_offset(first)) < 0.3


def test_first_field_keeps_the_even_rows_and_interpolates_the_odd_ones():
    first, combed = _interlaced(_texture(), (6.0, 4.0))
    out = first_field(combed)
    assert out.shape == combed.shape and out.dtype == combed.dtype
    assert np.array_equal(out[0::2], combed[0::2])
    inner = (slice(10, -10), slice(10, -10))
    # the odd rows come back to the first field's view: combed by the second field before
    assert np.abs(out[inner].astype(int) - first[inner]).mean() < 1.0
    assert np.abs(combed[inner].astype(int) - first[inner]).mean() > 2
    np.testing.assert_array_equal(out[-1], out[-2])  # the last odd row copies its neighbour


def test_field_aligner_deinterlaces_when_on_and_tells_an_interlaced_video_when_off():
    scene = _texture(1)
    on, off, progressive = Deinterlacer(on=True), Deinterlacer(), Deinterlacer()
    for i in range(6):
        step = (6.0 + i % 3, 4.0 - 2 * (i % 2))
        first, combed = _interlaced(scene, step, origin=(150 + 10 * i, 120))
        out, deinterlaced = on(combed)
        assert deinterlaced and np.array_equal(out, first_field(combed))
        assert off(combed) == (combed, False)  # off: measured, untouched
        assert progressive(first) == (first, False)
    assert off.looks_interlaced and off.median_offset_px > 5
    assert not progressive.looks_interlaced and progressive.median_offset_px < 0.3


def test_reflex_mask_removes_a_bright_spot_fixed_in_the_frame_not_one_on_the_retina():
    """Over a moving retina: a bright spot that stays at one place of the frame (wandering
    1 px, flickering) leaves the keypoint mask with a margin; an equally bright spot carried by
    the retina, a bright vessel the view moves along (at the same pixels in every frame, but a
    line), the rest of the view and a frame before the window is full stay in."""
    config = PreprocessConfig(overlay_mask=False)
    reflexes = ReflexMask(config)
    rng = np.random.default_rng(1)
    retina = cv2.GaussianBlur(rng.integers(60, 140, (240, 720), dtype=np.uint8), (0, 0), 3)
    cv2.circle(retina, (250, 150), 9, 250, -1)  # a bright spot of the retina (an exudate)
    cv2.line(retina, (100, 200), (330, 200), 250, 7)  # a bright vessel the view moves along
    n = ReflexMask.WINDOW + ReflexMask.STEADY_FRAMES
    for k in range(n):
        frame = retina[:, 8 * k : 8 * k + 320].copy()  # the retina moves 8 px a frame
        cv2.circle(frame, (200 + k % 2, 100), 8, int(230 + 10 * (k % 3)), -1)  # lens reflex
        bgr = np.dstack([frame] * 3)
        prepared = prepare(bgr, config)
        masked = reflexes(bgr, prepared)
        if k < n - 1:  # not yet seen long enough
            np.testing.assert_array_equal(masked.mask, prepared.mask)
    yy, xx = np.mgrid[0:240, 0:320]
    distance = np.hypot(xx - 200.5, yy - 100)
    assert (masked.mask[distance <= 8 + 4] == 0).all()  # the reflex and a margin
    grown = 8 + 1 + config.overlay_margin_px + ReflexMask.REACH_PX
    assert (masked.mask[distance > grown + 2] > 0).all()
    spot = np.hypot(xx - (250 - 8 * (n - 1)), yy - 150) <= 12
    assert (masked.mask[spot] > 0).all()  # in the view, and kept
    # what the re-render gets back: the same pixels, from a few hundred bytes
    assert reflexes.found is not None and len(reflexes.found.bits) < 1000
    np.testing.assert_array_equal(reflexes.found.removed_from(prepared.mask), masked.mask)
    off = ReflexMask(PreprocessConfig(overlay_mask=False, reflex_mask=False))
    assert (off(bgr, prepared).mask == prepared.mask).all()


def _aperture_frame(rng, surround=2, contrast=1.0, band_px=0, h=120, w=200):
    """A textured retina inside a dark elliptical aperture fixed to the camera (`surround`:
    the grey outside it: dark, or lifted by haze); `band_px`: the retina's own black border
    (moving with it) covering the frame's left columns."""
    retina = 150 + contrast * rng.normal(0, 20, (h, w))
    frame = np.full((h, w), float(surround))
    yy, xx = np.mgrid[:h, :w]
    inside = ((xx - w / 2) / (0.45 * w)) ** 2 + ((yy - h / 2) / (0.45 * h)) ** 2 < 1
    frame[inside] = retina[inside]
    frame[:, :band_px] = np.where(inside[:, :band_px], 2.0, frame[:, :band_px])
    return Prepared(np.clip(frame, 0, 255).astype(np.uint8), _mask_of(frame))


def _mask_of(frame):
    return field_of_view_mask(np.clip(frame, 0, 255).astype(np.uint8), threshold=12, erode_px=6)


def test_a_surround_lifted_by_haze_is_taken_out_and_a_dark_border_moving_with_the_retina_is_not():
    rng = np.random.default_rng(0)
    surround = SurroundMask(PreprocessConfig())
    clear = [_aperture_frame(rng) for _ in range(8)]
    for frame in clear:  # the camera's surround learned; clear frames left as they are
        np.testing.assert_array_equal(surround(frame).mask, frame.mask)
        assert surround.lifted is None
    always_outside = np.all([frame.mask == 0 for frame in clear], axis=0)
    assert always_outside.mean() > 0.25  # the aperture's surround
    for _ in range(5):  # haze lifts the surround to grey: the frame's own mask covers it all
        hazy = _aperture_frame(rng, surround=110, contrast=0.3)
        assert hazy.mask.min() == 255
        mask = surround(hazy).mask
        assert mask[always_outside].max() == 0  # the surround out
        assert mask[clear[-1].mask > 0].min() == 255  # the last clear frame's view in
        assert surround.lifted is not None
    clear_again = _aperture_frame(rng)
    np.testing.assert_array_equal(surround(clear_again).mask, clear_again.mask)
    # a camera that starts on the retina's black border and leaves it: no frame is changed
    moving = SurroundMask(PreprocessConfig())
    for band in [60] * 6 + [50, 30, 10, 0, 0]:
        frame = _aperture_frame(rng, band_px=band)
        np.testing.assert_array_equal(moving(frame).mask, frame.mask)
        assert moving.lifted is None


def test_a_surround_lifted_for_good_is_a_new_view():
    rng = np.random.default_rng(1)
    surround = SurroundMask(PreprocessConfig())
    for _ in range(SurroundMask.MIN_FRAMES):
        surround(_aperture_frame(rng))
    for _ in range(SurroundMask.MAX_LIFTED):
        surround(_aperture_frame(rng, surround=110))
        assert surround.lifted is not None
    new_view = _aperture_frame(rng, surround=110)  # one more: the history starts again
    np.testing.assert_array_equal(surround(new_view).mask, new_view.mask)
    assert surround.lifted is None
    off = SurroundMask(PreprocessConfig(surround_mask=False))
    for _ in range(SurroundMask.MIN_FRAMES):
        off(_aperture_frame(rng))
    hazy = _aperture_frame(rng, surround=110)
    np.testing.assert_array_equal(off(hazy).mask, hazy.mask)
