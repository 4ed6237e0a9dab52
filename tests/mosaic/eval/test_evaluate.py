"""Pair and video evaluation end to end, against fixtures whose ground truth is known."""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import shutil

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from glampoints.metrics import point_errors
from mosaic.cli import app as mosaic_app
from mosaic.config import Config, with_overrides
from mosaic.errors import ConfigError, InputError
from mosaic.eval.datasets import Pair
from mosaic.eval.evaluate import (
    FIRE_VARIANTS,
    VideoResult,
    _frame_references,
    _leading_accurate,
    _model_counts,
    _quality_vs_error,
    _step_errors,
    _unique_stems,
    _video_errors,
    compare_methods,
    evaluate_pair,
    evaluate_video,
    format_models,
    format_video_tables,
    load_video_results,
    make_extractors,
    parse_detectors,
    read_answers,
    scale_matrix,
    score_answers,
    summarize_videos,
    warn_of_precisions,
    write_video_outputs,
)
from mosaic.features import FeatureExtractor
from mosaic.geometry import relative_homographies
from mosaic.glampoints_cli import app as glampoints_app
from mosaic.io import sample_image_path
from mosaic.synthetic.curved import write_fire_folder
from mosaic.synthetic.synth import (
    SynthParams,
    gt_path_for,
    load_ground_truth,
    write_synthetic_video,
)
from tests.helpers import leaving_clip
from tests.mosaic.eval.test_datasets import make_fire_fixture

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
    # repeatability measured 0.498 (0.5+ before the 12 px border margin dropped more points)
    assert sift["repeatability"] > 0.45 and sift["coverage"] > 0.3

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


