"""Mosaic fidelity (issue 16) against ground truth: a source photograph warped into a canvas
by a known homography is the perfect mosaic; shifts and blur must cost, gain must not."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mosaic.eval.fidelity import (
    FidelityScores,
    fit_canvas_to_source,
    fit_homography,
    footprints_mask,
    highpass,
    local_ncc,
    mean_mosaic_fidelity,
    mosaic_fidelity,
    oracle_fidelity,
    prepare_source,
    transform,
)
from mosaic.geometry import corner_error
from mosaic.preprocess import field_of_view_mask
from mosaic.synthetic.synth import SynthParams, render_frames

CANVAS = (300, 240)  # (width, height)
FRAME = (120, 90)


def _translation(x: float, y: float) -> np.ndarray:
    return np.array([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def source_image(fundus) -> np.ndarray:
    """The shipped fundus photograph at 360x360 (black border around the view included)."""
    return cv2.resize(fundus, (360, 360), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope="module")
def scene(source_image):
    """A perfect mosaic: the source warped into a 300x240 canvas by a known canvas-to-source
    homography (similarity and a little perspective), tiled by 16 frames of 120x90."""
    a, s = np.deg2rad(8.0), 0.75
    H_c2s = np.array(
        [
            [s * np.cos(a), -s * np.sin(a), 70.0],
            [s * np.sin(a), s * np.cos(a), 60.0],
            [2e-5, 1e-5, 1.0],
        ]
    )
    poses = {
        k: _translation(x, y)
        for k, (x, y) in enumerate((x, y) for y in (0, 50, 100, 150) for x in (0, 60, 120, 180))
    }
    truth = [H_c2s @ poses[k] for k in range(len(poses))]
    w, h = CANVAS
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    mosaic = cv2.warpPerspective(source_image, H_c2s, (w, h), flags=flags)
    return {
        "H_c2s": H_c2s,
        "poses": poses,
        "truth": truth,
        "mosaic": mosaic,
        "content": np.ones((h, w), bool),
        "source": prepare_source(source_image),
    }


def _score(scene, mosaic=None, content=None) -> FidelityScores:
    return mosaic_fidelity(
        scene["mosaic"] if mosaic is None else mosaic,
        scene["content"] if content is None else content,
        scene["poses"],
        scene["truth"],
        scene["source"],
        FRAME,
        range(len(scene["truth"])),
    )


def test_the_source_itself_scores_one(scene):
    scores = _score(scene)
    assert scores.fidelity > 0.99
    assert scores.good_area == 1.0


def test_shifted_or_blurred_mosaics_score_lower(scene):
    w, h = CANVAS
    perfect = _score(scene)

    def shifted(dx: float) -> FidelityScores:
        M = np.float32([[1, 0, dx], [0, 1, 0]])
        return _score(scene, cv2.warpAffine(scene["mosaic"], M, (w, h)))

    one, two, four = shifted(1), shifted(2), shifted(4)
    # measured: 0.87 / 0.65 / 0.31, good area 0.99 / 0.78 / 0.29
    assert 0.80 < one.fidelity < 0.92 and 0.55 < two.fidelity < 0.72 and four.fidelity < 0.40
    assert two.good_area < 0.85 and four.good_area < 0.40
    blurred = _score(scene, cv2.GaussianBlur(scene["mosaic"], (0, 0), 3.0))
    assert blurred.fidelity < perfect.fidelity - 0.2  # measured 0.73


def test_gain_and_vignetting_do_not_count(scene):
    w, h = CANVAS
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) / w) ** 2 + ((yy - h / 2) / h) ** 2
    light = 0.6 * (1.0 - 0.8 * r2)  # 40 % darker, 20 % more at the corners
    dimmed = np.clip(scene["mosaic"] * light[..., None] + 20.0, 0, 255).astype(np.uint8)
    scores = _score(scene, dimmed)
    assert scores.fidelity > _score(scene).fidelity - 0.03  # measured 0.975 against 0.995
    assert scores.good_area == 1.0


def test_uncovered_retina_is_not_good(scene):
    content = scene["content"].copy()
    content[:, : CANVAS[0] // 2] = False
    mosaic = scene["mosaic"] * content[..., None]
    scores = _score(scene, mosaic, content)
    assert scores.fidelity > 0.98  # what is there is right
    assert scores.good_area == pytest.approx(0.5, abs=0.01)  # half the scanned retina is missing


def test_fit_recovers_a_known_canvas_to_source_homography(scene):
    poses, truth, H_c2s = scene["poses"], scene["truth"], scene["H_c2s"]
    H = fit_canvas_to_source(list(poses.values()), truth, FRAME)
    assert np.allclose(H, H_c2s / H_c2s[2, 2], atol=1e-9)

    # One frame of 16 misplaced by 15 px: the soft-L1 fit keeps the map within 0.4 px over the
    # canvas (measured 0.33), plain least squares is pulled 2.2 px.
    bad = dict(poses)
    bad[5] = _translation(15.0, 0.0) @ poses[5]
    H = fit_canvas_to_source(list(bad.values()), truth, FRAME)
    H_inv, H_true_inv = np.linalg.inv(H), np.linalg.inv(H_c2s)
    assert corner_error(H_inv, H_true_inv, CANVAS) < 0.4
    plain, _ = cv2.findHomography(
        np.concatenate([transform(bad[k], _grid()) for k in bad]),
        np.concatenate([transform(truth[k], _grid()) for k in bad]),
        0,
    )
    assert corner_error(np.linalg.inv(plain), H_true_inv, CANVAS) > 1.5


def _grid() -> np.ndarray:
    w, h = FRAME
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 5))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def test_fit_homography_on_perspective_points():
    rng = np.random.default_rng(0)
    H_true = np.array([[1.3, 0.2, -40.0], [-0.1, 0.9, 25.0], [4e-4, -2e-4, 1.0]])
    src = rng.uniform(0, 500, (60, 2))
    H = fit_homography(src, transform(H_true, src))
    assert np.abs(transform(H, src) - transform(H_true, src)).max() < 1e-6
    with pytest.raises(ValueError):
        fit_homography(src[:3], src[:3])


def test_local_ncc_is_gain_invariant_and_masked():
    rng = np.random.default_rng(1)
    a = cv2.GaussianBlur(rng.normal(0, 20, (80, 80)).astype(np.float32), (0, 0), 1.5)
    valid = np.ones(a.shape, bool)
    valid[:, 60:] = False
    b = np.where(valid, 3.0 * a + 5.0, 1000.0)  # garbage where invalid
    ncc, defined = local_ncc(a, b, valid)
    assert defined[:, :60].all() and not defined[:, 60:].any()
    assert ncc[defined].min() > 0.999
    ncc, _ = local_ncc(a, -a, valid)
    assert ncc[defined].max() < -0.995  # the variance floor (0.01 grey levels²) costs a little


def test_highpass_ignores_pixels_outside_the_mask():
    gray = np.full((60, 80), 120.0, np.float32)
    gray[:, :20] = 0.0  # a black border: outside
    valid = np.ones(gray.shape, bool)
    valid[:, :20] = False
    hp = highpass(gray, valid)
    assert np.abs(hp).max() < 1e-3  # no edge at the border


def test_source_field_of_view_excludes_the_black_border(source_image):
    fov = prepare_source(source_image).fov
    assert fov[0, 0] == 0 and fov[180, 180] == 255
    assert 0.6 < (fov > 0).mean() < 0.85


def test_oracle_beats_a_misposed_mean(fundus):
    """Frames of a clean synthetic video placed by the truth score high; the same frames each
    placed 3 px off (sigma) score clearly lower."""
    params = SynthParams(n_frames=8, size=(200, 140), seed=3, nuisances=False, max_step_px=8.0)
    source = cv2.resize(fundus, (600, 600), interpolation=cv2.INTER_AREA)
    rendered = list(render_frames(source, params))
    truth = [H for _, H in rendered]
    truth_source = prepare_source(source)

    def frames():
        return ((i, frame) for i, (frame, _) in enumerate(rendered))

    def mask_of(image):
        return field_of_view_mask(image[..., 1], 12, 6)

    oracle = oracle_fidelity(frames(), truth, truth_source, mask_of)
    assert oracle.fidelity > 0.8 and oracle.good_area > 0.7  # measured 0.87 / 0.78

    rng = np.random.default_rng(0)
    G0_inv = np.linalg.inv(truth[0])
    off = {}
    for i, G in enumerate(truth):
        dx, dy = rng.normal(0.0, 3.0, 2)
        off[i] = G0_inv @ G @ _translation(dx, dy)
    misposed = mean_mosaic_fidelity(frames(), off, truth, truth_source, mask_of)
    assert misposed.fidelity < oracle.fidelity - 0.15  # measured 0.62 / 0.62
    assert misposed.good_area < oracle.good_area


def test_no_posed_frame_gives_nan(scene):
    scores = mosaic_fidelity(
        scene["mosaic"], scene["content"], {}, scene["truth"], scene["source"], FRAME, range(3)
    )
    assert math.isnan(scores.fidelity) and math.isnan(scores.good_area)


def test_footprints_mask_is_the_union_of_quads():
    quads = [transform(_translation(10, 10), np.array([[0, 0], [19, 0], [19, 9], [0, 9]]))]
    quads.append(quads[0] + [30, 0])
    mask = footprints_mask(quads, (40, 80))
    assert mask.sum() == 2 * 20 * 10
    assert mask[15, 15] and not mask[15, 35]
