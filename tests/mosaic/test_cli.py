"""The `mosaic` command line, driven through typer's CliRunner."""

from __future__ import annotations

import json
import os
import re
import signal
import sys

import cv2
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

import mosaic.cli
from mosaic import preprocess
from mosaic.cli import app
from mosaic.synthetic.truth import load_ground_truth
from tests.conftest import SAMPLE_IMAGE
from tests.helpers import corner_error, crop_pair, leaving_clip, similarity

runner = CliRunner()
FRAME_KEYS = {"index", "status", "H_to_canvas", "n_keypoints", "n_matches", "n_inliers", "time_ms"}


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "clip.mp4"
    result = runner.invoke(
        app, ["synth", str(SAMPLE_IMAGE), "-o", str(out), "--frames", "12", "--size", "400x300"]
    )
    assert result.exit_code == 0, result.output
    return out


def _one_line_error(result, fragment: str) -> None:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), result.output
    assert fragment in lines[0]


def test_synth_writes_video_and_ground_truth(video):
    gt = json.loads(video.with_suffix(".gt.json").read_text())
    assert len(gt["frames"]) == 12
    cap = cv2.VideoCapture(str(video))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 12
    assert (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))) == (
        400,
        300,
    )


def test_build_writes_mosaic_and_report(video, tmp_path):
    out = tmp_path / "mosaic.png"
    result = runner.invoke(app, ["build", str(video), "-o", str(out), "--detector", "sift"])
    assert result.exit_code == 0, result.output
    mosaic = cv2.imread(str(out))
    assert mosaic is not None and mosaic.shape[0] >= 300 and mosaic.shape[1] >= 400
    report = json.loads((tmp_path / "mosaic.json").read_text())
    assert report["summary"]["frames_read"] == 12
    assert report["summary"]["frames_until_failure"] == 12
    assert len(report["frames"]) == 12
    assert all(set(f) >= FRAME_KEYS for f in report["frames"])
    # Frame 0's corners land inside the written mosaic.
    H0 = np.array(report["frames"][0]["H_to_canvas"])
    corners = H0 @ np.array([[0, 0, 1], [399, 299, 1]], float).T
    xy = corners[:2] / corners[2]
    assert (
        (xy >= -0.5).all() and (xy[0] <= mosaic.shape[1]).all() and (xy[1] <= mosaic.shape[0]).all()
    )
    assert "frames until failure" in result.output