def test_fire_table_on_curved_pairs_ranks_the_models_against_the_truth(tmp_path):
    """`glampoints evaluate --format fire` on two curved pairs (exact control points) at the
    paper's scale: one row per detector and model, the same matches fitted four ways."""
    write_fire_folder([sample_image_path()], tmp_path / "curved", 2, seed=0, size=1024)
    out = tmp_path / "out"
    args = ["evaluate", str(tmp_path / "curved"), "--format", "fire", "--detector", "sift"]
    result = runner.invoke(glampoints_app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "FIRE protocol per model" in result.output and "quad+refine" in result.output

    document = json.loads((out / "summary.json").read_text())
    assert document["meta"]["scale"] == 0.15
    models = {row["model"]: row for row in document["models"]}
    assert list(models) == list(FIRE_VARIANTS)
    hom, quad, best = models["hom"], models["quad"], models["quad+refine"]
    assert all(row["failed"] == 0 and row["pairs"] == 2 for row in models.values())
    # the curvature limits the homography to ~2 px at 1024 px; the quadratic removes it and
    # the refinement lowers its error again
    assert best["auc"] > hom["auc"] and best["auc_0_25"] > hom["auc_0_25"]
    assert hom["mean_error_px"] > 1.5 and best["mean_error_px"] < hom["mean_error_px"] / 5
    assert best["mean_error_px"] < quad["mean_error_px"] / 2 and best["mean_error_px"] < 0.4
    assert all(row["s_per_pair"] > 0 for row in models.values())
    with (out / "models.csv").open() as fh:
        assert [r["model"] for r in csv.DictReader(fh)] == list(FIRE_VARIANTS)
    assert (out / "cumulative_error_models.png").read_bytes()[:4] == b"\x89PNG"
    with (out / "pairs.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    errors = [float(r["error_px_quad+refine"]) for r in rows]
    assert np.mean(errors) == pytest.approx(best["mean_error_px"], rel=1e-3)


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


def _scored_frames(qualities, flagged):
    """Report entries 0..n: frame 0 the unscored reference, then the given scores and flags."""
    frames = [{"index": 0, "status": "registered", "quality": None, "flagged": False}]
    for i, (q, f) in enumerate(zip(qualities, flagged, strict=True), start=1):
        frames.append({"index": i, "status": "registered", "quality": q, "flagged": f})
    return frames


def test_quality_vs_error_by_hand():
    errors = {0: 0.0, 1: 1.0, 2: 3.0, 3: 8.0, 4: 12.0, 5: 20.0, 6: 40.0, 7: 50.0}
    # The score falls as the error grows; frame 7 (50 px off) has no score, so no flag either.
    qualities = [0.9, 0.8, 0.7, 0.6, 0.5, 0.4, None]
    flagged = [False, False, True, False, True, True, False]  # 3 good, 4 bad but missed
    check = _quality_vs_error(_scored_frames(qualities, flagged), errors)
    assert check["quality_rho"] == pytest.approx(-1.0)  # frames 1-6; 0 is the reference
    assert check["bad_frames"] == 4  # frames 4, 5, 6, 7 (> 10 px)
    assert check["bad_caught"] == pytest.approx(2 / 4)  # 5 and 6 flagged
    assert check["good_flagged"] == pytest.approx(1 / 3)  # 3 of the good frames 1, 2, 3

    # Ties and a frame scored high though far off: the rank correlation by hand.
    qualities = [0.9, 0.9, 0.7, 0.95, 0.5, 0.4, 0.3]
    check = _quality_vs_error(_scored_frames(qualities, [False] * 7), errors)
    rank_q = np.array([5.5, 5.5, 4, 7, 3, 2, 1])  # ties share the mean rank
    rank_e = np.arange(1, 8)
    assert check["quality_rho"] == pytest.approx(np.corrcoef(rank_q, rank_e)[0, 1])
    assert check["bad_caught"] == 0.0 and check["good_flagged"] == 0.0


def test_quality_vs_error_without_scores_or_truth():
    errors = {0: 0.0, 1: 2.0, 2: 15.0, 3: 30.0}
    older = [{"index": i, "status": "registered"} for i in range(4)]  # no "quality" keys
    check = _quality_vs_error(older, errors)
    assert check["bad_frames"] == 2
    assert all(math.isnan(check[k]) for k in ("quality_rho", "bad_caught", "good_flagged"))
    constant = _quality_vs_error(_scored_frames([0.5, 0.5, 0.5], [False] * 3), errors)
    assert math.isnan(constant["quality_rho"]) and constant["good_flagged"] == 0.0
    assert all(math.isnan(v) for v in _quality_vs_error(older, None).values())


def test_unique_stems(tmp_path):
    (tmp_path / "b").mkdir()
    (tmp_path / "clip.v2").mkdir()
    videos = [tmp_path / "a.mp4", tmp_path / "b" / "a.avi", tmp_path / "b" / "a.mp4"]
    assert _unique_stems([*videos, tmp_path / "clip.v2"]) == ["a", "a-2", "a-3", "clip.v2"]


def _rigid(angle_deg: float, tx: float, ty: float) -> np.ndarray:
    a = np.deg2rad(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, tx], [s, c, ty], [0, 0, 1.0]])


def _step_fixture():
    """Ten frames over two segments with exact poses, except frame 2 placed 8 px off in x.

    Returns (frames, gt, size, expected step errors): frame 3 is registered to frame 2 and frame
    5 to frame 2 (both inherit its 8 px), frame 6 to frame 0 (exact); frame 7 and 9 have no
    "reference" (older reports), so the previous registered frame of their segment stands in.
    """
    gt = [_rigid(2.0 * i, 7.0 * i, -3.0 * i) for i in range(10)]
    rel = relative_homographies(gt)
    canvas = [_rigid(0, 50.0, 20.0), _rigid(5.0, 400.0, 300.0)]  # per segment
    shift = _rigid(0, 8.0, 0)  # 8 px in frame 2's own pixels

    def entry(i, segment, reference, model, status="registered", off=None):
        pose = canvas[segment] @ np.linalg.solve(gt[8 if segment else 0], gt[i])
        pose = pose if off is None else pose @ off
        f = {"index": i, "status": status, "segment": segment, "H_to_canvas": pose.tolist()}
        if status != "registered":
            f.update(segment=None, H_to_canvas=None)
        if reference != "absent":
            f["reference"] = reference
        if model != "absent":
            f["model"] = model
        return f

    frames = [
        entry(0, 0, None, None),
        entry(1, 0, 0, "similarity"),
        entry(2, 0, 1, "similarity", off=shift),
        entry(3, 0, 2, "affine"),
        entry(4, 0, None, None, status="failed"),
        entry(5, 0, 2, "homography"),
        entry(6, 0, 0, "similarity"),
        entry(7, 0, "absent", "absent"),
        entry(8, 1, None, None),  # a new segment: no reference
        entry(9, 1, "absent", "translation"),
    ]
    np.testing.assert_allclose(frames[1]["H_to_canvas"], canvas[0] @ rel[1])
    expected = {1: 0.0, 2: 8.0, 3: 8.0, 5: 8.0, 6: 0.0, 7: 0.0, 9: 0.0}
    return frames, gt, (64, 48), expected


