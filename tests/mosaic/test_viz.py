"""The rerun viewer: a `--rerun save` recording is read back with rerun's own chunk reader and its
content checked against the run's report and the synthetic video's ground truth."""

from __future__ import annotations

import json
import logging
import math
import socket
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from mosaic.cli import app
from mosaic.synthetic.truth import load_ground_truth
from mosaic.viz import (
    INLIER,
    OUTLIER,
    UNMATCHED,
    NullViewer,
    RerunViewer,
    encode_jpeg,
    fit_scale,
    frame_outline,
    keypoint_classes,
    make_viewer,
    to_display,
)
from tests.conftest import SAMPLE_IMAGE
from tests.helpers import empty_report

rr_chunk = pytest.importorskip("rerun.chunk")

runner = CliRunner()
N_FRAMES, CANVAS_EVERY, W, H = 8, 3, 320, 240


def read_rrd(path: Path) -> dict[str, dict[str, Any]]:
    """entity path -> {"static": {column: cell}, "rows": [(frame, {column: cell})]}.

    A cell is the component batch of one row (a list: `[text]`, `[scalar]`, `[[x, y], ...]`).
    """
    out: dict[str, dict[str, Any]] = defaultdict(lambda: {"static": {}, "rows": []})
    for chunk in rr_chunk.RrdReader(path).stream():
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if ":" in n]  # Archetype:component columns
        cols = {n: batch.column(n).to_pylist() for n in names}
        entity = out[chunk.entity_path.lstrip("/")]
        if chunk.is_static:
            entity["static"].update({n: v[-1] for n, v in cols.items()})
            continue
        has_frame = "frame" in batch.schema.names  # rows logged before the first frame lack it
        frames = batch.column("frame").to_pylist() if has_frame else [-1] * batch.num_rows
        for i, frame in enumerate(frames):
            entity["rows"].append((frame, {n: v[i] for n, v in cols.items()}))
    for entity in out.values():
        entity["rows"].sort(key=lambda row: row[0])
    return out


def frames_of(rec: dict, entity: str) -> list[int]:
    return [frame for frame, _ in rec[entity]["rows"]]


def last_value(rec: dict, entity: str, column: str, frame: int) -> Any:
    values = [row[column] for f, row in rec[entity]["rows"] if f == frame and column in row]
    return values[-1]


