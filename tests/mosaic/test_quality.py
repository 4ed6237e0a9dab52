"""Per-frame quality without ground truth: a frame's agreement with the mosaic under it, checked
against frames placed at their true poses and at known offsets from them."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from mosaic.canvas import Canvas
from mosaic.config import ComposeConfig, Config, PreprocessConfig, with_overrides
from mosaic.io import open_frames
from mosaic.preprocess import prepare
from mosaic.quality import agreement, frame_vs_canvas, score_vs_error, shift_response
from mosaic.synthetic.synth import SynthParams, render_frames, write_synthetic_video
from mosaic.synthetic.truth import load_ground_truth
from tests.conftest import SAMPLE_IMAGE
from tests.helpers import build_from_folder

THRESHOLD = ComposeConfig().quality_threshold
N_PLACED = 4  # frames on the canvas before the scored one


def translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def scene(fundus):
    """A canvas of synthetic frames (illumination drift, vignetting, noise) at their true poses
    in frame 0's pixels, and the next frame with its true pose and field-of-view mask."""
    params = SynthParams(n_frames=N_PLACED + 1, seed=7)
    frames = list(render_frames(fundus, params))
    G0_inv = np.linalg.inv(frames[0][1])
    canvas = Canvas(ComposeConfig())
    for image, H_to_source in frames[:N_PLACED]:
        canvas.add(image, G0_inv @ H_to_source, prepare(image, PreprocessConfig()).mask)
    image, H_to_source = frames[N_PLACED]
    return canvas, image, G0_inv @ H_to_source, prepare(image, PreprocessConfig()).mask


def test_a_frame_at_its_true_pose_agrees_with_the_mosaic(scene):
    canvas, image, H, mask = scene
    assert frame_vs_canvas(canvas, image, H, mask) > 0.85
    # without the mask the frame's dark corners disagree with the mosaic: the median holds
    assert frame_vs_canvas(canvas, image, H) > 0.85


@pytest.mark.parametrize("offset_px", [10.0, 15.0])
def test_a_frame_placed_off_scores_clearly_lower(scene, offset_px):
    canvas, image, H, mask = scene
    true_score = frame_vs_canvas(canvas, image, H, mask)
    for angle in np.radians([0, 90, 135, 250]):
        T = translation(offset_px * np.cos(angle), offset_px * np.sin(angle))
        score = frame_vs_canvas(canvas, image, T @ H, mask)
        assert score < THRESHOLD, (angle, score)  # flagged at the default threshold
        assert score < true_score - 0.5, (angle, score)


def test_a_few_pixels_off_is_not_flagged(scene):
    canvas, image, H, mask = scene
    scores = [frame_vs_canvas(canvas, image, translation(3 * c, 3 * s) @ H, mask)
              for c, s in ((1, 0), (0, 1), (-0.6, 0.8))]  # fmt: skip
    assert min(scores) > THRESHOLD, scores
    assert max(scores) < frame_vs_canvas(canvas, image, H, mask)  # but it does fall


def test_gain_gamma_and_vignetting_of_the_frame_do_not_count(scene):
    canvas, image, H, mask = scene
    h, w = image.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((xs - 0.3 * w) ** 2 + (ys - 0.6 * h) ** 2) / (w**2 + h**2)
    vignette = (1.0 - 1.2 * r2)[..., None]
    changed = 255.0 * (0.6 * image.astype(np.float32) / 255.0) ** 1.8 * vignette
    changed = np.clip(changed + 0.5, 0, 255).astype(np.uint8)
    assert changed.mean() < 0.5 * image.mean()  # a much darker, uneven frame
    base = frame_vs_canvas(canvas, image, H, mask)
    score = frame_vs_canvas(canvas, changed, H, mask)
    assert score > 0.8
    assert abs(score - base) < 0.1