def test_step_errors_against_each_frames_reference():
    frames, gt, size, expected = _step_fixture()
    assert _frame_references(frames) == {1: 0, 2: 1, 3: 2, 5: 2, 6: 0, 7: 6, 9: 8}
    assert _step_errors(frames, gt, size) == pytest.approx(expected, abs=1e-9)
    # Frame -> first frame: only frame 2 is off; frames registered to it were placed right.
    errors = _video_errors(frames, gt, size)
    assert errors == pytest.approx({0: 0, 1: 0, 2: 8, 3: 0, 5: 0, 6: 0, 7: 0}, abs=1e-9)


def test_step_errors_of_older_reports_use_the_previous_frame():
    frames, gt, size, _ = _step_fixture()
    for f in frames:
        f.pop("reference", None)
        f.pop("model", None)
    assert _frame_references(frames) == {1: 0, 2: 1, 3: 2, 5: 3, 6: 5, 7: 6, 9: 8}
    steps = _step_errors(frames, gt, size)
    assert steps == pytest.approx({1: 0, 2: 8, 3: 8, 5: 0, 6: 0, 7: 0, 9: 0}, abs=1e-9)
    assert _model_counts(frames) == {
        "translation": 0,
        "similarity": 0,
        "affine": 0,
        "homography": 0,
    }


def test_model_counts_of_registered_frames():
    frames, _, _, _ = _step_fixture()
    frames[4]["model"] = "homography"  # frame 4 failed: not counted
    counts = _model_counts(frames)
    assert counts == {"translation": 1, "similarity": 3, "affine": 1, "homography": 1}
    assert format_models(counts) == "tra 1 / sim 3 / aff 1 / hom 1"
    assert format_models(dict.fromkeys(counts, 0)) is None


def _video_result(detector: str, **values) -> VideoResult:
    base = dict.fromkeys(
        ("registered_fraction", "accurate_fraction", "mean_error_px", "median_error_px"), 1.0
    )
    base.update(max_error_px=1.0, drift_px_per_frame=0.0, mean_inliers=50.0, fps=10.0)
    counts = dict(frames=10, registered=10, failed=0, skipped=0, frames_until_failure=10)
    return VideoResult(
        detector=detector,
        video=f"/videos/{detector.replace('/', '_')}.mp4",
        has_ground_truth=True,
        frames_until_failure_pipeline=10,
        **counts,
        **{**base, **values},
    )