def test_build_names_each_segment_when_the_camera_leaves_the_mapped_area(tmp_path):
    frames = leaving_clip(tmp_path, (400, 300))
    config = tmp_path / "c.toml"
    config.write_text("[pipeline]\nnew_segment_after = 4\n")
    out = tmp_path / "m.png"
    args = ["build", str(frames), "-o", str(out), "--detector", "sift", "--config", str(config)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "segments                2 (12 / 14 frames; main mosaic: segment 1)" in result.output
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["summary"]["registered"] == 26 and report["main_segment"] == 1
    for index in (0, 1):
        path = tmp_path / f"m_seg{index:03d}.png"
        assert f"segment {index}: {path}" in result.output and path.is_file()
    assert cv2.imread(str(out)).shape == cv2.imread(str(tmp_path / "m_seg001.png")).shape


def test_build_options_step_and_max_frames(video, tmp_path):
    out = tmp_path / "m.png"
    report = tmp_path / "r.json"
    args = [
        "build",
        str(video),
        "-o",
        str(out),
        "--report",
        str(report),
        "--step",
        "2",
        "--max-frames",
        "4",
        "--detector",
        "orb",
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    frames = json.loads(report.read_text())["frames"]
    assert [f["index"] for f in frames] == [0, 2, 4, 6]


@pytest.mark.parametrize(
    ("make_input", "fragment"),
    [
        (lambda tmp: tmp / "missing.mp4", "missing.mp4"),
        (lambda tmp: (tmp / "text.mp4").write_text("not a video") and tmp / "text.mp4", "text.mp4"),
        (lambda tmp: (tmp / "empty").mkdir() or tmp / "empty", "empty"),
    ],
)
def test_bad_inputs_give_one_line_errors(tmp_path, make_input, fragment):
    path = make_input(tmp_path)
    result = runner.invoke(app, ["build", str(path), "-o", str(tmp_path / "m.png")])
    _one_line_error(result, fragment)


def test_bad_config_and_output(video, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[compose]\nblending = 'feather'\n")
    result = runner.invoke(
        app, ["build", str(video), "-o", str(tmp_path / "m.png"), "-c", str(bad)]
    )
    _one_line_error(result, "blending")
    result = runner.invoke(app, ["build", str(video), "-o", str(tmp_path / "nowhere" / "m.png")])
    _one_line_error(result, "nowhere")
    result = runner.invoke(
        app, ["build", str(video), "-o", str(tmp_path / "m.png"), "--detector", "surf"]
    )
    _one_line_error(result, "surf")


def _stopped_at(index, stop):
    """`open_frames` whose frames call `stop()` when frame `index` is read."""
    real_open = mosaic.cli.open_frames

    class Stopped:
        def __init__(self, *args, **kwargs):
            self._source = real_open(*args, **kwargs)
            self.info = self._source.info

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._source.close()

        def __iter__(self):
            for frame in self._source:
                if frame.index == index:
                    stop()
                yield frame

    return Stopped


def _ctrl_c():
    raise KeyboardInterrupt


def _build_partial(video, tmp_path):
    """`mosaic build` expected to stop part way: exit 130, the partial outputs, the report."""
    out = tmp_path / "partial.png"
    result = runner.invoke(app, ["build", str(video), "-o", str(out), "--detector", "sift"])
    assert result.exit_code == 130
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["summary"]["interrupted"] is True
    assert cv2.imread(str(out)) is not None
    return report


def test_interrupt_writes_partial_mosaic_and_report(video, tmp_path, monkeypatch):
    monkeypatch.setattr(mosaic.cli, "open_frames", _stopped_at(5, _ctrl_c))
    assert _build_partial(video, tmp_path)["summary"]["frames_read"] == 5


def test_sigterm_writes_partial_mosaic_and_report_like_ctrl_c(video, tmp_path, monkeypatch):
    """`kill`, a job scheduler or `docker stop` send SIGTERM: the run keeps what it has."""
    sigterm = _stopped_at(6, lambda: os.kill(os.getpid(), signal.SIGTERM))
    monkeypatch.setattr(mosaic.cli, "open_frames", sigterm)
    before = signal.getsignal(signal.SIGTERM)
    report = _build_partial(video, tmp_path)
    # the handler runs in the main thread, which registers a frame or two behind the reader
    assert 3 <= report["summary"]["frames_read"] <= 7
    assert signal.getsignal(signal.SIGTERM) == before  # the handler is put back


def test_register_prints_the_homography(fundus, tmp_path):
    H_b_to_a = similarity(-6.0, 0.95, -20.0, 10.0, center=(240, 160))
    a, b = crop_pair(fundus, H_b_to_a, origin=(500, 450), size=(480, 320))
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), b)
    args = [
        "register",
        str(tmp_path / "a.png"),
        str(tmp_path / "b.png"),
        "--json",
        "--detector",
        "sift",
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["status"] == "registered"
    assert corner_error(np.array(out["H_moving_to_fixed"]), H_b_to_a, (480, 320)) < 2.0
    (tmp_path / "pairs.csv").write_text("fixed,moving\na.png,b.png\nb.png,a.png\n")
    result = runner.invoke(
        app, ["register", "--pairs", str(tmp_path / "pairs.csv"), "--detector", "sift"]
    )
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert len(lines) == 2
    assert "2 pairs: 2 registered, 0 failed" in result.stderr  # the tally, beside a progress bar
    assert (
        corner_error(np.array(lines[1]["H_moving_to_fixed"]), np.linalg.inv(H_b_to_a), (480, 320))
        < 2.0
    )
    # a missing image and a row without its moving image: one failed line each, the batch goes
    # on, exit 1
    (tmp_path / "pairs.csv").write_text("fixed,moving\na.png,missing.png\nb.png\na.png,b.png\n")
    result = runner.invoke(
        app, ["register", "--pairs", str(tmp_path / "pairs.csv"), "--detector", "sift"]
    )
    assert result.exit_code == 1 and "Traceback" not in result.output
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert [line["status"] for line in lines] == ["failed", "failed", "registered"]
    assert "3 pairs: 1 registered, 2 failed" in result.stderr
    assert "missing.png" in lines[0]["reason"] and "row 3" in lines[1]["reason"]
    assert corner_error(np.array(lines[2]["H_moving_to_fixed"]), H_b_to_a, (480, 320)) < 2.0


def test_synth_curved_pairs_writes_a_fire_folder_with_exact_control_points(tmp_path):
    from mosaic.eval.datasets import load_fire

    out = tmp_path / "curved"
    args = ["synth", "--curved-pairs", "2", "--size", "320x320", "--seed", "4", "-o", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    pairs = list(load_fire(out))
    assert [p.name for p in pairs] == ["C01", "C02"]
    assert pairs[0].image1.shape == (320, 320, 3) and pairs[0].control_points.shape == (10, 4)
    assert len((out / "pairs.csv").read_text().splitlines()) == 3
    _one_line_error(runner.invoke(app, [*args[:4], "320x200", "-o", str(out)]), "square")


def test_register_describes_photographs_at_the_photo_descriptor_size(fundus, tmp_path):
    """`mosaic register` takes `photo_descriptor_size_px` (sharp photographs), not the video
    frames' `descriptor_size_px`: changing the video's size leaves the answer as it is, the
    photographs' size changes the matches."""
    H_b_to_a = similarity(4.0, 1.05, 15.0, -8.0, center=(240, 160))
    a, b = crop_pair(fundus, H_b_to_a, origin=(500, 450), size=(480, 320))
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), b)
    outputs = {}
    for name, table in (
        ("default", ""),
        ("video", "descriptor_size_px = 30.0\n"),
        ("photo", "photo_descriptor_size_px = 30.0\n"),
    ):
        config = tmp_path / f"{name}.toml"
        config.write_text(f"[features]\n{table}")
        args = ["register", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--json"]
        result = runner.invoke(app, [*args, "--config", str(config)])
        assert result.exit_code == 0, result.output
        outputs[name] = json.loads(result.stdout)
        H = np.array(outputs[name]["H_moving_to_fixed"])
        assert corner_error(H, H_b_to_a, (480, 320)) < 1.0, name
    assert outputs["video"]["n_inliers"] == outputs["default"]["n_inliers"]
    assert outputs["video"]["n_matches"] == outputs["default"]["n_matches"]
    assert outputs["photo"]["n_matches"] != outputs["default"]["n_matches"]


@pytest.mark.both_precisions
def test_register_curved_pair_prints_the_quadratic_and_warps(tmp_path):
    from mosaic.registration import apply_quadratic
    from mosaic.synthetic.curved import curved_pair

    pair = curved_pair(cv2.imread(str(SAMPLE_IMAGE)), seed=3, size=1024)
    fixed, moving, warp = tmp_path / "f.png", tmp_path / "m.png", tmp_path / "warp.png"
    cv2.imwrite(str(fixed), pair.fixed)
    cv2.imwrite(str(moving), pair.moving)
    result = CliRunner().invoke(
        app,
        [
            "register",
            str(fixed),
            str(moving),
            "--json",
            "--model",
            "quadratic",
            "--warp",
            str(warp),
        ],
    )
    assert result.exit_code == 0, result.output
    out = json.loads(result.output)
    assert out["model"] == "quadratic" and np.array(out["Q_moving_to_fixed"]).shape == (2, 6)
    assert np.array(out["H_moving_to_fixed"]).shape == (3, 3) and out["refined_levels"] == 3
    cp = pair.control_points
    err = np.linalg.norm(
        apply_quadratic(np.array(out["Q_moving_to_fixed"]), cp[:, 2:]) - cp[:, :2], axis=1
    )
    assert err.mean() < 1.0  # px at 1024
    assert cv2.imread(str(warp)).shape == (1024, 2048, 3)
    # --model homography answers the same homography (the best over the overlap), alone
    args = ["register", str(fixed), str(moving), "--json", "--model", "homography"]
    only = json.loads(CliRunner().invoke(app, args).output)
    assert only["model"] == "homography" and only["Q_moving_to_fixed"] is None
    H = np.array(only["H_moving_to_fixed"])
    np.testing.assert_allclose(H, np.array(out["H_moving_to_fixed"]), rtol=1e-6, atol=1e-9)
    err_h = np.linalg.norm(cv2.perspectiveTransform(cp[None, :, 2:], H)[0] - cp[:, :2], axis=1)
    assert err.mean() < err_h.mean() / 2
    # each answer's residual on its inliers: the curvature shows in the homography's
    assert 0 < out["residual_px"] < 1.0 and only["residual_px"] > 2 * out["residual_px"]
    assert out["inverted"] is None  # two colour photographs: registered as they are
    # the moving photograph as an angiogram (its negative in the view): registered inverted
    from mosaic.preprocess import invert_in_view

    cv2.imwrite(str(moving), invert_in_view(pair.moving))
    picture = tmp_path / "matches.png"
    args = ["register", str(fixed), str(moving), "--json", "--matches", str(picture)]
    angio = json.loads(CliRunner().invoke(app, args).output)
    assert angio["status"] == "registered" and angio["inverted"] == "moving"
    err_a = np.linalg.norm(
        apply_quadratic(np.array(angio["Q_moving_to_fixed"]), cp[:, 2:]) - cp[:, :2], axis=1
    )
    assert err_a.mean() < 1.0
    assert cv2.imread(str(picture)) is not None


def test_register_pair_without_overlap_fails_with_a_clear_status(tmp_path):
    for name, seed in (("a.png", 1), ("b.png", 2)):
        noise = np.random.default_rng(seed).uniform(0, 255, (400, 400)).astype(np.float32)
        img = cv2.GaussianBlur(noise, (0, 0), 3)
        cv2.imwrite(
            str(tmp_path / name), cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
        )
    result = CliRunner().invoke(
        app, ["register", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--json"]
    )
    assert result.exit_code == 1
    out = json.loads(result.output)
    assert out["status"] == "failed" and out["reason"] and out["H_moving_to_fixed"] is None
    assert out["Q_moving_to_fixed"] is None


def test_register_prints_a_failed_pair_without_an_internal_error(tmp_path):
    """Two unrelated photographs, answered in text (not --json): the failure and its reason,
    exit 1; no residual or model printed as None (issue 40: the residual's format crashed on
    None), and -v is taken as by the other commands."""
    for name, seed in (("a.png", 1), ("b.png", 2)):
        noise = np.random.default_rng(seed).uniform(0, 255, (400, 400)).astype(np.float32)
        img = cv2.GaussianBlur(noise, (0, 0), 3)
        cv2.imwrite(str(tmp_path / name), cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX))
    for verbose in ([], ["-v"]):
        args = ["register", str(tmp_path / "a.png"), str(tmp_path / "b.png"), *verbose]
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 1, result.output
        assert result.exception is None or isinstance(result.exception, SystemExit)
        assert result.stdout.startswith("status: failed (") and "None" not in result.stdout
        assert "matches: " in result.stdout and "internal error" not in result.output


def test_build_of_one_frame_prints_no_none(video, tmp_path):
    """A one-frame video has no quality (no mosaic under its frame): the summary says "-"."""
    out = tmp_path / "m.png"
    args = ["build", str(video), "-o", str(out), "--detector", "sift", "--max-frames", "1"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "None" not in result.stdout
    assert re.search(r"^quality / flagged\s+- / 0$", result.stdout, re.M), result.stdout


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the display check is Linux's")
def test_the_viewer_without_a_display_suggests_options_that_parse(video, tmp_path, monkeypatch):
    """`--viewer` with no display is one line whose suggested options parse with `mosaic
    build` as they are written, and the recording one writes its file (issue 40: it said
    `--rerun save FILE.rrd`, which does not parse)."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.chdir(tmp_path)
    base = ["build", str(video), "-o", "m.png", "--detector", "sift", "--max-frames", "2"]
    result = runner.invoke(app, [*base, "--viewer"])
    _one_line_error(result, "needs a display")
    suggested = re.findall(r"(?:--[a-z-]+ [^\s,-]\S*(?: |$))+", result.output.strip())
    assert [s.split()[:2] for s in suggested] == [["--rerun", "serve"], ["--rerun", "save"]]
    command = typer.main.get_command(app).commands["build"]
    for options in suggested:
        with command.make_context("build", [*base[1:], *options.split()]) as context:
            assert context.params["rerun"] == options.split()[1]
    save = suggested[1].split()
    assert save[2:] == ["--rerun-target", "FILE.rrd"]
    result = runner.invoke(app, [*base, *save])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "FILE.rrd").stat().st_size > 0


def test_version_and_the_help_of_every_verbose_option():
    """`mosaic --version` and `glampoints --version` print the installed version, exit 0;
    every command's -v/--verbose says what it does."""
    from importlib.metadata import version

    from mosaic.glampoints_cli import app as glampoints_app

    for tool, tool_app in (("mosaic", app), ("glampoints", glampoints_app)):
        result = CliRunner().invoke(tool_app, ["--version"])
        assert result.exit_code == 0, result.output
        assert result.stdout == f"{tool} {version('retina-mosaic')}\n"
    commands = typer.main.get_command(app).commands
    for name in ("build", "batch", "evaluate", "register", "synth", "bench"):
        (verbose,) = [p for p in commands[name].params if "--verbose" in getattr(p, "opts", ())]
        assert "-v" in verbose.opts and verbose.help, name


@pytest.mark.both_precisions
def test_build_of_the_shipped_sample_matches_its_ground_truth(tmp_path):
    """`mosaic build samples/sample.mp4` (the README's first command, default settings and
    shipped weights) places every frame within a few pixels of `samples/sample.gt.json`
    (measured: 0.97 px mean corner error, 1.75 px at worst)."""
    from tests.conftest import REPO
    from tests.helpers import errors_to_first

    sample = REPO / "samples" / "sample.mp4"
    out = tmp_path / "mosaic.png"
    result = runner.invoke(app, ["build", str(sample), "-o", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads(out.with_suffix(".json").read_text())
    truth = load_ground_truth(REPO / "samples" / "sample.gt.json")
    assert report["summary"]["registered"] == len(truth) == 48
    errors = errors_to_first(report["frames"], truth, (660, 350))
    assert errors.mean() < 1.5 and errors.max() < 3.0, errors


def test_an_interlaced_video_is_told_and_deinterlaced_on_request(tmp_path):
    """`synth --interlaced` renders an interlaced camera; `build` says the video looks
    interlaced, and with `[preprocess] deinterlace = true` takes every frame's first field."""
    clip = tmp_path / "interlaced"
    args = ["synth", str(SAMPLE_IMAGE), "-o", str(clip), "--frames", "12", "--size", "400x300"]
    result = runner.invoke(app, [*args, "--interlaced", "--clean"])
    assert result.exit_code == 0, result.output
    frame = cv2.imread(str(sorted(clip.glob("*.png"))[5]))
    assert preprocess.field_offset(frame)[0] != pytest.approx(0, abs=1.0)  # combed
    result = runner.invoke(
        app, ["build", str(clip), "-o", str(tmp_path / "a.png"), "--detector", "sift"]
    )
    assert result.exit_code == 0, result.output
    assert "looks interlaced" in result.stdout
    report = json.loads((tmp_path / "a.json").read_text())["summary"]
    assert (
        report["looks_interlaced"] and report["field_offset_px"] > 2 and report["deinterlaced"] == 0
    )
    (tmp_path / "di.toml").write_text("[preprocess]\ndeinterlace = true\n")
    out = tmp_path / "b.png"
    build = [
        "build",
        str(clip),
        "-o",
        str(out),
        "--detector",
        "sift",
        "-c",
        str(tmp_path / "di.toml"),
    ]
    result = runner.invoke(app, build)
    assert result.exit_code == 0, result.output
    assert re.search(r"deinterlaced\s+12", result.stdout)
    result = runner.invoke(app, [*args, "--interlaced", "--curved-pairs", "2"])
    assert result.exit_code == 2 and "not --curved-pairs" in result.output


def test_build_says_in_how_many_frames_lens_reflexes_were_masked(tmp_path):
    """A video with lens reflexes: the summary names the frames they were left out of (from
    the 15th on: 12 frames to be seen in, 3 more to hold still), as the report counts them."""
    clip = tmp_path / "reflexes.mp4"
    args = ["synth", str(SAMPLE_IMAGE), "-o", str(clip), "--frames", "20", "--realistic"]
    result = runner.invoke(app, [*args, "--lens-reflexes", "2", "--seed", "4"])
    assert result.exit_code == 0, result.output
    out = tmp_path / "m.png"
    result = runner.invoke(app, ["build", str(clip), "-o", str(out), "--detector", "sift"])
    assert result.exit_code == 0, result.output
    summary = json.loads(out.with_suffix(".json").read_text())["summary"]
    assert summary["reflex_frames"] == 6, summary["reflex_frames"]
    assert "lens reflexes masked    6 frames" in result.stdout
