"""Video evaluation (`mosaic evaluate`) against synthetic ground truth: corner and step
errors, frames until failure, the quality score against the error, end to end."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from mosaic.cli import app as mosaic_app
from mosaic.config import Config, with_overrides
from mosaic.eval.video_eval import (
    _corner_errors,
    _frame_references,
    _leading_accurate,
    _placed_against_truth,
    _quality_vs_error,
    _step_errors,
    _unique_stems,
    _view_parts,
    evaluate_video,
)
from mosaic.eval.video_tables import (
    format_models,
)
from mosaic.features import FeatureExtractor
from mosaic.geometry import relative_homographies
from mosaic.glampoints_cli import app as glampoints_app
from mosaic.io import sample_image_path
from mosaic.report import BuildReport, FrameEntry
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from mosaic.synthetic.truth import gt_path_for, load_ground_truth
from tests.helpers import leaving_clip

runner = CliRunner()


def _entry(**fields) -> FrameEntry:
    """A report's frame entry with `fields` (index and status at least), the rest as read
    from a report that leaves them out."""
    unread = {"segment": 0, "H_to_canvas": None, "n_keypoints": 0, "n_matches": 0}
    unread |= {"n_inliers": 0, "reproj_error_px": None, "time_ms": 0.0}
    return FrameEntry.from_dict(unread | fields)


def test_video_errors_and_frames_until_failure_by_hand():
    gt = [np.eye(3), np.array([[1, 0, 10.0], [0, 1, 0], [0, 0, 1]]), np.eye(3), np.eye(3)]
    rel = relative_homographies(gt)
    canvas = np.array([[1, 0, 50.0], [0, 1, 20.0], [0, 0, 1]])  # H_ref_to_canvas
    off = np.array([[1, 0, 0], [0, 1, 12.0], [0, 0, 1]])  # 12 px wrong in y
    entries = [
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
    frames = [_entry(**e) for e in entries]
    errors = _corner_errors(list(_placed_against_truth(frames, gt)), (40, 30))
    assert errors == pytest.approx({0: 0.0, 1: 0.0, 3: 12.0})
    assert _leading_accurate(frames, errors) == 2  # frame 3 is off by more than 10 px
    assert _leading_accurate(frames, None) == 3  # without ground truth: registration only
    frames[1] = replace(frames[1], status="failed")
    assert _leading_accurate(frames, errors) == 1


def _scored_frames(qualities, flagged):
    """Report entries 0..n: frame 0 the unscored reference, then the given scores and flags."""
    frames = [_entry(index=0, status="registered", quality=None, flagged=False)]
    for i, (q, f) in enumerate(zip(qualities, flagged, strict=True), start=1):
        frames.append(_entry(index=i, status="registered", quality=q, flagged=f))
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
    older = [_entry(index=i, status="registered") for i in range(4)]  # no "quality" keys
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
        return _entry(**f)

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
    np.testing.assert_allclose(frames[1].H_to_canvas, canvas[0] @ rel[1])
    expected = {1: 0.0, 2: 8.0, 3: 8.0, 5: 8.0, 6: 0.0, 7: 0.0, 9: 0.0}
    return frames, gt, (64, 48), expected


def test_step_errors_against_each_frames_reference():
    frames, gt, size, expected = _step_fixture()
    assert _frame_references(frames) == {1: 0, 2: 1, 3: 2, 5: 2, 6: 0, 7: 6, 9: 8}
    assert _step_errors(frames, gt, size) == pytest.approx(expected, abs=1e-9)
    # Frame -> first frame: only frame 2 is off; frames registered to it were placed right.
    errors = _corner_errors(list(_placed_against_truth(frames, gt)), size)
    assert errors == pytest.approx({0: 0, 1: 0, 2: 8, 3: 0, 5: 0, 6: 0, 7: 0}, abs=1e-9)
    # taken apart: frame 2's 8 px are a shift (the same at the centre), no zoom, no roll
    parts = _view_parts(list(_placed_against_truth(frames, gt)), size)
    assert parts == pytest.approx(
        {"shift_error_px": 8 / 7, "zoom_error_pct": 0.0, "roll_error_deg": 0.0}, abs=1e-9
    )


def test_step_errors_of_older_reports_use_the_previous_frame():
    frames, gt, size, _ = _step_fixture()
    frames = [replace(f, reference=None, model=None) for f in frames]
    assert _frame_references(frames) == {1: 0, 2: 1, 3: 2, 5: 3, 6: 5, 7: 6, 9: 8}
    steps = _step_errors(frames, gt, size)
    assert steps == pytest.approx({1: 0, 2: 8, 3: 8, 5: 0, 6: 0, 7: 0, 9: 0}, abs=1e-9)


def test_format_models():
    counts = {"translation": 1, "similarity": 3, "affine": 1, "homography": 1}
    assert format_models(counts) == "tra 1 / sim 3 / aff 1 / hom 1"
    assert format_models(dict.fromkeys(counts, 0)) is None


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
    # the corner error taken apart. For a similarity error (shift s, zoom and roll z about the
    # centre) the corners move by s + z v_k, v_k their offsets (|v_k| = r, half the diagonal,
    # opposite in pairs), and |s + z v| + |s - z v| >= 2 max(|s|, |z| r): the centre's shift
    # and |z| r are each at most the corners' mean error, frame by frame (1 % slack for
    # these frames' little perspective)
    r = np.hypot(239, 159) / 2
    bound = 1.01 * with_truth["mean_error_px"]
    assert with_truth["shift_error_px"] <= bound
    assert with_truth["zoom_error_pct"] / 100 * r <= bound
    assert np.deg2rad(with_truth["roll_error_deg"]) * r <= bound
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
    frames = BuildReport.from_dict(report).frames
    errors = _corner_errors(list(_placed_against_truth(frames, gt)), (240, 160))
    assert [[i, pytest.approx(e, abs=1e-3)] for i, e in sorted(errors.items())] == with_truth[
        "errors"
    ]
    check = _quality_vs_error(frames, errors)
    assert check["good_flagged"] == 0.0 and check["bad_frames"] == 0


def test_video_evaluation_reports_user_errors(tmp_path):
    result = runner.invoke(mosaic_app, ["evaluate", str(tmp_path / "nope.mp4")])
    assert result.exit_code == 2
    assert "error: input not found" in result.output
    result = runner.invoke(glampoints_app, ["evaluate", str(tmp_path), "--detector", "surf"])
    assert result.exit_code == 2
    assert "unknown detector surf" in result.output


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