def test_no_overlap_or_no_texture_gives_no_score(scene):
    canvas, image, H, mask = scene
    assert math.isnan(frame_vs_canvas(canvas, image, translation(5000, 0) @ H, mask))
    assert math.isnan(frame_vs_canvas(Canvas(ComposeConfig()), image, H, mask))
    flat = np.full_like(image, 120)
    assert math.isnan(frame_vs_canvas(canvas, flat, H, mask))
    assert math.isnan(frame_vs_canvas(canvas, image, H, np.zeros_like(mask)))
    # a sliver of overlap: too little to judge
    w = image.shape[1]
    assert math.isnan(frame_vs_canvas(canvas, image, translation(w - 20, 0) @ H, mask))


def test_agreement_of_an_image_with_itself_and_with_its_negative():
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.normal(0, 40, (120, 160)).astype(np.float32), (0, 0), 2.0)
    image = np.clip(128 + noise, 0, 255)
    valid = np.ones(image.shape, bool)
    assert agreement(image, image, valid) == pytest.approx(1.0, abs=1e-4)
    assert agreement(image, 255 - image, valid) == pytest.approx(-1.0, abs=1e-4)
    assert agreement(image, 3 * image + 10, valid) == pytest.approx(1.0, abs=1e-4)
    unrelated = np.roll(image, 40, axis=1)
    assert abs(agreement(image, unrelated, valid)) < 0.3
    with pytest.raises(ValueError):
        agreement(image, image[:-1], valid)


# ------------------------------------------------------------------------------ pipeline

SIZE = (400, 300)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A short clean synthetic video through the pipeline (SIFT, keyframes, re-rendered)."""
    folder = tmp_path_factory.mktemp("quality") / "frames"
    params = SynthParams(n_frames=16, size=SIZE, seed=3, nuisances=False)
    gt = load_ground_truth(write_synthetic_video(SAMPLE_IMAGE, folder, params))
    result = _build(folder, with_overrides(Config(), features={"detector": "sift"}))
    return folder, gt, result.report.to_dict()


def _build(folder: Path, config: Config):
    return build_from_folder(folder, config)


def test_report_scores_every_registered_frame_but_the_first(built):
    _, gt, report = built
    frames = report["frames"]
    assert all(f["status"] == "registered" for f in frames)
    assert report["summary"]["tracking"]["rerendered"]  # scored again at the refined poses
    assert frames[0]["quality"] is None and frames[0]["flagged"] is False
    scores = [f["quality"] for f in frames[1:]]
    assert all(s is not None and 0.8 < s <= 1.0 for s in scores), scores
    assert not any(f["flagged"] for f in frames)
    summary = report["summary"]
    assert summary["quality"] == pytest.approx(float(np.median(scores)), abs=1e-3)
    assert summary["quality_flagged"] == 0
    assert report["config"]["compose"]["quality_threshold"] == THRESHOLD

    analysis = score_vs_error(report, gt, SIZE)
    assert analysis["n_frames"] == len(frames) - 1
    assert analysis["corner"]["false_flags"] == analysis["misalignment"]["false_flags"] == 0
    assert max(row[3] for row in analysis["frames"]) < 2.0  # misalignment, px


def test_frames_under_the_threshold_are_flagged(built):
    folder, _, report = built
    strict = with_overrides(
        Config(), features={"detector": "sift"}, compose={"quality_threshold": 1.0}
    )
    flagged = _build(folder, strict).report.to_dict()
    assert [f["flagged"] for f in flagged["frames"]] == [False] + [True] * (
        len(report["frames"]) - 1
    )
    assert flagged["summary"]["quality_flagged"] == len(report["frames"]) - 1


def test_shifting_reported_poses_drops_the_score(built):
    folder, _, report = built
    with open_frames(folder) as frames:
        scores = shift_response(((f.index, f.image) for f in frames), report, (0.0, 15.0))
    assert len(scores[0.0]) == len(report["frames"]) - 1
    assert (scores[0.0] > 0.8).all(), scores[0.0]
    assert (scores[15.0] < THRESHOLD).all(), scores[15.0]
