"""Photometry against injected ground truth: side bands, vignetting, exposure gains, sharpness
weighting, and seamless blends of frames with different gains."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mosaic.blending import LaplacianBlender, fill_invalid
from mosaic.canvas import BLENDS, Canvas
from mosaic.compose import LiveCompositor
from mosaic.config import ComposeConfig
from mosaic.photometry import (
    GainObservations,
    SideBandDetector,
    VideoPhotometry,
)
from mosaic.render import render_segments

H, W = 120, 160  # frame size of the synthetic videos


def translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def scene(fundus: np.ndarray) -> np.ndarray:
    """A patch of retina with vessels, its green channel in all three (33-126 grey levels:
    room for gains up to 1.3 without saturating)."""
    return np.repeat(fundus[350:950, 300:1100, 1:2], 3, axis=2)


def _crop(scene: np.ndarray, x: int, y: int) -> np.ndarray:
    return scene[y : y + H, x : x + W].astype(np.float32)


def _to_u8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _walk(n: int, seed: int = 0) -> list[tuple[int, int]]:
    """Top-left corners of n frames wandering over the scene (steps of 10-30 px)."""
    rng = np.random.default_rng(seed)
    xy = np.array([300.0, 200.0])
    out = []
    for _ in range(n):
        xy = np.clip(xy + rng.uniform(-30, 30, 2), [0, 0], [800 - W - 1, 600 - H - 1])
        out.append((int(xy[0]), int(xy[1])))
    return out


def _vignette(cx: float = 0.15, cy: float = -0.1, strength: float = 0.35) -> np.ndarray:
    """An off-centre radial fall-off, 1 - strength x r^2 (r = 1 at the frame corners)."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    u = (xs - (W - 1) / 2) / (W / 2) - cx
    v = (ys - (H - 1) / 2) / (H / 2) - cy
    return 1.0 - strength * (u * u + v * v) / 2.0


def _mask() -> np.ndarray:
    return np.full((H, W), 255, np.uint8)


def _source(frames: list[tuple[int, np.ndarray]]):
    def read():
        for index, image in frames:
            yield index, image, _mask()

    return read


# ------------------------------------------------------------------------------ side bands