def test_methods_are_compared_paired_over_the_same_videos(tmp_path):
    """12 videos that differ widely (accurate 0.2-1.0); sift is better on each by ~0.05, orb
    better on half and worse on half by 0.2. Pairing over videos puts sift's interval tight
    around its gain, orb's around 0."""
    rng = np.random.default_rng(3)
    base = rng.uniform(0.2, 0.8, 12)
    gain = 0.05 + rng.normal(0.0, 0.01, 12)
    results = []
    for i in range(12):
        video = f"/videos/v{i}.mp4"
        for method, accurate, error, until in (
            ("glampoints/keyframes", base[i], 5.0, 6),
            ("sift/keyframes", base[i] + gain[i], 4.0, 5),
            ("orb/keyframes", base[i] + (0.2 if i % 2 else -0.2), 5.0, 6),
        ):
            run = _video_result(method, accurate_fraction=accurate, mean_error_px=error)
            results.append(dataclasses.replace(run, video=video, frames_until_failure=until))
    results.append(_video_result("sift/keyframes"))  # a video the first method did not run
    sift, orb = compare_methods(results)
    assert sift["method"] == "sift/keyframes" and sift["against"] == "glampoints/keyframes"
    assert sift["videos"] == 12 and orb["videos"] == 12
    assert sift["accurate_fraction"] == pytest.approx(gain.mean())
    low, high = sift["accurate_fraction_low"], sift["accurate_fraction_high"]
    assert 0.04 < low < gain.mean() < high < 0.06  # the videos' own spread does not widen it
    assert sift["mean_error_px"] == pytest.approx(-1.0)
    assert sift["mean_error_px_low"] == pytest.approx(-1.0) == sift["mean_error_px_high"]
    assert sift["until_failure_share"] == pytest.approx(-0.1)
    assert orb["accurate_fraction"] == 0.0
    assert orb["accurate_fraction_low"] < -0.05 and orb["accurate_fraction_high"] > 0.05
    assert compare_methods(results) == compare_methods(results)  # seeded: the same each run

    text = format_video_tables(results, summarize_videos(results))
    assert "Paired over the same videos: mean difference [95 % bootstrap interval" in text
    line = next(x for x in text.splitlines() if x.startswith("sift/keyframes") and "[" in x)
    assert f"{gain.mean():+.3f} [{low:+.3f}, {high:+.3f}]" in line
    assert "-1.00 [-1.00, -1.00]" in line and "-0.000" not in text
    write_video_outputs(results, summarize_videos(results), tmp_path)
    with (tmp_path / "video_differences.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["method"] for r in rows] == ["sift/keyframes", "orb/keyframes"]
    assert float(rows[0]["accurate_fraction_low"]) == pytest.approx(low)
    document = json.loads((tmp_path / "video_evaluation.json").read_text())
    assert document["differences"][1]["method"] == "orb/keyframes"


def test_a_run_is_compared_with_an_earlier_one_video_by_video(tmp_path):
    """`--against`: the earlier run's results read back from its folder; each method paired
    with itself there over the videos both hold, matched by file name (the earlier run was
    started from another folder)."""
    before, after = [], []
    for i in range(6):
        run = _video_result("sift/keyframes", accurate_fraction=0.5 + 0.05 * i)
        before.append(dataclasses.replace(run, video=f"old/place/v{i}.mp4", quality_rho=math.nan))
        if i < 5:  # the last video is not in the new run
            better = dataclasses.replace(run, accurate_fraction=run.accurate_fraction + 0.1)
            after.append(dataclasses.replace(better, video=f"v{i}.mp4"))
    write_video_outputs(before, summarize_videos(before), tmp_path / "before")
    previous = load_video_results(tmp_path / "before")
    assert [r.video for r in previous] == [r.video for r in before]
    assert math.isnan(previous[0].quality_rho)  # JSON's null back to nan
    [row] = compare_methods(after, previous)
    assert row["against"] == "sift/keyframes (previous run)" and row["videos"] == 5
    assert row["accurate_fraction"] == pytest.approx(0.1)
    assert row["accurate_fraction_low"] == pytest.approx(0.1)
    text = format_video_tables(after, summarize_videos(after), previous)
    assert "sift/keyframes (previous run)" in text and "+0.100 [+0.100, +0.100]" in text

    with pytest.raises(InputError, match="not the output of `mosaic evaluate`"):
        load_video_results(tmp_path / "nothing here")
    bad = tmp_path / "bad.json"
    bad.write_text('{"videos": [{"detector": "x"}]}')
    with pytest.raises(InputError, match=r"bad\.json"):
        load_video_results(bad)
    result = CliRunner().invoke(
        mosaic_app, ["evaluate", str(tmp_path), "--against", str(tmp_path / "nothing here")]
    )
    assert result.exit_code == 2 and "not the output of `mosaic evaluate`" in result.output


def test_one_method_has_nothing_to_compare(tmp_path):
    results = [_video_result("sift/chain")]
    assert compare_methods(results) == []
    assert "paired" not in format_video_tables(results, summarize_videos(results))
    write_video_outputs(results, summarize_videos(results), tmp_path)
    assert not (tmp_path / "video_differences.csv").exists()
    assert json.loads((tmp_path / "video_evaluation.json").read_text())["differences"] == []


def test_video_tables_and_files_carry_step_errors_and_models(tmp_path):
    results = [
        _video_result(
            "sift/chain",
            step_median_px=1.0,
            step_p90_px=3.0,
            model_counts={"similarity": 8, "affine": 1, "homography": 0},
            quality_rho=-0.8,
            bad_frames=4.0,
            bad_caught=0.5,
            good_flagged=0.1,
        ),
        _video_result(
            "sift/chain",
            step_median_px=2.0,
            step_p90_px=5.0,
            model_counts={"similarity": 6, "homography": 3},
            quality_rho=-0.6,
            bad_frames=0.0,  # nothing to catch: bad_caught stays nan
            good_flagged=0.0,
        ),
        _video_result("orb/chain"),  # an older report: no references to score, no models
    ]
    summary = summarize_videos(results)
    sift, orb = summary
    assert sift["step_median_px"] == 1.5 and sift["step_p90_px"] == 4.0
    assert sift["model_similarity"] == 7.0 and sift["model_affine"] == 0.5
    assert sift["model_homography"] == 1.5 and sift["model_translation"] == 0.0
    assert math.isnan(orb["step_median_px"]) and orb["model_similarity"] == 0.0
    assert sift["quality_rho"] == pytest.approx(-0.7) and sift["bad_frames"] == 2.0
    assert sift["bad_caught"] == 0.5 and sift["good_flagged"] == pytest.approx(0.05)
    assert math.isnan(orb["quality_rho"]) and math.isnan(orb["bad_caught"])

    text = format_video_tables(results, summary)
    assert "step med px" in text and "step p90 px" in text
    assert "sim 8 / aff 1" in text and "sim 6 / hom 3" in text
    assert "sim 7.0 / aff 0.5 / hom 1.5" in text  # the mean over videos
    assert "quality rho" in text and "bad caught" in text and "good flagged" in text
    assert "-0.70" in text and "0.05" in text

    write_video_outputs(results, summary, tmp_path)
    with (tmp_path / "videos.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["step_p90_px"] for r in rows] == ["3", "5", ""]
    assert [r["model_similarity"] for r in rows] == ["8", "6", "0"]
    assert [r["model_translation"] for r in rows] == ["0", "0", "0"]
    assert [r["quality_rho"] for r in rows] == ["-0.8", "-0.6", ""]
    assert [r["bad_caught"] for r in rows] == ["0.5", "", ""]
    assert [r["good_flagged"] for r in rows] == ["0.1", "0", ""]
    assert "model_counts" not in rows[0] and "step_errors" not in rows[0]
    with (tmp_path / "video_summary.csv").open() as fh:
        assert next(csv.DictReader(fh))["model_homography"] == "1.5"
    document = json.loads((tmp_path / "video_evaluation.json").read_text())
    assert document["videos"][1]["model_counts"] == {"similarity": 6, "homography": 3}
    assert document["videos"][2]["model_counts"] == {}
    assert document["summary"][0]["step_median_px"] == 1.5
    assert document["summary"][0]["bad_caught"] == 0.5
    assert document["videos"][1]["bad_caught"] is None  # nan in JSON


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
    assert [i for i, _ in with_truth["step_errors"]] == list(range(1, 6))  # frame 0: no reference
    assert 0.0 <= with_truth["step_median_px"] <= with_truth["step_p90_px"] < 2.0
    assert sum(with_truth["model_counts"].values()) == 5  # frames 1..5; frame 0 has no model
    assert without["step_median_px"] is None and without["step_errors"] == []
    assert without["frames_until_failure"] == without["frames_until_failure_pipeline"] == 6
    assert without["mean_error_px"] is None  # nan: nothing to compare with
    for name in ("videos.csv", "video_summary.csv", "video_frames_until_failure.png"):
        assert (out / name).stat().st_size > 0
    assert (out / "video_error.png").read_bytes()[:4] == b"\x89PNG"
    assert math.isclose(document["summary"][0]["frames_until_failure"], 6.0)

    # Quality against the truth: a clean video has no bad frame to catch and none flagged.
    assert with_truth["bad_frames"] == 0 and with_truth["bad_caught"] is None
    assert with_truth["good_flagged"] == 0.0
    assert without["bad_frames"] is None and without["quality_rho"] is None

    # Every run's full report, named video stem, detector, strategy; the one that was scored.
    names = ["clip__sift__keyframes", "clip__sift__chain", "copy__sift__keyframes"]
    names.append("copy__sift__chain")
    assert document["meta"]["reports"] == [f"reports/{n}.json" for n in names]
    assert sorted(p.name for p in (out / "reports").iterdir()) == sorted(f"{n}.json" for n in names)
    report = json.loads((out / "reports" / "clip__sift__keyframes.json").read_text())
    assert report["input"]["path"] == str(small_video) and report["input"]["width"] == 240
    assert report["summary"]["strategy"] == "keyframes" and len(report["frames"]) == 6
    gt = load_ground_truth(gt_path_for(small_video))
    errors = _video_errors(report["frames"], gt, (240, 160))
    assert [[i, pytest.approx(e, abs=1e-3)] for i, e in sorted(errors.items())] == with_truth[
        "errors"
    ]
    check = _quality_vs_error(report["frames"], errors)
    assert check["good_flagged"] == 0.0 and check["bad_frames"] == 0


def test_video_evaluation_reports_user_errors(tmp_path):
    result = runner.invoke(mosaic_app, ["evaluate", str(tmp_path / "nope.mp4")])
    assert result.exit_code == 2
    assert "error: input not found" in result.output
    result = runner.invoke(glampoints_app, ["evaluate", str(tmp_path), "--detector", "surf"])
    assert result.exit_code == 2
    assert "unknown detector surf" in result.output


def _answer(name: str, model: str, H: np.ndarray, Q: np.ndarray | None = None) -> dict:
    return {
        "fixed": f"Images/{name}_1.jpg",
        "moving": f"Images/{name}_2.jpg",
        "status": "registered",
        "model": model,
        "H_moving_to_fixed": H.tolist(),
        "Q_moving_to_fixed": None if Q is None else Q.tolist(),
    }


def test_score_answers_applies_the_fire_protocol_to_register_answers(tmp_path):
    """Known answers on a FIRE folder whose truth is a shift of (10, -5): the exact answer
    scores 0 px, an answer 3-4-5 off scores 5 px, a pair without an answer is a miss."""
    root = tmp_path / "FIRE"
    (root / "Images").mkdir(parents=True)
    (root / "Ground Truth").mkdir()
    xy2 = np.random.default_rng(0).uniform(0, 300, (10, 2))
    for name in ("S01", "P01", "A01"):
        points = np.hstack([xy2 + np.array([10.0, -5.0]), xy2])
        np.savetxt(root / "Ground Truth" / f"control_points_{name}_1_2.txt", points)
    shift = np.array([[1.0, 0, 10], [0, 1, -5], [0, 0, 1]])
    Q_off = np.array([[0, 0, 0, 1.0, 0, 13], [0, 0, 0, 0, 1.0, -1]])  # (3, 4) off
    H_off = shift + np.array([[0, 0, 6], [0, 0, 8], [0, 0, 0]])  # (6, 8) off
    answers = [_answer("S01", "homography", shift), _answer("P01", "quadratic", H_off, Q_off)]
    path = tmp_path / "answers.jsonl"
    path.write_text("".join(json.dumps(a) + "\n" for a in answers))
    rows, summary = score_answers(root, read_answers(path))
    assert [(r["pair"], r["category"], r["status"]) for r in rows] == [
        ("A01", "A", "no answer"),
        ("P01", "P", "registered"),
        ("S01", "S", "registered"),
    ]
    np.testing.assert_allclose([r["answer_error_px"] for r in rows], [math.inf, 5, 0], atol=1e-9)
    np.testing.assert_allclose([r["H_error_px"] for r in rows], [math.inf, 10, 0], atol=1e-9)
    answer, homography = summary
    assert answer["failed"] == homography["failed"] == 1
    # AUC 1-25: 0 px is under all 25 thresholds, 5 px under 20 (t = 6..25), 10 px under 15
    assert answer["auc"] == pytest.approx((25 + 20) / 75)
    assert homography["auc"] == pytest.approx((25 + 15) / 75)
    assert (answer["auc_S"], answer["auc_P"], answer["auc_A"]) == (1.0, 0.8, 0.0)
    assert answer["mauc"] == pytest.approx(0.6)
    assert answer["mean_error_px"] == pytest.approx(2.5)  # of the pairs answered
    path.write_text("not json\n")
    with pytest.raises(InputError, match="line 1 is not JSON"):
        read_answers(path)


def test_register_answers_scored_by_glampoints_evaluate(tmp_path, fundus):
    """`mosaic register --pairs` on a FIRE folder, then `glampoints evaluate --answers`: the
    pairs with retina score within 2 px of the truth, the featureless one is a miss."""
    root = tmp_path / "FIRE"
    make_fire_fixture(root, fundus)
    names = ("S01", "P01", "A01")
    (root / "pairs.csv").write_text(
        "fixed,moving\n" + "".join(f"Images/{n}_1.jpg,Images/{n}_2.jpg\n" for n in names)
    )
    result = runner.invoke(
        mosaic_app, ["register", "--pairs", str(root / "pairs.csv"), "--detector", "sift"]
    )
    assert result.exit_code == 1  # A01 fails
    (tmp_path / "answers.jsonl").write_text(result.stdout)
    out = tmp_path / "scored"
    args = ["evaluate", str(root), "--answers", str(tmp_path / "answers.jsonl"), "--out", str(out)]
    result = runner.invoke(glampoints_app, args)
    assert result.exit_code == 0, result.output
    assert "H_moving_to_fixed" in result.stdout
    with (out / "answers_pairs.csv").open() as fh:
        rows = {r["pair"]: r for r in csv.DictReader(fh)}
    for name in ("S01", "P01"):
        assert rows[name]["status"] == "registered"
        assert float(rows[name]["answer_error_px"]) < 2.0
    assert rows["A01"]["status"] == "failed" and rows["A01"]["answer_error_px"] == "inf"
    with (out / "answers.csv").open() as fh:
        answer = next(csv.DictReader(fh))
    assert answer["failed"] == "1" and float(answer["auc"]) > 0.6
    # an answers file that is not one: one clear line, no traceback
    (tmp_path / "bad.jsonl").write_text('{"a": 1}\n')
    result = runner.invoke(
        glampoints_app, ["evaluate", str(root), "--answers", str(tmp_path / "bad.jsonl")]
    )
    assert result.exit_code == 2 and "not a `mosaic register --pairs` answer" in result.output
    assert "Traceback" not in result.output


def test_a_video_that_leaves_the_mapped_area_counts_every_segment_as_registered(tmp_path):
    """`registered` counts the frames of every segment; `accurate` and the errors are of the
    first placed frame's segment (the frames of the other area are placed, but not against the
    first frame)."""
    clip = leaving_clip(tmp_path, (400, 300))
    config = with_overrides(
        Config(), features={"detector": "sift"}, pipeline={"new_segment_after": 4}
    )
    result = evaluate_video(clip, config, FeatureExtractor(config.features), fidelity=False)
    assert result.segments == 2 and result.registered == 26
    assert result.registered_fraction == pytest.approx(26 / 28)
    assert result.accurate_fraction == pytest.approx(12 / 28)  # the first segment's 12 frames
    assert [i for i, _ in result.errors] == list(range(12)) and result.max_error_px < 3.0


def test_a_comparison_across_precisions_is_said(tmp_path, caplog):
    """GLAMpoints in float32 and in bfloat16 differ by tenths on single videos: a run compared
    with an earlier one in the other precision says so; the precision survives the JSON."""
    run = _video_result("glampoints/keyframes")
    before = [dataclasses.replace(run, precision="float32")]
    write_video_outputs(before, summarize_videos(before), tmp_path / "before")
    previous = load_video_results(tmp_path / "before")
    assert previous[0].precision == "float32"
    with caplog.at_level(logging.WARNING, logger="mosaic.eval.evaluate"):
        warn_of_precisions([dataclasses.replace(run, precision="float32")], previous)
        assert not caplog.records
        warn_of_precisions([dataclasses.replace(run, precision="bfloat16")], previous)
    assert "in bfloat16 here and in float32 in the earlier run" in caplog.text