def decode_jpeg(blob: list[list[int]]) -> np.ndarray:
    """The image of an EncodedImage:blob cell (a batch of one blob)."""
    image = cv2.imdecode(np.asarray(blob[0], np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> dict[str, Any]:
    """One `mosaic build --rerun save` on a short clean synthetic video (frame-to-frame chain)."""
    folder = tmp_path_factory.mktemp("viz")
    video = folder / "clip.mp4"
    args = ["synth", str(SAMPLE_IMAGE), "-o", str(video), "--frames", str(N_FRAMES)]
    result = runner.invoke(app, [*args, "--size", f"{W}x{H}", "--clean"])
    assert result.exit_code == 0, result.output
    rrd = folder / "run.rrd"
    result = runner.invoke(
        app,
        [
            "build",
            str(video),
            "-o",
            str(folder / "mosaic.png"),
            "--detector",
            "sift",
            "--strategy",
            "chain",
            "--rerun",
            "save",
            "--rerun-target",
            str(rrd),
            "--rerun-canvas-every",
            str(CANVAS_EVERY),
        ],
    )
    assert result.exit_code == 0, result.output
    assert f"recording: {rrd}" in result.output
    report = json.loads((folder / "mosaic.json").read_text())
    return {
        "rec": read_rrd(rrd),
        "report": report,
        "mosaic": cv2.imread(str(folder / "mosaic.png")),
        "gt": load_ground_truth(video),
    }


def test_entity_paths_with_one_row_per_frame(run):
    rec, report = run["rec"], run["report"]
    all_frames = list(range(N_FRAMES))
    assert [f["status"] for f in report["frames"]] == ["registered"] * N_FRAMES
    per_frame = [
        "video/frame",
        "video/frame/keypoints",
        "video/frame/matches",
        "log/status",
        "metrics/keypoints",
        "metrics/matches",
        "metrics/inliers",
        "metrics/reproj_error_px",
        "metrics/quality",
        "metrics/fps",
        "metrics/ms/total",
        "metrics/ms/viewer",
        "metrics/ms/detect",
        "metrics/ms/compose",
    ]
    for entity in per_frame:
        assert frames_of(rec, entity) == all_frames, entity
    # the first frame is the reference: nothing matched, no estimate
    assert frames_of(rec, "metrics/ms/match") == all_frames[1:]
    for entity in ("run/config", "run/video", "run/report", "video"):
        assert rec[entity]["static"], entity


def test_scalars_equal_the_report(run):
    rec, frames = run["rec"], run["report"]["frames"]
    for name, key in (("keypoints", "n_keypoints"), ("matches", "n_matches")):
        logged = [row["Scalars:scalars"][0] for _, row in rec[f"metrics/{name}"]["rows"]]
        assert logged == [f[key] for f in frames]
    inliers = [row["Scalars:scalars"][0] for _, row in rec["metrics/inliers"]["rows"]]
    assert inliers == [f["n_inliers"] for f in frames]
    assert min(inliers[1:]) >= 20  # a clean clip registers with many inliers
    errors = [row["Scalars:scalars"][0] for _, row in rec["metrics/reproj_error_px"]["rows"]]
    assert math.isnan(errors[0])
    assert errors[1:] == pytest.approx([f["reproj_error_px"] for f in frames[1:]], abs=1e-3)
    quality = [row["Scalars:scalars"][0] for _, row in rec["metrics/quality"]["rows"]]
    assert math.isnan(quality[0])  # nothing on the canvas yet
    assert quality[1:] == pytest.approx([f["quality"] for f in frames[1:]], abs=1e-3)


def test_keypoints_classes_and_match_lines(run):
    rec, frames, gt = run["rec"], run["report"]["frames"], run["gt"]
    for (i, kp), (_, lines), entry in zip(
        rec["video/frame/keypoints"]["rows"],
        rec["video/frame/matches"]["rows"],
        frames,
        strict=True,
    ):
        xy = np.array(kp["Points2D:positions"], np.float32)
        classes = np.array(kp["Points2D:class_ids"])
        assert len(xy) == entry["n_keypoints"]
        assert (xy >= 0).all() and (xy[:, 0] <= W).all() and (xy[:, 1] <= H).all()
        assert (classes == INLIER).sum() == entry["n_inliers"]
        assert (classes != UNMATCHED).sum() == entry["n_matches"]  # cross-check: one match each
        strips = np.array(lines["LineStrips2D:strips"], np.float32).reshape(-1, 2, 2)
        assert len(strips) == entry["n_matches"]
        if i == 0:
            continue
        inlier = np.array(lines["LineStrips2D:class_ids"]) == INLIER
        assert inlier.sum() == entry["n_inliers"]
        # inlier segments join a keypoint to its match in the previous frame: the ground truth
        # homography maps one end onto the other (OpenCV coords = rerun coords - 0.5)
        H_moving_to_fixed = np.linalg.inv(gt[i - 1]) @ gt[i]
        cur = np.hstack([strips[inlier, 0] - 0.5, np.ones((inlier.sum(), 1))]) @ H_moving_to_fixed.T
        err = np.linalg.norm(cur[:, :2] / cur[:, 2:] - (strips[inlier, 1] - 0.5), axis=1)
        assert np.median(err) < 1.5, (i, np.median(err))


def test_canvas_is_throttled_and_outline_on_it(run):
    rec, mosaic = run["rec"], run["mosaic"]
    periodic = list(range(0, N_FRAMES, CANVAS_EVERY))
    assert len(periodic) == math.ceil(N_FRAMES / CANVAS_EVERY)
    # every CANVAS_EVERY-th frame, plus the final state after the last frame
    assert frames_of(rec, "mosaic/canvas") == [*periodic, N_FRAMES - 1]
    first = decode_jpeg(last_value(rec, "mosaic/canvas", "EncodedImage:blob", 0))
    assert first.shape[:2] == (H, W)  # one frame on the canvas
    outline0 = np.array(last_value(rec, "mosaic/outline", "LineStrips2D:strips", 0)[0])
    expected = [[0, 0], [W, 0], [W, H], [0, H], [0, 0]]
    np.testing.assert_allclose(outline0, expected, atol=1e-3)
    final = decode_jpeg(last_value(rec, "mosaic/canvas", "EncodedImage:blob", N_FRAMES - 1))
    assert final.shape == mosaic.shape  # the final snapshot is the written mosaic (< 1024 px)
    assert np.abs(final.astype(int) - mosaic.astype(int)).mean() < 4.0  # JPEG quality 80
    last = np.array(last_value(rec, "mosaic/outline", "LineStrips2D:strips", N_FRAMES - 1)[0])
    hm, wm = mosaic.shape[:2]
    assert (last >= -1e-3).all() and (last[:, 0] <= wm + 1e-3).all()
    assert (last[:, 1] <= hm + 1e-3).all()


def test_outline_on_a_canvas_composed_at_the_working_size(tmp_path):
    """Frames larger than the working size are composed there: the live canvas is at that
    scale, and the frame's outline (decoded pixels) is drawn on it where the frame lies."""
    video = tmp_path / "clip.mp4"
    args = ["synth", str(SAMPLE_IMAGE), "-o", str(video), "--frames", "3"]
    assert runner.invoke(app, [*args, "--size", f"{2 * W}x{2 * H}", "--clean"]).exit_code == 0
    config = tmp_path / "half.toml"
    config.write_text(f"[preprocess]\nmax_side_px = {W}\n")  # half the frame
    rrd = tmp_path / "run.rrd"
    result = runner.invoke(
        app,
        [
            "build", str(video), "-o", str(tmp_path / "m.png"), "--config", str(config),
            "--detector", "sift", "--rerun", "save", "--rerun-target", str(rrd),
            "--rerun-canvas-every", "1",
        ],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    rec = read_rrd(rrd)
    first = decode_jpeg(last_value(rec, "mosaic/canvas", "EncodedImage:blob", 0))
    assert first.shape[:2] == (H, W)  # one frame on the canvas, at half size
    outline0 = np.array(last_value(rec, "mosaic/outline", "LineStrips2D:strips", 0)[0])
    np.testing.assert_allclose(outline0, [[0, 0], [W, 0], [W, H], [0, H], [0, 0]], atol=0.5)


def test_status_log_has_one_entry_per_frame(run):
    rows = run["rec"]["log/status"]["rows"]
    assert [f for f, _ in rows] == list(range(N_FRAMES))
    for (i, row), entry in zip(rows, run["report"]["frames"], strict=True):
        assert row["TextLog:text"][0].startswith(f"frame {i} registered")
        assert row["TextLog:level"][0] == "INFO"
        if i > 0:
            assert f"{entry['n_inliers']}/{entry['n_matches']} inliers" in row["TextLog:text"][0]


def test_static_config_video_and_report(run):
    rec = run["rec"]
    assert 'detector = "sift"' in rec["run/config"]["static"]["TextDocument:text"][0]
    assert f"| width | {W} |" in rec["run/video"]["static"]["TextDocument:text"][0]
    report = rec["run/report"]["static"]["TextDocument:text"][0]
    assert f"| frames_until_failure | {N_FRAMES} |" in report
    # the written mosaic itself, as a static image at the end
    final = decode_jpeg(rec["final/mosaic"]["static"]["EncodedImage:blob"])
    assert final.shape == run["mosaic"].shape
    assert np.abs(final.astype(int) - run["mosaic"].astype(int)).mean() < 4  # JPEG only


def test_python_logging_reaches_the_recording_and_is_detached(tmp_path):
    rrd = tmp_path / "log.rrd"
    viewer = RerunViewer("save", rrd)
    logger = logging.getLogger("mosaic.test_viz")
    logger.warning("vessels too faint in frame %d", 3)
    viewer.finish(empty_report())
    logger.warning("after finish")
    assert not [h for h in logging.getLogger("mosaic").handlers if "Recording" in type(h).__name__]
    rows = read_rrd(rrd)["log/python/mosaic/test_viz"]["rows"]
    assert [row["TextLog:text"][0] for _, row in rows] == ["vessels too faint in frame 3"]
    assert rows[0][1]["TextLog:level"][0] == "WARN"


def test_off_imports_nothing_of_rerun():
    code = (
        "import sys, mosaic.cli\n"
        "from mosaic.viz import make_viewer, NullViewer\n"
        "assert isinstance(make_viewer('off', None, None, None), NullViewer)\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('rerun', 'rerun_bindings'))\n"
        "assert not bad, bad\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert isinstance(make_viewer("off", None, None, None), NullViewer)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_hosts_the_web_viewer():
    """In a subprocess, so that the servers end with it."""
    grpc_port, web_port = _free_port(), _free_port()
    code = (
        "import urllib.request\n"
        "from mosaic.viz import RerunViewer\n"
        f"v = RerunViewer('serve', grpc_port={grpc_port}, web_port={web_port})\n"
        "print(v.url)\n"
        "html = urllib.request.urlopen(v.url, timeout=10).read().decode()\n"
        "assert 'rerun' in html.lower(), html[:200]\n"
        "from tests.helpers import empty_report\n"
        "v.finish(empty_report())\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    url = result.stdout.strip().splitlines()[-1]
    assert url == (
        f"http://localhost:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy"
    )


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--rerun", "bogus"], "unknown --rerun mode 'bogus'"),
        (["--viewer", "--rerun", "save"], "--viewer is short for --rerun spawn"),
        (["--rerun", "serve", "--rerun-target", "x.rrd"], "only used with --rerun save or connect"),
        (["--rerun", "save", "--rerun-target", "run.txt"], "unsupported output format '.txt'"),
        (["--rerun", "connect", "--rerun-target", "http://x"], "cannot open the rerun viewer"),
        (["--viewer"], "rerun spawn needs a display"),
    ],
)
def test_bad_viewer_arguments_are_one_line_errors(tmp_path, monkeypatch, args, fragment):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.chdir(tmp_path)
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(2):
        cv2.imwrite(str(frames / f"f{i}.png"), np.full((64, 64, 3), 100, np.uint8))
    result = runner.invoke(app, ["build", str(frames), "-o", str(tmp_path / "m.png"), *args])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], lines


def test_pure_helpers():
    assert fit_scale((350, 660, 3), 1024) == 1.0
    assert fit_scale((1000, 2048), 1024) == 0.5
    jpeg, (sx, sy) = encode_jpeg(np.zeros((1000, 2048, 3), np.uint8), 0.5, 80)
    assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (500, 1024, 3)
    assert (sx, sy) == (0.5, 0.5)
    np.testing.assert_allclose(
        to_display(np.array([[0, 0], [9, 4]], np.float32), (0.5, 0.5)),
        [
            [0.25, 0.25],
            [4.75, 2.25],
        ],
    )
    classes = keypoint_classes(5, np.array([4, 1, 2]), np.array([True, False, True]))
    assert classes.tolist() == [UNMATCHED, OUTLIER, INLIER, UNMATCHED, INLIER]
    shift = np.array([[2.0, 0, 10], [0, 2.0, 20], [0, 0, 1]])  # scale 2 then translate
    outline = frame_outline(shift, 4, 3)
    np.testing.assert_allclose(outline, [[9, 19], [17, 19], [17, 25], [9, 25], [9, 19]])


def test_status_line_marks_a_flagged_frame():
    from mosaic.pipeline import FrameEvent, FrameRecord
    from mosaic.viz import _status_text

    record = FrameRecord(index=7, status="registered", segment=0, n_matches=90, n_inliers=60)
    record.reproj_error_px, record.quality = 1.25, 0.91
    text = _status_text(FrameEvent(record, None, None, None, None, None, None))
    assert "FLAGGED" not in text and "quality 0.91" in text
    record.quality, record.flagged = 0.12, True
    text = _status_text(FrameEvent(record, None, None, None, None, None, None))
    assert text.startswith("frame 7 registered, FLAGGED") and "quality 0.12" in text
