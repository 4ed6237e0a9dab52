"""Pair and video evaluation end to end, against fixtures whose ground truth is known."""

from __future__ import annotations

import csv
import json
import math
import shutil

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from glampoints.cli import app as glampoints_app
from glampoints.metrics import point_errors
from mosaic.cli import app as mosaic_app
from mosaic.config import Config, with_overrides
from mosaic.datasets import Pair
from mosaic.errors import ConfigError
from mosaic.evaluate import (
    _leading_accurate,
    _video_errors,
    evaluate_pair,
    make_extractors,
    parse_detectors,
    scale_matrix,
)
from mosaic.io import sample_image_path
from mosaic.synth import SynthParams, relative_homographies, write_synthetic_video
from tests.mosaic.test_datasets import make_fire_fixture

runner = CliRunner()


def test_scale_matrix_maps_pixel_centres():
    S = scale_matrix((100, 200), (50, 100))  # half size: pixel centres 0, 1 -> -0.25, 0.25
    np.testing.assert_allclose(S @ [0, 0, 1], [-0.25, -0.25, 1])
    np.testing.assert_allclose(S @ [199, 99, 1], [99.25, 49.25, 1])


def test_parse_detectors():
    assert parse_detectors(None)[:3] == ["glampoints", "sift", "orb"]
    assert parse_detectors(" sift, orb,sift ") == ["sift", "orb"]
    with pytest.raises(ConfigError, match="unknown detector surf"):
        parse_detectors("sift,surf")


def test_glampoints_without_weights_is_skipped(tmp_path, caplog):
    config = with_overrides(Config(), features={"weights": str(tmp_path / "missing.pt")})
    built = make_extractors(config, ["glampoints", "sift"])
    assert list(built) == ["sift"]
    assert "skipping detector glampoints" in caplog.text
    with pytest.raises(ConfigError, match="none of the detectors"):
        make_extractors(config, ["glampoints"])


def test_identity_pair_scores_perfectly(fundus):
    image = fundus[500:700, 500:740]
    pair = Pair("same", "", image, image.copy(), np.eye(3))
    config, extractor = make_extractors(Config(), ["sift"])["sift"]
    result = evaluate_pair(pair, config, extractor)
    assert result.repeatability == 1.0
    assert result.n_true_positives == result.n_matches > 100
    assert result.matching_score >= 0.95
    assert result.status == "acceptable"
    assert result.mee_px < 1e-3 and result.error_px < 1e-3
    assert result.coverage > 0.9


