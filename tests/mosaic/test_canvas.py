"""Mosaic canvas: placement, growth, blending and the size cap, against synthetic ground truth."""

from __future__ import annotations

import itertools
import logging
import math

import cv2
import numpy as np
import pytest

from mosaic.canvas import PICTURE_THREADS, Canvas
from mosaic.config import ComposeConfig
from mosaic.errors import CanvasLimitError
from mosaic.preprocess import scale_matrix

BLENDS = ("feather", "average", "last")


def translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def similarity(angle_deg: float, scale: float, tx: float, ty: float) -> np.ndarray:
    a = math.radians(angle_deg)
    c, s = scale * math.cos(a), scale * math.sin(a)
    return np.array([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]])


def random_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def smooth_field(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Smooth 3-channel test pattern (float, within [30, 225]) at arbitrary coordinates."""
    r = 128 + 60 * np.sin(xs / 17.0) * np.cos(ys / 23.0) + 0.1 * xs
    g = 128 + 70 * np.cos((xs + ys) / 29.0)
    b = 128 + 50 * np.sin(ys / 13.0) + 0.15 * ys
    return np.stack([r, g, b], axis=-1)


def smooth_tile(x0: float, y0: float, h: int, w: int) -> np.ndarray:
    """uint8 tile whose pixel (x, y) shows the smooth pattern at (x0 + x, y0 + y)."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.clip(np.rint(smooth_field(xs + x0, ys + y0)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("blend", BLENDS)
def test_identity_renders_the_frame_exactly(blend: str) -> None:
    image = random_image(60, 80)
    canvas = Canvas(ComposeConfig(blend=blend))
    assert canvas.shape == (0, 0) and canvas.n_frames == 0
    assert canvas.render().shape == (0, 0, 3)

    canvas.add(image, np.eye(3))

    assert canvas.shape == (60, 80)
    assert canvas.n_frames == 1
    np.testing.assert_array_equal(canvas.H_ref_to_canvas, np.eye(3))
    np.testing.assert_array_equal(canvas.render(), image)
    assert canvas.coverage().dtype == np.uint8
    assert np.all(canvas.coverage() == 255)


@pytest.mark.parametrize("blend", BLENDS)
def test_single_channel_tiles(blend: str) -> None:
    base = random_image(60, 90)[..., 1].copy()
    canvas = Canvas(ComposeConfig(blend=blend), channels=1)
    canvas.add(base[:, 30:], np.eye(3))
    np.testing.assert_array_equal(canvas.render()[..., 0], base[:, 30:])
    canvas.add(base[:, :50], translation(-30, 0))
    out = canvas.render()
    assert out.shape == (60, 90, 1)
    np.testing.assert_array_equal(out[..., 0], base)
    with pytest.raises(ValueError, match="channel"):
        canvas.add(random_image(60, 90), np.eye(3))


@pytest.mark.parametrize("blend", BLENDS)
def test_integer_tiles_reassemble_image_and_grow_up_left(blend: str) -> None:
    base = random_image(120, 160, seed=1)
    ref = base[40:120, 50:160]  # reference frame: top-left at base (50, 40)
    tile = base[0:80, 0:110]  # lies at (-50, -40) in reference coords
    canvas = Canvas(ComposeConfig(blend=blend))
    canvas.add(ref, np.eye(3))
    canvas.add(tile, translation(-50, -40))

    assert canvas.shape == (120, 160)
    np.testing.assert_array_equal(canvas.H_ref_to_canvas, translation(50, 40))
    expected_cov = np.zeros((120, 160), bool)
    expected_cov[40:120, 50:160] = True
    expected_cov[0:80, 0:110] = True
    np.testing.assert_array_equal(canvas.coverage() > 0, expected_cov)
    out = canvas.render().astype(np.int16)
    err = np.abs(out - base.astype(np.int16))
    assert err[expected_cov].max() < 1
    assert np.all(out[~expected_cov] == 0)


@pytest.mark.parametrize("blend", ["average", "feather"])
def test_subpixel_tiles_reconstruct_smooth_image(blend: str) -> None:
    # Reference tile shows the pattern from (0, 0); the second from (-50.5, -40.25), so it sits
    # at that (sub-pixel) translation in reference coords and must be resampled bilinearly.
    h, w = 90, 120
    canvas = Canvas(ComposeConfig(blend=blend, feather_px=15))
    canvas.add(smooth_tile(0.0, 0.0, h, w), np.eye(3))
    canvas.add(smooth_tile(-50.5, -40.25, h, w), translation(-50.5, -40.25))

    # Union bbox: x in [-50.5, 119] -> pixels -51..119, y in [-40.25, 89] -> -41..89.
    assert canvas.shape == (89 + 41 + 1, 119 + 51 + 1)
    np.testing.assert_array_equal(canvas.H_ref_to_canvas, translation(51, 41))
    out = canvas.render().astype(np.float64)
    ys, xs = np.mgrid[0 : canvas.shape[0], 0 : canvas.shape[1]].astype(np.float64)
    truth = smooth_field(xs - 51, ys - 41)
    # Interior of the union (2 px away from every tile border).
    interior = np.zeros(canvas.shape, bool)
    interior[41 + 2 : 41 + h - 2, 51 + 2 : 51 + w - 2] = True
    interior[2 : h - 2, 2 : w - 2] = True
    err = np.abs(out - truth)[interior]
    assert err.max() < 1.5  # bilinear resampling of a smooth field + two uint8 roundings
    assert err.mean() < 0.5
    # The second tile's sub-pixel border is never sampled half outside the frame.
    cov = canvas.coverage() > 0
    assert not cov[0, :].any() and cov[1, 1 : 1 + w - 1].all()


@pytest.mark.parametrize("blend", BLENDS)
def test_landmark_lands_where_homographies_predict(blend: str) -> None:
    h, w = 100, 140
    dot_xy = (30.0, 70.0)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    dot = 250 * np.exp(-((xs - dot_xy[0]) ** 2 + (ys - dot_xy[1]) ** 2) / (2 * 2.0**2))
    frame = np.repeat(np.rint(dot).astype(np.uint8)[..., None], 3, axis=2)
    H = similarity(25.0, 1.3, -40.0, 15.0)
    H[2, :2] = (2e-4, -1e-4)  # a little perspective too

    canvas = Canvas(ComposeConfig(blend=blend))
    canvas.add(np.zeros((h, w, 3), np.uint8), np.eye(3))  # dark reference frame
    canvas.add(frame, H)

    predicted = canvas.H_ref_to_canvas @ H @ np.array([dot_xy[0], dot_xy[1], 1.0])
    predicted = predicted[:2] / predicted[2]
    assert canvas.H_ref_to_canvas[0, 2] > 0  # the warped frame reaches negative x
    img = canvas.render()[..., 1].astype(np.float64)
    py, px = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    near = (px - predicted[0]) ** 2 + (py - predicted[1]) ** 2 < 12**2
    weights = np.where(near & (img > 20), img, 0.0)
    assert weights.sum() > 0
    centroid = np.array([(px * weights).sum(), (py * weights).sum()]) / weights.sum()
    assert np.linalg.norm(centroid - predicted) < 1.0
    peak_y, peak_x = np.unravel_index(np.argmax(img), img.shape)
    assert abs(peak_x - predicted[0]) <= 1 and abs(peak_y - predicted[1]) <= 1


def test_last_blend_later_frame_wins() -> None:
    red = np.zeros((60, 80, 3), np.uint8)
    red[...] = (0, 0, 200)
    blue = np.zeros((60, 80, 3), np.uint8)
    blue[...] = (180, 10, 0)
    canvas = Canvas(ComposeConfig(blend="last"))
    canvas.add(red, np.eye(3))
    canvas.add(blue, translation(30, 20))

    out = canvas.render()
    assert canvas.shape == (80, 110)
    assert np.all(out[20:80, 30:110] == (180, 10, 0))  # the whole second frame, overlap included
    assert np.all(out[0:20, 0:80] == (0, 0, 200))
    assert np.all(out[20:60, 0:30] == (0, 0, 200))
    assert np.all(out[0:20, 80:110] == 0) and np.all(out[60:80, 0:30] == 0)


def _seam_profile(blend: str) -> np.ndarray:
    dark = np.full((80, 120, 3), 100, np.uint8)
    bright = np.full((80, 120, 3), 160, np.uint8)
    canvas = Canvas(ComposeConfig(blend=blend, feather_px=20))
    canvas.add(dark, np.eye(3))
    canvas.add(bright, translation(60, 0))  # overlap: x in [60, 120)
    assert canvas.shape == (80, 180)
    return canvas.render()[40, :, 0].astype(np.int16)


def test_feather_blend_is_smooth_across_seam() -> None:
    row = _seam_profile("feather")
    assert np.all(row[:60] == 100) and np.all(row[120:] == 160)
    steps = np.diff(row)
    assert steps.min() >= 0  # monotonic ramp from the dark to the bright frame
    assert steps.max() <= 5  # 60 grey levels spread over the 20 px feather ramps
    # Average, by contrast, jumps by half the difference at each frame edge.
    avg_steps = np.diff(_seam_profile("average"))
    assert avg_steps.max() >= 29


def test_far_placement_raises_and_leaves_canvas_unchanged() -> None:
    image = random_image(50, 70, seed=3)
    canvas = Canvas(ComposeConfig(blend="feather"))
    canvas.add(image, np.eye(3))
    canvas.add(image, translation(10, -5))
    before = (canvas.shape, canvas.render(), canvas.coverage(), canvas.H_ref_to_canvas)

    far = translation(1e5, 0)
    assert not canvas.fits(far, (50, 70))
    with pytest.raises(CanvasLimitError, match=r"8000 px") as info:
        canvas.add(image, far)
    assert "100070x55" in str(info.value)  # the size it would reach, width x height
    assert "max_canvas_px" in str(info.value)

    assert canvas.n_frames == 2
    assert canvas.shape == before[0]
    np.testing.assert_array_equal(canvas.render(), before[1])
    np.testing.assert_array_equal(canvas.coverage(), before[2])
    np.testing.assert_array_equal(canvas.H_ref_to_canvas, before[3])


def test_cap_boundary_and_buffer_stay_within_cap() -> None:
    image = random_image(100, 100, seed=4)
    canvas = Canvas(ComposeConfig(max_canvas_px=300))
    assert canvas.fits(np.eye(3), (100, 100))
    canvas.add(image, np.eye(3))
    assert canvas.fits(translation(200, 0), (100, 100))  # union exactly 300 px wide
    assert not canvas.fits(translation(201, 0), (100, 100))
    assert not canvas.fits(translation(-201, 0), (100, 100))
    assert not canvas.fits(translation(0, 200.5), (100, 100))
    canvas.add(image, translation(200, 0))
    assert canvas.shape == (100, 300)
    with pytest.raises(CanvasLimitError):
        canvas.add(image, translation(0, 201))
    assert canvas.shape == (100, 300) and canvas.n_frames == 2
    # Memory stays bounded by the cap: the growth slack never pushes a buffer side past it.
    assert max(canvas._weight.shape) <= 300


def test_degenerate_homography_is_refused() -> None:
    canvas = Canvas(ComposeConfig())
    H = np.eye(3)
    H[2, 0] = -0.02  # the line at infinity crosses the frame (x = 50)
    assert not canvas.fits(H, (60, 80))
    with pytest.raises(CanvasLimitError, match="infinity"):
        canvas.add(random_image(60, 80), H)
    assert canvas.shape == (0, 0) and canvas.n_frames == 0


@pytest.mark.parametrize("blend", BLENDS)
def test_masked_border_never_leaks_dark_pixels(blend: str) -> None:
    h, w = 90, 120
    frame = np.zeros((h, w, 3), np.uint8)
    frame[10:-10, 10:-10] = 200
    border_mask = np.zeros((h, w), np.uint8)
    border_mask[10:-10, 10:-10] = 255
    disc_mask = np.zeros((h, w), np.uint8)
    cv2.circle(disc_mask, (60, 45), 33, 255, -1)  # inside the bright area

    canvas = Canvas(ComposeConfig(blend=blend, feather_px=10))
    canvas.add(frame, np.eye(3), border_mask)
    canvas.add(frame, similarity(10.0, 1.1, 15.3, 7.7), border_mask)
    canvas.add(frame, similarity(-7.0, 0.9, -20.6, 30.2), disc_mask)

    cov = canvas.coverage() > 0
    out = canvas.render()
    assert np.all(out[cov] == 200)  # no dark pixel anywhere on the covered canvas
    assert np.all(out[~cov] == 0)
    # ... without eroding the valid region away: the identity frame keeps all its pixels.
    T = canvas.H_ref_to_canvas
    ox, oy = int(T[0, 2]), int(T[1, 2])
    assert cov[oy + 10 : oy + h - 10, ox + 10 : ox + w - 10].all()
    assert not cov[oy + 9, ox + 11 : ox + 20].any()  # the masked band stays uncovered


@pytest.mark.parametrize("blend", BLENDS)
def test_many_frames_growing_in_all_directions(
    blend: str, caplog: pytest.LogCaptureFixture
) -> None:
    # A walk over a large known image (left, up, right, down, with jitter): the canvas
    # re-allocates in every direction and must still show exactly the image wherever a frame
    # covered it; the growth slack keeps the re-allocations few.
    bh, bw, fh, fw = 1000, 1400, 60, 80
    base = random_image(bh, bw, seed=5)
    rng = np.random.default_rng(6)
    ref_xy = np.array([700, 500])
    corners = [ref_xy, (0, 500), (0, 0), (bw - fw, 0), (bw - fw, bh - fh)]
    offsets = []
    for a, b in itertools.pairwise(corners):
        n = int(np.abs(np.subtract(b, a)).max() // 40) + 1
        for t in np.linspace(0.0, 1.0, n, endpoint=False):
            jitter = rng.integers(-5, 6, size=2)
            xy = np.rint(np.add(a, t * np.subtract(b, a))).astype(int) + jitter
            offsets.append(np.clip(xy, 0, [bw - fw, bh - fh]))
    offsets[0] = ref_xy
    canvas = Canvas(ComposeConfig(blend=blend))
    covered = np.zeros((bh, bw), bool)
    with caplog.at_level(logging.DEBUG, logger="mosaic.canvas"):
        for x, y in offsets:
            canvas.add(base[y : y + fh, x : x + fw], translation(x - ref_xy[0], y - ref_xy[1]))
            covered[y : y + fh, x : x + fw] = True
    growths = sum("canvas buffer" in r.getMessage() for r in caplog.records)
    assert 4 <= growths <= 12, growths  # first allocation + a few amortised growths

    xs = [o[0] for o in offsets]
    ys = [o[1] for o in offsets]
    x0, y0 = min(xs), min(ys)
    assert canvas.shape == (max(ys) + fh - y0, max(xs) + fw - x0)
    np.testing.assert_array_equal(
        canvas.H_ref_to_canvas, translation(ref_xy[0] - x0, ref_xy[1] - y0)
    )
    window = (slice(y0, max(ys) + fh), slice(x0, max(xs) + fw))
    np.testing.assert_array_equal(canvas.coverage() > 0, covered[window])
    out = canvas.render()
    np.testing.assert_array_equal(out[covered[window]], base[window][covered[window]])
    assert canvas.n_frames == len(offsets)


@pytest.mark.parametrize("blend", BLENDS)
def test_content_in_frame_samples_the_canvas_where_a_frame_lands(blend: str) -> None:
    h, w = 90, 120
    canvas = Canvas(ComposeConfig(blend=blend, feather_px=15))
    canvas.add(smooth_tile(0.0, 0.0, h, w), np.eye(3))
    canvas.add(smooth_tile(40.0, 10.0, h, w), translation(40.0, 10.0))
    H = similarity(8.0, 0.9, 20.0, 5.0)  # a frame seen rotated and zoomed
    for scale, shape in ((1.0, (60, 80)), (0.5, (30, 40))):
        values, valid = canvas.content_in_frame(H, (60, 80, 3), scale)
        H_out = scale_matrix((60, 80), shape)
        assert values.shape == valid.shape == shape and values.dtype == np.float32
        ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
        pts = np.stack([xs, ys, np.ones_like(xs)], axis=-1)
        to_ref = H @ np.linalg.inv(H_out)
        ref = pts @ to_ref.T
        rx, ry = ref[..., 0] / ref[..., 2], ref[..., 1] / ref[..., 2]
        inside = ((rx > 1) & (rx < w - 2) & (ry > 1) & (ry < h - 2)) | (
            (rx > 41) & (rx < 40 + w - 2) & (ry > 11) & (ry < 10 + h - 2)
        )
        assert valid[inside].all() and not valid[(rx < -1) | (ry < -1) | (ry > 10 + h)].any()
        truth = smooth_field(rx, ry)[..., 1]
        assert np.abs(values - truth)[inside].max() < 2.0


def test_content_in_frame_lets_nothing_of_the_empty_canvas_in() -> None:
    canvas = Canvas(ComposeConfig(), channels=1)
    assert not canvas.content_in_frame(np.eye(3), (10, 10))[1].any()  # empty canvas
    canvas.add(np.full((50, 60), 200, np.uint8), np.eye(3))
    values, valid = canvas.content_in_frame(translation(30.3, 20.7), (50, 60))  # half outside
    assert valid.any() and not valid.all()
    np.testing.assert_allclose(values[valid], 200.0, atol=1e-3)
    assert (values[~valid] == 0).all()
    assert not canvas.content_in_frame(translation(500, 0), (50, 60))[1].any()


@pytest.mark.parametrize("blend", ["average", "feather", "multiband", "best"])
def test_weight_factors_and_float_frames(blend: str) -> None:
    # two flat frames on top of each other, the second weighing 3x: the mean leans to it
    canvas = Canvas(ComposeConfig(blend=blend), extent=(0, 0, 80, 60))
    canvas.add(
        np.full((60, 80, 3), 100.0, np.float32), np.eye(3), None, np.ones((60, 80), np.float32)
    )
    canvas.add(
        np.full((60, 80, 3), 140.0, np.float32), np.eye(3), None, np.full((60, 80), 3, np.float32)
    )
    out = canvas.render()
    assert out.shape == (60, 80, 3)
    np.testing.assert_allclose(out[20:40, 30:50], 130, atol=1)
    values, valid = canvas.content_in_frame(np.eye(3), (60, 80, 3), 0.5, channel=None)
    assert values.shape == (30, 40, 3) and valid[5:25, 5:35].all()
    np.testing.assert_allclose(values[10:20, 15:25], 130, atol=1)


def test_planes_hold_what_separate_canvases_hold():
    """`CanvasPlanes` (the flat-field's shading mosaic) warps each frame's weights once for all its
    planes: sums, weights and reads are those of one `Canvas` per plane, bit for bit, across
    buffer growth."""
    from mosaic.canvas import CanvasPlanes

    rng = np.random.default_rng(4)
    config = ComposeConfig(blend="average")
    planes = CanvasPlanes(config, 2)
    separate = [Canvas(config, 3) for _ in range(2)]
    h, w = 40, 60
    for i in range(12):
        angle, tx, ty = 0.05 * i, 90.0 * i - 50.0 * (i % 3), 40.0 * i * (-1) ** i
        H = np.array(
            [
                [math.cos(angle), -math.sin(angle), tx],
                [math.sin(angle), math.cos(angle), ty],
                [1e-4 * (i % 4), -5e-5 * (i % 3), 1.0],
            ]
        )
        images = [rng.normal(0, 1, (h, w, 3)).astype(np.float32) for _ in range(2)]
        mask = (rng.random((h, w)) > 0.1).astype(np.uint8) * 255
        if i:
            read, seen = planes.planes_in_frame(H, (h, w))
            for canvas, values in zip(separate, read, strict=True):
                expected, valid = canvas.content_in_frame(H, (h, w), 1.0, channel=None)
                np.testing.assert_array_equal(seen, valid)
                np.testing.assert_array_equal(values, expected)
        planes.add_planes(images, H, mask)
        for canvas, image in zip(separate, images, strict=True):
            canvas.add(image, H, mask)
    sums = [planes._content_views()[0]]
    x0, y0, x1, y1 = planes._content
    rows = slice(y0 - planes._buf_y0, y1 - planes._buf_y0)
    cols = slice(x0 - planes._buf_x0, x1 - planes._buf_x0)
    sums += [more[rows, cols] for more in planes._more_sums]
    for canvas, total in zip(separate, sums, strict=True):
        expected_sum, expected_weight = canvas._content_views()
        np.testing.assert_array_equal(total, expected_sum)
        np.testing.assert_array_equal(planes._content_views()[1], expected_weight)


def _random_canvas(blend: str = "multiband") -> Canvas:
    """A canvas of known extent with 15 random frames at subpixel placements, weighted."""
    rng = np.random.default_rng(11)
    canvas = Canvas(ComposeConfig(blend=blend), extent=(-20, -10, 430, 300))
    for i in range(15):
        image = rng.uniform(0, 255, (90, 120, 3)).astype(np.float32)
        H = similarity(3.0 * i, 1.0 + 0.01 * i, 25.3 * i - 10, 17.7 * (i % 7))
        canvas.add(image, H, None, rng.uniform(0.5, 2.0, (90, 120)).astype(np.float32))
    canvas.flush()  # the blending thread's frames in the blender
    return canvas


def test_multiband_in_its_thread_renders_as_in_order_here(monkeypatch) -> None:
    """The pyramids built in the canvas' blending thread (`BLEND_AHEAD` frames ahead) give
    the mosaic, pixel for pixel, that adding each frame's pyramid in the caller's thread
    gives."""
    threaded = _random_canvas().render()
    monkeypatch.setattr(Canvas, "_blend_later", lambda self, boxed: self._blender.add_boxed(boxed))
    np.testing.assert_array_equal(_random_canvas().render(), threaded)


def test_an_error_in_the_blending_thread_is_raised_to_the_caller(monkeypatch) -> None:
    """A frame whose pyramid fails in the blending thread fails the caller's next add or
    render, with the thread's own exception; nothing is swallowed."""

    def broken(self, boxed) -> None:
        raise MemoryError("no room for the pyramid")

    monkeypatch.setattr("mosaic.blending.LaplacianBlender.add_boxed", broken)
    with pytest.raises(MemoryError, match="no room for the pyramid"):
        _random_canvas().render()


def test_multiband_renders_strip_by_strip_exactly(monkeypatch) -> None:
    """The collapse by strips (`RENDER_ROWS`, `LaplacianBlender.render_rows`) gives the whole
    canvas' collapse pixel for pixel, whatever the strip's height."""
    canvas = _random_canvas()
    blender = canvas._blender
    assert blender is not None
    # the whole pyramid collapsed at once, as the blender did before it rendered by strips
    out = None
    for k in range(blender.levels, -1, -1):
        den = blender._den[k][..., None]
        level = np.divide(blender._num[k], den, out=np.zeros_like(blender._num[k]), where=den > 0)
        if out is not None:
            h, w = level.shape[:2]
            level = level + cv2.pyrUp(out, dstsize=(w, h)).reshape(h, w, 3)
        out = level
    assert out is not None
    whole = out[: blender.height, : blender.width]
    np.testing.assert_array_equal(blender.render(), whole)
    for y0, rows in [(0, 1), (3, 2), (31, 33), (64, 64), (100, 7), (blender.height - 5, 9)]:
        np.testing.assert_array_equal(blender.render_rows(y0, y0 + rows), whole[y0 : y0 + rows])
    monkeypatch.setattr("mosaic.canvas.RENDER_ROWS", 10**6)
    reference = canvas.render()
    for rows in (1, 7, 64):
        monkeypatch.setattr("mosaic.canvas.RENDER_ROWS", rows)
        np.testing.assert_array_equal(canvas.render(), reference)


def test_multiband_over_its_memory_budget_feathers_with_a_warning(monkeypatch, caplog) -> None:
    from mosaic.blending import LaplacianBlender

    need = LaplacianBlender.bytes_for(310, 450, 3)
    monkeypatch.setattr("mosaic.canvas.MULTIBAND_MAX_BYTES", need)
    assert _random_canvas()._blender is not None
    monkeypatch.setattr("mosaic.canvas.MULTIBAND_MAX_BYTES", need - 1)
    with caplog.at_level(logging.WARNING, logger="mosaic.canvas"):
        canvas = _random_canvas()
    assert canvas._blender is None and canvas.blend == "feather"
    assert "feathering instead of multiband" in caplog.text
    # what it renders is the feathered mosaic of the same frames
    np.testing.assert_array_equal(canvas.render(), _random_canvas("feather").render())


@pytest.mark.parametrize("blend", ["multiband", "feather"])
def test_render_needs_no_float_image_of_the_whole_canvas(blend: str) -> None:
    """Rendering a 2400x1600 canvas allocates its uint8 image and strips of rows, not whole
    float images (before the strips, multiband's collapse took 190 MB here, feather 59 MB)."""
    import tracemalloc

    canvas = Canvas(ComposeConfig(blend=blend), extent=(0, 0, 2400, 1600))
    rng = np.random.default_rng(5)
    for x, y in [(0, 0), (1900, 1200), (1000, 600)]:
        canvas.add(rng.uniform(0, 255, (400, 500, 3)).astype(np.float32), translation(x, y))
    tracemalloc.start()
    try:
        image = canvas.render()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert image.shape == (1600, 2400, 3)
    strip = 2400 * 256 * 4 * 3  # one float32 strip of RENDER_ROWS rows
    # measured: the image + 3.4 strips (multiband), + 1.3 (feather) one strip at a time, + 6.7
    # (multiband) two at a time (PICTURE_THREADS = 2); before the strips: + 25.5 and 6.8
    assert peak < image.nbytes + 4 * PICTURE_THREADS * strip, (peak - image.nbytes) / strip


def _noisy_vessels(sigma: float = 6.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A vessel-like pattern (thin bright and dark lines, a dark disc) with Gaussian noise:
    (noisy BGR uint8, clean float32 grey, content mask with an empty band on the left)."""
    h, w = 300, 400
    yy, xx = np.mgrid[:h, :w]
    lines = np.abs(((xx + 0.3 * yy) % 40) - 20) < 2.5
    clean = 120.0 + 60 * lines - 50 * (np.hypot(xx - 200, yy - 150) < 40)
    clean = cv2.GaussianBlur(clean.astype(np.float32), (0, 0), 1.0)
    noisy = clean + np.random.default_rng(0).normal(0, sigma, clean.shape)
    image = np.dstack([np.clip(noisy, 0, 255).astype(np.uint8)] * 3)
    content = np.ones((h, w), bool)
    content[:, :30] = False
    image[~content] = 0
    return image, clean, content


def test_shrink_noise_smooths_the_noise_and_keeps_the_vessels():
    """The noise blending left (sigma 6 here) is more than halved and a vessel keeps its
    contrast to within 8 %: both better than a Gaussian blur of the band's sigma (rms 2.78,
    contrast -9 %; measured 2.70 and -6 %). The empty canvas stays empty, and the strips add up
    to the whole, made two at a time or with their bands made again."""
    from mosaic.blending import shrink_noise

    image, clean, content = _noisy_vessels()
    out = shrink_noise(image, content, rows=64)
    inner = content.copy()
    inner[:, :40] = False  # the edge of the content
    blurred = cv2.GaussianBlur(image, (0, 0), 1.0)
    images = (image, out, blurred)
    rms = [np.sqrt(((im[..., 1] - clean.astype(float))[inner] ** 2).mean()) for im in images]
    assert rms[1] < 0.5 * rms[0] and rms[1] < rms[2], rms
    vessel, background = (clean > 170) & inner, (np.abs(clean - 120) < 1) & inner
    contrast = [float(im[..., 1][vessel].mean() - im[..., 1][background].mean()) for im in images]
    truth = clean[vessel].mean() - clean[background].mean()
    assert abs(contrast[1] / truth - 1) < 0.08 and contrast[1] > contrast[2], (contrast, truth)
    assert out[~content].max() == 0
    np.testing.assert_array_equal(out, shrink_noise(image, content, rows=10_000))
    np.testing.assert_array_equal(out, shrink_noise(image, content, 64, 2, keep_bytes=0))


def test_canvas_picture_is_the_render_denoised_only_when_asked():
    image, _, _ = _noisy_vessels()
    H = np.eye(3)
    pictures = {}
    for denoise in (False, True):
        canvas = Canvas(ComposeConfig(blend="feather", denoise=denoise))
        canvas.add(image, H)
        pictures[denoise] = canvas.picture()
        np.testing.assert_array_equal(canvas.render(), pictures[False])  # render stays exact
    smoother = [
        cv2.Laplacian(p[..., 1], cv2.CV_32F)[50:-50, 80:-50].std() for p in pictures.values()
    ]
    assert smoother[1] < 0.7 * smoother[0]


def test_shrink_noise_reads_the_noise_where_the_mosaic_is_quiet():
    """A fine texture over most of the mosaic (photoreceptors in an adaptive-optics view) is
    not taken for noise: the noise level comes from the quiet places, so the texture keeps
    over 0.9 of its fine detail and gets no worse, while the quiet part loses most of its
    noise (measured: 0.93; rms 3.05 → 2.94 and 3.08 → 1.03 grey levels)."""
    from mosaic.blending import _band_energy, shrink_noise

    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.normal(0, 1, (300, 300)).astype(np.float32), (0, 0), 1.0)
    clean = 120 + 20 * texture / texture.std()
    clean[:, 240:] = 120  # a fifth of the mosaic without texture
    noisy = np.clip(clean + rng.normal(0, 3, clean.shape), 0, 255).astype(np.uint8)
    content = np.ones(clean.shape, bool)
    out = shrink_noise(np.dstack([noisy] * 3), content)[..., 1].astype(np.float32)
    textured, quiet = np.zeros_like(content), np.zeros_like(content)
    textured[10:-10, 10:230], quiet[10:-10, 250:-10] = True, True
    band_clean, _ = _band_energy(clean, content)
    band_out, _ = _band_energy(out, content)
    assert (band_out[textured] ** 2).mean() > 0.9 * (band_clean[textured] ** 2).mean()

    def rms(image: np.ndarray, where: np.ndarray) -> float:
        return float(np.sqrt(((image.astype(np.float32) - clean)[where] ** 2).mean()))

    assert rms(out, textured) <= rms(noisy, textured)
    assert rms(out, quiet) < 0.5 * rms(noisy, quiet)
