"""`mosaic.runner.run_video`: one video end to end, its outputs, and what survives Ctrl-C or an
exception while streaming, refining or re-rendering."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from mosaic.cli import app
from mosaic.config import Config, with_overrides
from mosaic.errors import MosaicError
from mosaic.io import open_frames
from mosaic.runner import Outputs, is_frame_folder, run_video, segment_path, thumbnail
from mosaic.segments import Segments
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from tests.conftest import SAMPLE_IMAGE

SIFT = with_overrides(Config(), features={"detector": "sift"})


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    out = tmp_path_factory.mktemp("runner") / "clip.mp4"
    params = SynthParams(n_frames=10, size=(200, 150), seed=2, max_step_px=4.0, nuisances=False)
    write_synthetic_video(SAMPLE_IMAGE, out, params)
    return out


def _outputs(tmp_path, thumb=True) -> Outputs:
    return Outputs(tmp_path / "m.png", tmp_path / "m.json", tmp_path / "t.jpg" if thumb else None)


def _statuses(report):
    return [(f["index"], f["status"]) for f in report["frames"]]


def test_writes_mosaic_thumbnail_and_a_complete_report(clip, tmp_path):
    run = run_video(clip, SIFT, _outputs(tmp_path))
    assert run.complete and not run.interrupted and run.error is None
    report = json.loads((tmp_path / "m.json").read_text())
    assert report["summary"]["complete"] is True
    assert report["summary"]["registered"] >= 8
    assert report["summary"]["tracking"]["rerendered"] is True
    assert report["mosaic"] == str(tmp_path / "m.png")
    assert report["input"]["path"] == str(clip) and report["input"]["n_frames"] == 10
    mosaic = cv2.imread(str(tmp_path / "m.png"))
    thumb = cv2.imread(str(tmp_path / "t.jpg"))
    assert mosaic.shape == run.result.main.image.shape
    assert max(thumb.shape[:2]) == min(320, max(mosaic.shape[:2]))
    # what was written is what is returned
    assert (tmp_path / "m.json").read_text() == run.report.to_json() + "\n"
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left behind


def test_same_report_as_mosaic_build(clip, tmp_path):
    config = tmp_path / "sift.toml"
    config.write_text('[features]\ndetector = "sift"\n')
    result = CliRunner().invoke(
        app, ["build", str(clip), "-o", str(tmp_path / "b.png"), "-c", str(config)]
    )
    assert result.exit_code == 0, result.output
    built = json.loads((tmp_path / "b.json").read_text())
    run = run_video(clip, SIFT, _outputs(tmp_path, thumb=False))
    assert _statuses(built) == _statuses(run.report.to_dict())
    for a, b in zip(built["frames"], run.report.to_dict()["frames"], strict=True):
        if a["H_to_canvas"] is not None:
            np.testing.assert_allclose(a["H_to_canvas"], b["H_to_canvas"], atol=1e-6)


def test_ctrl_c_while_streaming_writes_the_frames_so_far(clip, tmp_path):
    def interrupt_at_6(source):
        for frame in source:
            if frame.index == 6:
                raise KeyboardInterrupt
            yield frame

    run = run_video(clip, SIFT, _outputs(tmp_path), wrap_frames=interrupt_at_6)
    assert run.interrupted and not run.complete
    report = json.loads((tmp_path / "m.json").read_text())
    summary = report["summary"]
    assert summary["interrupted"] is True and summary["complete"] is False
    assert summary["frames_read"] == 6
    assert cv2.imread(str(tmp_path / "m.png")) is not None
    with pytest.raises(KeyboardInterrupt):
        run_video(clip, SIFT, _outputs(tmp_path), wrap_frames=interrupt_at_6, salvage=False)


def _failing_second_read(exc: BaseException):
    """An opener whose second pass (the re-render) raises `exc` at its first frame."""
    calls = []

    def opener(path, step, max_frames):
        calls.append(path)
        source = open_frames(path, step, max_frames)
        if len(calls) == 1:
            return source

        class Failing:
            info = source.info

            def __enter__(self):
                return self

            def __exit__(self, *args):
                source.close()

            def __iter__(self):
                raise exc
                yield  # a generator

        return Failing()

    return opener


@pytest.mark.parametrize(
    ("exc", "interrupted"),
    [(KeyboardInterrupt(), True), (np.linalg.LinAlgError("Singular matrix"), False)],
)
def test_ctrl_c_or_an_exception_while_rendering_keeps_the_live_mosaic(
    clip, tmp_path, exc, interrupted
):
    run = run_video(clip, SIFT, _outputs(tmp_path), opener=_failing_second_read(exc))
    assert run.interrupted is interrupted and not run.complete
    report = json.loads((tmp_path / "m.json").read_text())
    summary = report["summary"]
    assert summary["complete"] is False and summary["interrupted"] is interrupted
    assert summary["tracking"]["rerendered"] is False
    assert summary["frames_read"] == 10 and summary["registered"] >= 8
    if not interrupted:
        assert "Singular matrix" in summary["error"] and "rendering" in summary["error"]
    assert cv2.imread(str(tmp_path / "m.png")) is not None
    with pytest.raises(type(exc)):
        run_video(clip, SIFT, _outputs(tmp_path), opener=_failing_second_read(exc), salvage=False)


def test_build_exits_1_and_writes_the_live_mosaic_when_refinement_fails(
    clip, tmp_path, monkeypatch
):
    def broken(self):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(Segments, "refine", broken)
    out = tmp_path / "m.png"
    result = CliRunner().invoke(app, ["build", str(clip), "-o", str(out), "--detector", "sift"])
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    assert "Singular matrix" in result.stderr
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["summary"]["complete"] is False
    assert cv2.imread(str(out)) is not None


def test_no_frame_placed_writes_the_report_and_raises(clip, tmp_path):
    every_frame_skipped = with_overrides(SIFT, gating={"min_fov_fraction": 1.0})  # the border
    with pytest.raises(MosaicError, match="no frame could be placed"):
        run_video(clip, every_frame_skipped, _outputs(tmp_path))
    report = json.loads((tmp_path / "m.json").read_text())
    assert report["summary"]["skipped"] == 10 and "mosaic" not in report
    assert not (tmp_path / "m.png").exists()


def test_frame_folders(tmp_path):
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "frames" / "f0.png"), np.zeros((8, 8, 3), np.uint8))
    assert is_frame_folder(tmp_path / "frames") and not is_frame_folder(tmp_path)


def test_unwritable_output_fails_before_the_first_frame(clip, tmp_path):
    opened = []

    def opener(*args):
        opened.append(args)
        return open_frames(*args)

    with pytest.raises(MosaicError, match="does not exist"):
        run_video(clip, SIFT, Outputs(tmp_path / "missing" / "m.png"), opener=opener)
    assert not opened


def test_thumbnail_and_segment_paths(tmp_path):
    image = np.zeros((100, 800, 3), np.uint8)
    assert thumbnail(image).shape == (40, 320, 3)
    assert thumbnail(image[:, :200]).shape == (100, 200, 3)  # never enlarged
    assert segment_path(tmp_path / "m.png", 2) == tmp_path / "m_seg002.png"