def test_fire_layout_end_to_end(tmp_path, fundus):
    """`glampoints evaluate` on a FIRE-layout fixture: two good pairs, one that must fail."""
    truth = make_fire_fixture(tmp_path / "FIRE", fundus)
    out = tmp_path / "out"
    args = ["evaluate", str(tmp_path / "FIRE"), "--format", "fire", "--detector", "sift,orb"]
    result = runner.invoke(glampoints_app, [*args, "--scale", "0.5", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "AUC S" in result.output and "sift" in result.output
    for name in ("summary.csv", "pairs.csv", "summary.json", "cumulative_error.png"):
        assert (out / name).stat().st_size > 0
    assert (out / "success_rates.png").read_bytes()[:4] == b"\x89PNG"

    document = json.loads((out / "summary.json").read_text())
    assert document["meta"]["scale"] == 0.5
    summary = {row["detector"]: row for row in document["summary"]}
    sift = summary["sift"]
    assert sift["failed_pct"] == pytest.approx(100 / 3)  # A01: featureless second image
    assert sift["acceptable_pct"] == pytest.approx(200 / 3)
    assert sift["auc_A"] == 0.0
    assert sift["auc_S"] >= 0.9 and sift["auc_P"] >= 0.9
    assert sift["mauc"] == pytest.approx((sift["auc_S"] + sift["auc_P"]) / 3)
    assert sift["repeatability"] > 0.5 and sift["coverage"] > 0.3

    # each pair's FIRE error is the control points' error of its homography, at full resolution
    for row in document["pairs"]:
        points = truth[row["pair"]]
        if row["status"] == "failed":
            assert row["error_px"] == "inf" and row["H_est_1_to_2"] is None
            continue
        H_2_to_1 = np.linalg.inv(np.array(row["H_est_1_to_2"]))
        errors = point_errors(H_2_to_1, points[:, 2:], points[:, :2])
        assert row["error_px"] == pytest.approx(errors.mean(), abs=1e-3)  # files: 4 decimals
        if row["detector"] == "sift":
            assert row["error_px"] < 2.0  # px at full resolution (320 px images)
    with (out / "pairs.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 6 and {r["detector"] for r in rows} == {"sift", "orb"}


def test_hpatches_style_pair_uses_six_fixed_points(fundus):
    image = fundus[450:650, 450:690]
    H = np.array([[1.0, 0.02, 5.0], [-0.02, 1.0, -3.0], [0.0, 0.0, 1.0]])
    warped = cv2.warpPerspective(image, H, (image.shape[1], image.shape[0]))
    config, extractor = make_extractors(Config(), ["sift"])["sift"]
    result = evaluate_pair(Pair("h", "v", image, warped, H), config, extractor)
    assert result.status == "acceptable"
    assert result.mee_px < 1.0 and result.rmse_px < 1.0
    # full and detection resolution are the same at scale 1
    assert result.error_px == pytest.approx(result.rmse_px, abs=0.5)


def test_video_errors_and_frames_until_failure_by_hand():
    gt = [np.eye(3), np.array([[1, 0, 10.0], [0, 1, 0], [0, 0, 1]]), np.eye(3), np.eye(3)]
    rel = relative_homographies(gt)
    canvas = np.array([[1, 0, 50.0], [0, 1, 20.0], [0, 0, 1]])  # H_ref_to_canvas
    off = np.array([[1, 0, 0], [0, 1, 12.0], [0, 0, 1]])  # 12 px wrong in y
    frames = [
        {"index": 0, "status": "registered", "segment": 0, "H_to_canvas": canvas.tolist()},
        {
            "index": 1,
            "status": "registered",
            "segment": 0,
            "H_to_canvas": (canvas @ rel[1]).tolist(),
        },
        {"index": 2, "status": "skipped", "segment": None, "H_to_canvas": None},
        {"index": 3, "status": "registered", "segment": 0, "H_to_canvas": (canvas @ off).tolist()},
    ]
    errors = _video_errors(frames, gt, (40, 30))
    assert errors == pytest.approx({0: 0.0, 1: 0.0, 3: 12.0})
    assert _leading_accurate(frames, errors) == 2  # frame 3 is off by more than 10 px
    assert _leading_accurate(frames, None) == 3  # without ground truth: registration only
    frames[1]["status"] = "failed"
    assert _leading_accurate(frames, errors) == 1


@pytest.fixture(scope="module")
def small_video(tmp_path_factory):
    """Six clean 240x160 frames with exact ground truth, as a folder of PNGs."""
    root = tmp_path_factory.mktemp("videos")
    params = SynthParams(n_frames=6, size=(240, 160), seed=5, nuisances=False, max_step_px=6.0)
    write_synthetic_video(sample_image_path(), root / "clip", params)
    return root / "clip"


def test_video_evaluation_end_to_end(small_video, tmp_path):
    no_truth = tmp_path / "copy"
    shutil.copytree(small_video, no_truth)
    out = tmp_path / "out"
    args = ["evaluate", str(small_video), str(no_truth), "--detector", "sift", "--out", str(out)]
    result = runner.invoke(mosaic_app, args)
    assert result.exit_code == 0, result.output
    assert "Mean over videos" in result.output
    document = json.loads((out / "video_evaluation.json").read_text())
    # Both strategies side by side (the default), per video.
    assert [v["detector"] for v in document["videos"]] == ["sift/keyframes", "sift/chain"] * 2
    assert [row["detector"] for row in document["summary"]] == ["sift/keyframes", "sift/chain"]
    with_truth, without = (v for v in document["videos"] if v["detector"] == "sift/keyframes")
    assert with_truth["has_ground_truth"] and not without["has_ground_truth"]
    assert with_truth["frames"] == 6 and with_truth["registered"] == 6
    assert with_truth["frames_until_failure"] == 6
    assert with_truth["registered_fraction"] == 1.0 and with_truth["accurate_fraction"] == 1.0
    assert with_truth["mean_error_px"] < 2.0
    assert abs(with_truth["drift_px_per_frame"]) < 1.0
    assert [i for i, _ in with_truth["errors"]] == list(range(6))
    assert without["frames_until_failure"] == without["frames_until_failure_pipeline"] == 6
    assert without["mean_error_px"] is None  # nan: nothing to compare with
    for name in ("videos.csv", "video_summary.csv", "video_frames_until_failure.png"):
        assert (out / name).stat().st_size > 0
    assert (out / "video_error.png").read_bytes()[:4] == b"\x89PNG"
    assert math.isclose(document["summary"][0]["frames_until_failure"], 6.0)


def test_video_evaluation_reports_user_errors(tmp_path):
    result = runner.invoke(mosaic_app, ["evaluate", str(tmp_path / "nope.mp4")])
    assert result.exit_code == 2
    assert "error: input not found" in result.output
    result = runner.invoke(glampoints_app, ["evaluate", str(tmp_path), "--detector", "surf"])
    assert result.exit_code == 2
    assert "unknown detector surf" in result.output