def _striped(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A static-looking adaptive-optics band: every other row black, the others noisy."""
    band = rng.integers(25, 60, (h, w)).astype(np.float32)
    band[::2] = 0
    return band


def test_side_band_detection_finds_injected_striped_bands(scene: np.ndarray) -> None:
    rng = np.random.default_rng(1)
    detector = SideBandDetector()
    for x, y in _walk(16):
        frame = _crop(scene, x, y)
        frame[:, :18] = _striped(H, 18, rng)[..., None]  # left: striped, not dark on average
        frame[:, W - 11 :] = 140.0 + rng.normal(0, 3, (H, 11, 1))  # right: a bright bar
        detector.add(_to_u8(frame), _mask())
    bands = detector.estimate()
    assert 18 <= bands.left <= 18 + SideBandDetector.MARGIN_PX + 1, bands
    assert 11 <= bands.right <= 11 + SideBandDetector.MARGIN_PX + 1, bands
    assert bands.top == 0 and bands.bottom == 0, bands
    keep = bands.keep((H, W))
    assert not keep[:, :18].any() and keep[:, 25:140].all()


def test_side_band_detection_finds_nothing_on_plain_retina(scene: np.ndarray) -> None:
    detector = SideBandDetector()
    aperture = np.zeros((H, W), np.uint8)
    cv2.ellipse(aperture, (W // 2, H // 2), (W // 2 - 2, int(0.62 * H)), 0, 0, 360, 255, -1)
    for x, y in _walk(16, seed=2):
        detector.add(_to_u8(_crop(scene, x, y) * _vignette()[..., None]), aperture)
    assert not detector.estimate().any()


# ------------------------------------------------------------------------------ flat-field


def _flatfield_of(scene: np.ndarray, truth: np.ndarray, correct: bool) -> np.ndarray:
    """The flat-field estimated on 60 frames wandering over `scene`, shaded by `truth`."""
    config = ComposeConfig(exposure=False, flatfield=True, sharpness_weighting=False)
    photometry = VideoPhotometry(bands=False, flatfield=True)
    compositor = LiveCompositor(config, photometry, correct=correct)
    canvas = Canvas(config)
    for x, y in _walk(60, seed=3):
        frame = _to_u8(_crop(scene, x, y) * truth[..., None])
        compositor.add(canvas, frame, translation(x, y), _mask())
    photometry.refresh()
    flat = photometry.flatfield
    assert flat is not None and flat.profile.shape == (H, W)
    return flat.profile


@pytest.mark.parametrize("correct", [False, True])
def test_flatfield_recovers_an_injected_vignetting(scene: np.ndarray, correct: bool) -> None:
    # frames wander over a retina with its own large-scale shading (what a mean of the frames
    # would take for vignetting); the ratio to the mosaic under each frame cancels it
    truth = _vignette(cx=0.0, cy=0.0)
    profile = _flatfield_of(scene, truth, correct)
    error = np.abs(profile / profile.mean() / (truth / truth.mean()) - 1)
    assert error.max() < 0.03, error.max()  # measured 0.018
    assert np.median(error) < 0.01


def test_off_centre_vignetting_is_recovered_up_to_a_tilt(scene: np.ndarray) -> None:
    # shifted views of a place differ by a constant under a tilted shading: the exposure gains
    # take it, and the flat-field is the rest of the profile
    truth = _vignette(cx=0.15, cy=-0.1)
    log_ratio = np.log(_flatfield_of(scene, truth, False) / truth).ravel()
    ys, xs = np.mgrid[0:H, 0:W]
    plane = np.stack([np.ones(H * W), xs.ravel(), ys.ravel()], 1)
    rest = log_ratio - plane @ np.linalg.lstsq(plane, log_ratio, rcond=None)[0]
    assert np.abs(np.expm1(rest)).max() < 0.04, np.abs(rest).max()  # measured 0.034
    assert np.median(np.abs(rest)) < 0.01


# ------------------------------------------------------------------------------ exposure


def _gain_video(scene: np.ndarray, n: int = 12, seed: int = 4):
    rng = np.random.default_rng(seed)
    gains = rng.uniform(0.75, 1.3, n)
    offsets = [(40 * i, 15 * (i % 3)) for i in range(n)]  # a pan: each frame overlaps the next
    frames = [
        (i, _to_u8(_crop(scene, x, y) * g))
        for i, ((x, y), g) in enumerate(zip(offsets, gains, strict=True))
    ]
    poses = {0: {i: translation(x, y) for i, (x, y) in enumerate(offsets)}}
    return frames, poses, gains


def test_exposure_recovers_injected_gains_within_two_percent(scene: np.ndarray) -> None:
    frames, poses, gains = _gain_video(scene)
    config = ComposeConfig(exposure=True, flatfield=False, sharpness_weighting=False)
    rendered = render_segments(config, _source(frames), poses)[0]
    est = np.array([rendered.gains[i] for i in range(len(gains))])
    # a frame scaled by g needs the gain 1 / g, up to one factor for the whole mosaic
    ratio = est * gains
    ratio /= np.exp(np.mean(np.log(ratio)))
    assert np.abs(ratio - 1).max() < 0.02, ratio


@pytest.mark.parametrize("keep_bytes", [0, 5 * (H * W * 3 + H * W // 8)])  # none; five frames
def test_rerender_reads_again_past_what_it_keeps_and_renders_the_same(
    scene: np.ndarray, keep_bytes: int
) -> None:
    """The re-render keeps the frames of its first pass for its second up to `keep_bytes`
    (none; the first five) and reads the others again: the same mosaic and gains, pixel for
    pixel, as with every frame kept, and each frame read once more only when it was not
    kept."""
    frames, poses, _ = _gain_video(scene)
    config = ComposeConfig()  # multiband, exposure, flat-field, sharpness weighting
    reads: list[int] = []

    def counted():
        for index, image, mask in _source(frames)():
            reads.append(index)
            yield index, image, mask

    kept_all = render_segments(config, _source(frames), poses)[0]
    partly = render_segments(config, counted, poses, keep_bytes=keep_bytes)[0]
    np.testing.assert_array_equal(partly.canvas.render(), kept_all.canvas.render())
    assert partly.gains == kept_all.gains
    assert len(reads) == 2 * len(frames)  # a second read whenever a frame was not kept
    assert len(render_segments(config, counted, poses)) == 1
    assert len(reads) == 3 * len(frames)  # all kept: read once


def test_gain_solve_is_robust_to_a_glared_cell() -> None:
    obs = GainObservations()
    cells = np.arange(50)
    radiance = np.linspace(40, 160, 50)
    obs.add(0, cells, radiance)
    glared = radiance * 1.2
    glared[:5] = 250  # a few cells the other frame sees glared
    obs.add(1, cells, glared)
    gains = obs.solve()  # what each frame is multiplied by
    assert gains[1] / gains[0] == pytest.approx(1 / 1.2, rel=0.01)


def test_live_gain_matches_the_canvas_under_the_frame(scene: np.ndarray) -> None:
    config = ComposeConfig(exposure=True, flatfield=False, sharpness_weighting=False)
    compositor = LiveCompositor(config, VideoPhotometry(False, False))
    canvas = Canvas(config)
    assert compositor.add(canvas, _to_u8(_crop(scene, 100, 100)), np.eye(3), _mask()) is None
    gain = compositor.add(
        canvas, _to_u8(_crop(scene, 140, 110) * 1.25), translation(40, 10), _mask()
    )
    assert gain == pytest.approx(1 / 1.25, rel=0.02)


# ------------------------------------------------------------------------------ seams


@pytest.mark.parametrize("blend", BLENDS)
def test_every_blend_is_seamless_on_frames_with_different_gains(blend: str) -> None:
    # a flat grey scene seen by three overlapping frames with gains 1, 1.4 and 0.8: any
    # brightness change along the mosaic is a seam
    frames = [
        (i, np.full((H, W, 3), round(100 * g), np.uint8)) for i, g in enumerate((1, 1.4, 0.8))
    ]
    poses = {0: {0: np.eye(3), 1: translation(60, 0), 2: translation(120, 5)}}
    ranges = {}
    for exposure in (False, True):
        config = ComposeConfig(blend=blend, exposure=exposure, flatfield=False)
        mosaic = render_segments(config, _source(frames), poses)[0].canvas.render()
        profile = mosaic[20:100, :, 1].astype(np.float64).mean(axis=0)
        ranges[exposure] = float(np.ptp(profile))
    assert ranges[False] > 20, ranges  # the steps (or ramps) between the frames
    assert ranges[True] < 1.5, ranges  # after compensation: measured 0-1 grey level


# ------------------------------------------------------------------------------ sharpness


def _band(image: np.ndarray) -> np.ndarray:
    """Band-pass (difference of Gaussians, σ 1.5 and 4) of the green channel: vessel detail."""
    g = np.asarray(image, np.float32)[..., 1]
    return cv2.GaussianBlur(g, (0, 0), 1.5) - cv2.GaussianBlur(g, (0, 0), 4)


def _sharpness(image: np.ndarray, truth: np.ndarray) -> float:
    """How much of the true detail `image` shows: its band-pass projected on the truth's
    (1: as sharp as the truth; blur lowers it, noise averages out)."""
    b, t = _band(image), _band(truth)
    return float((b * t).sum() / (t * t).sum())


def test_sharpness_weighting_keeps_a_blurred_frame_out_of_a_sharp_one(scene: np.ndarray) -> None:
    # a pan of five frames with the same sensor noise; the middle one is defocused (σ 3 px),
    # and the others see all of it: where they do, the mosaic is as sharp as they are
    rng = np.random.default_rng(5)
    offsets = (0, 20, 40, 60, 80)
    views = [_crop(scene, 200 + dx, 200) for dx in offsets]
    views[2] = cv2.GaussianBlur(views[2], (0, 0), 3.0)
    frames = [(i, _to_u8(v + rng.normal(0, 3, (H, W, 3)))) for i, v in enumerate(views)]
    poses = {0: {i: translation(dx, 0) for i, dx in enumerate(offsets)}}
    rows, cols = slice(20, 100), slice(85, 155)  # the blurred frame's middle
    truth = _crop(scene, 200, 200)[rows, cols]  # where frame 0 sits, the scene itself
    shown = {}
    for on in (False, True):
        config = ComposeConfig(sharpness_weighting=on, exposure=False, flatfield=False)
        mosaic = render_segments(config, _source(frames), poses)[0].canvas.render()
        shown[on] = _sharpness(mosaic[rows, cols], truth)
    # the mosaic of the sharp frames alone
    sharp_only = {0: {i: H for i, H in poses[0].items() if i != 2}}
    mosaic = render_segments(ComposeConfig(sharpness_weighting=False), _source(frames), sharp_only)
    ideal = _sharpness(mosaic[0].canvas.render()[rows, cols], truth)
    blurred_alone = _sharpness(cv2.GaussianBlur(truth, (0, 0), 3.0), truth)
    assert blurred_alone < 0.5  # what the blurred frame has of the detail
    assert shown[False] < ideal - 0.1, (shown, ideal)  # plain feather: softened
    assert shown[True] > ideal - 0.05, (shown, ideal)  # measured 0.964, plain 0.877, ideal 1.003


@pytest.mark.parametrize("blend", ["multiband", "feather", "average"])
def test_a_glared_frame_gives_way_where_another_frame_saw(scene: np.ndarray, blend: str) -> None:
    clear = _to_u8(_crop(scene, 200, 200))
    glared = clear.copy()
    glared[30:90, 40:120] = 255  # a saturated reflection
    frames = [(0, clear), (1, glared)]
    poses = {0: {0: np.eye(3), 1: translation(2, 0)}}
    config = ComposeConfig(blend=blend, exposure=False, flatfield=False)
    mosaic = render_segments(config, _source(frames), poses)[0].canvas.render()
    # the reflection's middle shows the clear frame, not a mix with 255 (nor a halo)
    middle = mosaic[45:75, 65:105].astype(np.float64)
    assert np.abs(middle - clear[45:75, 63:103]).mean() < 3


# ------------------------------------------------------------------------------ multiband


def test_multiband_reproduces_a_single_frame_and_smooths_a_step() -> None:
    rng = np.random.default_rng(6)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (100, 140, 3)).astype(np.float32), (0, 0), 2)
    blender = LaplacianBlender(180, 240, 3, levels=4)
    blender.add(image, np.ones((100, 140), np.float32), 37, 41)
    np.testing.assert_allclose(blender.render()[41:141, 37:177], image, atol=1e-3)
    # two flat frames meeting at a hard seam (weights 1 | 0 from column 70 on): the levels
    # blend the step over ~2^levels px instead of leaving it in one pixel
    blender = LaplacianBlender(60, 140, 1, levels=4)
    left, right = np.zeros((60, 140), np.float32), np.zeros((60, 140), np.float32)
    left[:, :70], right[:, 70:] = 1, 1
    blender.add(np.full((60, 140), 100, np.float32), left + 1e-6, 0, 0)
    blender.add(np.full((60, 140), 140, np.float32), right + 1e-6, 0, 0)
    row = blender.render()[30, :, 0]
    assert row[5] == pytest.approx(100, abs=1) and row[-5] == pytest.approx(140, abs=1)
    assert np.abs(np.diff(row)).max() < 8  # a hard seam would step by 40


def test_fill_invalid_extends_the_valid_pixels_smoothly() -> None:
    image = np.zeros((40, 60), np.float32)
    valid = np.zeros((40, 60), bool)
    valid[10:30, 10:40] = True
    image[valid] = 80
    filled = fill_invalid(image, valid)
    assert np.all(filled[valid] == 80)
    np.testing.assert_allclose(filled, 80, atol=1)  # a constant stays constant outside


# ------------------------------------------------------------------------------ end to end


def test_striped_side_bands_stay_out_of_the_built_mosaic(tmp_path) -> None:
    from mosaic.config import Config, with_overrides
    from mosaic.synthetic.synth import SynthParams, write_synthetic_video
    from tests.conftest import SAMPLE_IMAGE
    from tests.helpers import build_from_folder

    folder = tmp_path / "frames"
    params = SynthParams(n_frames=16, size=(320, 240), seed=4, nuisances=False, aperture=False)
    write_synthetic_video(SAMPLE_IMAGE, folder, params)
    rng = np.random.default_rng(7)
    for path in sorted(folder.glob("*.png")):
        image = cv2.imread(str(path))
        image[:, :16] = _striped(240, 16, rng)[..., None].astype(np.uint8)
        image[:, -10:] = _striped(240, 10, rng)[..., None].astype(np.uint8)
        cv2.imwrite(str(path), image)

    def stripes(config: Config) -> float:
        """Row-to-row alternation (|2 I(y) - I(y-1) - I(y+1)|) of the mosaic's green."""
        result = build_from_folder(folder, config)
        assert result.report.to_dict()["summary"]["registered"] == 16
        g = result.main.image[..., 1].astype(np.float32)
        covered = result.main.image.any(axis=2)
        inner = cv2.erode(covered.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        alternation = np.abs(2 * g[1:-1] - g[:-2] - g[2:])
        return float(alternation[inner[1:-1]].mean())

    base = with_overrides(Config(), features={"detector": "sift"})
    with_bands = stripes(with_overrides(base, compose={"side_bands": False}))
    without = stripes(base)
    assert without < 0.6 * with_bands, (without, with_bands)
