"""`mosaic.report`: the typed report reads back what it writes, and reads reports written before
its newer keys existed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mosaic.config import Config, with_overrides
from mosaic.report import FAILED, REGISTERED, SKIPPED, BuildReport, read_report
from mosaic.runner import Outputs, run_video
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from tests.conftest import SAMPLE_IMAGE

SIFT = with_overrides(Config(), features={"detector": "sift"})
OLD_REPORT = Path(__file__).parent / "data" / "report_2026-12-01.json"  # 3 frames of the sample


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[BuildReport, Path]:
    """A build of a 10-frame clip (frames as PNGs, frame 4 unreadable), the report it returned
    and the file it wrote."""
    out = tmp_path_factory.mktemp("report")
    folder = out / "frames"
    params = SynthParams(n_frames=10, size=(200, 150), seed=2, max_step_px=4.0, nuisances=False)
    write_synthetic_video(SAMPLE_IMAGE, folder, params)
    sorted(folder.glob("*.png"))[4].write_bytes(b"not a picture")
    run = run_video(folder, SIFT, Outputs(out / "m.png", out / "m.json", out / "t.jpg"))
    return run.report, out / "m.json"


def test_round_trip_of_a_written_report(written) -> None:
    report, path = written
    text = path.read_text()
    assert text == report.to_json() + "\n"  # to_json is what was written
    again = BuildReport.from_json(text)
    assert again == report
    assert again.to_json() == report.to_json()
    assert read_report(path) == report


def test_written_report_has_its_optional_keys(written) -> None:
    report, _ = written
    summary = report.summary
    assert summary.complete is True and summary.checkpoint is False and summary.error is None
    assert summary.frames_read == 10 and summary.skipped == 1
    assert report.input is not None and report.input.kind == "folder"
    assert report.mosaic is not None and report.thumbnail is not None
    skipped = report.frames[4]
    assert skipped.status == SKIPPED and skipped.reason is not None
    assert "reason" in skipped.to_dict() and "reference" not in skipped.to_dict()
    placed = [f for f in report.frames if f.status == REGISTERED and f.reference is not None]
    keys = {"reference", "model", "coverage", "aligned_px"}
    assert placed and all(keys <= f.to_dict().keys() for f in placed)
    assert "error" not in json.loads(report.to_json())["summary"]  # left out, not null


def test_reads_a_report_written_before_its_newer_keys() -> None:
    """A report of 2026-12-01 (no `compose`, no lens, flow or blend keys) reads back; what it
    has is kept, what it lacks reads as None, False or 0."""
    data = json.loads(OLD_REPORT.read_text())
    report = read_report(OLD_REPORT)
    assert report is not None
    assert report.compose is None and report.summary.precision is None
    assert report.summary.frames_read == data["summary"]["frames_read"] == 3
    assert report.summary.lens_rim_frames == 0 and report.summary.tracking.joined_segments == 0
    assert report.summary.tracking.keyframes == data["summary"]["tracking"]["keyframes"]
    assert report.segments[0].blend is None and report.main_segment == 0
    for entry, old in zip(report.frames, data["frames"], strict=True):
        assert entry.H_to_canvas == old["H_to_canvas"] and entry.status == old["status"]
        assert entry.blended == (old["status"] == REGISTERED) and entry.gain is None
    written = report.to_dict()
    assert written["summary"]["complete"] is True and "compose" not in written


def test_what_is_not_a_report_reads_as_none(tmp_path) -> None:
    assert read_report(tmp_path / "missing.json") is None
    (tmp_path / "other.json").write_text(json.dumps({"summary": {"status": FAILED}}))
    assert read_report(tmp_path / "other.json") is None
    (tmp_path / "broken.json").write_text("{")
    assert read_report(tmp_path / "broken.json") is None


def test_model_counts_of_registered_frames():
    """Registered frames per model, in MODELS order: a failed frame and a segment's first
    frame (no reference) are not counted."""
    from mosaic.pipeline import FrameRecord
    from mosaic.report import _model_counts

    records = [
        FrameRecord(0, REGISTERED, segment=0),
        FrameRecord(1, REGISTERED, segment=0, model="similarity", reference=0),
        FrameRecord(2, REGISTERED, segment=0, model="homography", reference=1),
        FrameRecord(3, REGISTERED, segment=0, model="similarity", reference=2),
        FrameRecord(4, FAILED, reason="too few inliers", model="homography", reference=3),
        FrameRecord(5, REGISTERED, segment=1, model="affine"),
    ]
    assert list(_model_counts(records).items()) == [
        ("similarity", 2),
        ("homography", 1),
    ]
