"""End-to-end: synthetic videos with known trajectories through the whole pipeline."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from mosaic.config import Config, with_overrides
from mosaic.geometry import scale_matrix
from mosaic.io import Frame, Lookahead, open_frames
from mosaic.pipeline import MosaicBuilder, MosaicResult
from mosaic.scheduling import OverlapTrial, Turns
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from mosaic.synthetic.truth import load_ground_truth
from tests.conftest import SAMPLE_IMAGE
from tests.helpers import (
    build_from_folder,
    corner_error,
    errors_to_first,
    left_and_back,
    similarity,
)

SIZE = (400, 300)


def _config(**pipeline) -> Config:
    return with_overrides(Config(), features={"detector": "sift"}, pipeline=pipeline or {})


def _frames_folder(tmp_path: Path, n: int, seed: int = 3) -> tuple[Path, list[np.ndarray]]:
    folder = tmp_path / "frames"
    params = SynthParams(n_frames=n, size=SIZE, seed=seed, nuisances=False)
    gt_path = write_synthetic_video(SAMPLE_IMAGE, folder, params)
    return folder, load_ground_truth(gt_path)


def _run(
    folder: Path, config: Config, corrupt: set[int] = frozenset(), bad: set[int] = frozenset()
):
    builder = MosaicBuilder(config)
    with open_frames(folder) as frames:
        for frame in frames:
            image = frame.image
            if frame.index in bad:  # an unregistrable frame (e.g. a blink): flat noise
                rng = np.random.default_rng(frame.index)
                image = rng.integers(0, 255, image.shape, dtype=np.uint8)
            if frame.index in corrupt:
                builder.process(frame.index, None, "corrupt frame")
            else:
                builder.process(frame.index, image, frame.error)
            if builder.stopped:
                break
    return builder.finish()


def _errors_to_first(frames: list[dict], gt: list[np.ndarray], size: tuple[int, int]) -> list:
    """Corner error of each reported frame->first-frame homography against the truth."""
    return list(errors_to_first(frames, gt, size)[1:])


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    return _frames_folder(tmp_path_factory.mktemp("video"), 24)


def test_chained_homographies_follow_the_ground_truth(video):
    folder, gt = video
    result = _run(folder, _config())
    summary = result.report.to_dict()["summary"]
    assert summary["frames_read"] == 24
    assert summary["registered"] == 24
    assert summary["frames_until_failure"] == 24
    assert summary["segments"] == 1
    errors = _errors_to_first(result.report.to_dict()["frames"], gt, SIZE)
    assert np.mean(errors) < 3.0, errors
    assert np.max(errors) < 6.0, errors


def test_mosaic_pixels_agree_with_the_frames(video):
    folder, _ = video
    result = _run(folder, _config())
    mosaic = result.main.image
    frame_index = 12
    entry = result.report.to_dict()["frames"][frame_index]
    frame = cv2.imread(str(sorted(folder.glob("*.png"))[frame_index]))
    H = np.array(entry["H_to_canvas"])
    warped = cv2.warpPerspective(frame, H, (mosaic.shape[1], mosaic.shape[0]))
    inside = cv2.warpPerspective(np.full(frame.shape[:2], 255, np.uint8), H, warped.shape[1::-1])
    inside = cv2.erode(inside, np.ones((15, 15), np.uint8)) > 0
    diff = np.abs(mosaic.astype(int) - warped.astype(int))[inside]
    assert np.median(diff) < 6


def test_skip_policy_drops_a_bad_frame_and_goes_on(video):
    folder, _ = video
    result = _run(folder, _config(on_failure="skip"), bad={5})
    summary = result.report.to_dict()["summary"]
    statuses = [f["status"] for f in result.report.to_dict()["frames"]]
    assert statuses[5] == "failed" and statuses.count("registered") == 23
    assert summary["frames_until_failure"] == 5
    assert summary["longest_registered_run"] == 18
    assert result.report.to_dict()["frames"][5]["H_to_canvas"] is None


def test_a_first_frame_nothing_registers_to_is_dropped_and_the_mosaic_starts_again(video):
    folder, gt = video
    result = _run(folder, _config(on_failure="skip"), bad={0})  # opens on a frame of noise
    frames = result.report.to_dict()["frames"]
    statuses = [f["status"] for f in frames]
    # frames 1-5 fail against frame 0; frame 5 registers to frame 4, which becomes the first
    assert statuses[:4] == ["failed"] * 4 and statuses[4:] == ["registered"] * 20
    assert frames[0]["reason"].startswith("dropped as the mosaic's first frame")
    assert frames[0]["H_to_canvas"] is None and frames[5]["reference"] == 4
    assert result.report.to_dict()["summary"]["segments"] == 1 and result.main.n_frames == 20
    errors = errors_to_first(frames[4:], gt, SIZE)[1:]
    assert np.mean(errors) < 3.0 and np.max(errors) < 6.0, errors


def test_without_reanchoring_an_unregistrable_first_frame_fails_the_video(video):
    folder, _ = video
    result = _run(folder, _config(on_failure="skip", reanchor_after=0), bad={0})
    statuses = [f["status"] for f in result.report.to_dict()["frames"]]
    assert statuses == ["registered"] + ["failed"] * 23


def test_a_camera_that_leaves_the_mapped_area_starts_a_new_segment_and_comes_back(video, tmp_path):
    images, truth = left_and_back(tmp_path, *video, SIZE)
    results = {}
    for after in (4, 0):
        builder = MosaicBuilder(_config(on_failure="skip", new_segment_after=after))
        for index, image in enumerate(images):
            builder.process(index, image)
        results[after] = builder.finish()
    frames = results[4].report.to_dict()["frames"]
    statuses = [f["status"] for f in frames]
    # 12-15 fail against the mosaic; at the 4th failure 15 registers to 14: a new segment
    assert statuses[12:14] == ["failed"] * 2 and statuses[14:] == ["registered"] * 26
    assert [f["segment"] for f in frames[14:28]] == [1] * 14
    # the camera is back: frame 28 registers to the first segment, and the rest follow it
    assert {f["segment"] for f in frames[:12] + frames[28:]} == {0}
    assert len(results[4].segments) == 2 and results[4].main.index == 0
    assert results[4].main.n_frames == 24
    first, second = frames[:12] + frames[28:], frames[14:28]
    for placed in (first, second):  # each segment against its own truth
        errors = errors_to_first(placed, truth, SIZE)[1:]
        assert np.mean(errors) < 3.0 and np.max(errors) < 6.0, errors
    # without it the frames of the other area fail, and the first segment is the same
    without = results[0].report.to_dict()["frames"]
    assert [f["status"] for f in without[12:28]] == ["failed"] * 16
    assert results[0].report.to_dict()["summary"]["segments"] == 1
    for a, b in zip(first, without[:12] + without[28:], strict=True):
        np.testing.assert_allclose(a["H_to_canvas"], b["H_to_canvas"], atol=1e-9)


def _along(xs: list, blink) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Frames of the sample cropped at (x, 550) along `xs` (None: a frame from `blink()`, a
    blink), and their truth (H_frame_to_source, pure translations)."""
    sample = cv2.imread(str(SAMPLE_IMAGE))
    y, (w, h) = 550, SIZE
    images = [
        blink() if x is None else np.ascontiguousarray(sample[y : y + h, x : x + w]) for x in xs
    ]
    truth = [np.array([[1.0, 0, x or 0], [0, 1, y], [0, 0, 1]]) for x in xs]
    return images, truth


def _out_and_back() -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Crops of the sample along a known path: 10 frames, a 6-frame blink (noise) while the
    camera moves far right, then back left across the first frames' area."""
    xs = [150 + 15 * i for i in range(10)] + [None] * 6 + list(range(800, 385, -15))
    rng = np.random.default_rng(0)
    return _along(xs, lambda: rng.integers(0, 255, (*SIZE[::-1], 3), dtype=np.uint8))


def _build_segments(images: list[np.ndarray], reread) -> MosaicResult:
    builder = MosaicBuilder(_config(on_failure="skip", new_segment_after=4))
    for index, image in enumerate(images):
        builder.process(index, image)
    return builder.finish(reread=reread)


@pytest.mark.slow
def test_a_new_segment_the_camera_comes_back_from_joins_the_first():
    """`_out_and_back`: the frames after the blink start a second segment; the frame that
    registers to the first segment again also registers to the second, which ties them:
    re-rendered, one mosaic, every frame at its true place."""
    images, truth = _out_and_back()
    live = _build_segments(images, None)  # no re-render: the live canvases cannot be joined
    assert len(live.segments) == 2
    joined = _build_segments(images, lambda: enumerate(images))
    frames = joined.report.to_dict()["frames"]
    statuses = [f["status"] for f in frames]
    assert statuses[10:16] == ["failed"] * 6 and statuses.count("registered") == len(images) - 6
    assert len(joined.segments) == 1 and joined.report.to_dict()["summary"]["segments"] == 1
    assert joined.main.n_frames == len(images) - 6
    assert joined.report.to_dict()["summary"]["tracking"]["joined_segments"] == 1
    assert live.report.to_dict()["summary"]["tracking"]["joined_segments"] == 0
    assert {f["segment"] for f in frames if f["status"] == "registered"} == {0}
    placed = [f for f in frames if f["status"] == "registered"]
    errors = errors_to_first(placed, truth, SIZE)[1:]
    assert np.max(errors) < 2.0, errors


def test_segments_stay_apart_where_the_first_cannot_be_rendered_again():
    """The input changes on re-reading (frame 3 unreadable): the first segment keeps its live
    canvas, and the segment the camera came back from is not joined to it but kept, its
    frames on its own canvas at their own poses."""
    images, truth = _out_and_back()

    def reread():
        return ((i, None if i == 3 else image) for i, image in enumerate(images))

    result = _build_segments(images, reread)
    frames = result.report.to_dict()["frames"]
    assert result.report.to_dict()["summary"]["tracking"]["joined_segments"] == 0
    assert len(result.segments) == 2 and result.report.to_dict()["summary"]["segments"] == 2
    registered = [f for f in frames if f["status"] == "registered"]
    assert sum(m.n_frames for m in result.segments) == len(registered) == len(images) - 6
    later = [f for f in registered if f["segment"] == 1]
    assert len(later) == result.segments[1].n_frames > 0
    for k in (0, 1):
        placed = [f for f in registered if f["segment"] == k]
        errors = errors_to_first(placed, truth, SIZE)[1:]
        assert np.max(errors) < 2.0, (k, errors)


def test_a_camera_back_over_a_later_segment_continues_it():
    """Crops of the sample: area A, a blink (dark frames: skipped), area B (far right), a
    blink, A again, a blink, B again. B's frames fail against A's mosaic until the 4th starts
    a segment; on the second visit the 4th continues B's segment instead of starting a third."""
    blink = [None] * 6
    xs = [150 + 15 * i for i in range(10)] + blink + list(range(800, 906, 15)) + blink
    xs += list(range(285, 220, -15)) + blink + list(range(905, 799, -15))
    images, truth = _along(xs, lambda: np.zeros((*SIZE[::-1], 3), np.uint8))
    builder = MosaicBuilder(_config(on_failure="skip", new_segment_after=4))
    for index, image in enumerate(images):
        builder.process(index, image)
    result = builder.finish()
    frames = result.report.to_dict()["frames"]
    segments = [f["segment"] for f, x in zip(frames, xs, strict=True) if x is not None]
    assert segments == [0] * 10 + [None] * 2 + [1] * 6 + [0] * 5 + [None] * 3 + [1] * 5
    assert len(result.segments) == 2
    statuses = [f["status"] for f, x in zip(frames, xs, strict=True) if x is None]
    assert statuses == ["skipped"] * 18
    for k in (0, 1):
        placed = [f for f in frames if f["segment"] == k and f["status"] == "registered"]
        errors = errors_to_first(placed, truth, SIZE)[1:]
        assert np.max(errors) < 2.0, (k, errors)


def test_stop_policy_ends_at_the_first_failure(video):
    folder, _ = video
    result = _run(folder, _config(on_failure="stop"), bad={7})
    summary = result.report.to_dict()["summary"]
    assert summary["frames_read"] == 8
    assert summary["frames_until_failure"] == 7
    assert summary["stopped_at_failure"]


def test_restart_policy_starts_a_new_segment(video, tmp_path):
    folder, _ = video
    other, _ = _frames_folder(tmp_path, 6, seed=11)  # a cut to another view (mirrored)
    images = [cv2.imread(str(p)) for p in sorted(folder.glob("*.png"))[:8]]
    images += [cv2.flip(cv2.imread(str(p)), 1) for p in sorted(other.glob("*.png"))]
    builder = MosaicBuilder(_config(on_failure="restart"))
    for index, image in enumerate(images):
        builder.process(index, image)
    result = builder.finish()
    frames = result.report.to_dict()["frames"]
    assert len(result.segments) == 2
    assert frames[8]["status"] == "failed" and frames[8]["segment"] == 1
    assert {f["segment"] for f in frames[:8]} == {0}
    assert {f["segment"] for f in frames[9:]} == {1}
    assert [f["status"] for f in frames[9:]] == ["registered"] * 5
    assert result.main.index == 0 and result.main.n_frames == 8


def test_corrupt_frame_is_skipped_and_counted(video):
    folder, _ = video
    result = _run(folder, _config(), corrupt={4})
    summary = result.report.to_dict()["summary"]
    assert summary["skipped"] == 1 and summary["registered"] == 23
    assert summary["frames_until_failure"] == 23
    assert result.report.to_dict()["frames"][4]["reason"] == "corrupt frame"


@pytest.mark.parametrize("on_failure", ["skip", "stop"])
def test_overlapped_stream_gives_the_serial_result(video, on_failure, monkeypatch):
    """Extracting frame i+1 in a background thread, always or as the overlap trial switches
    it on and off, must not change a single number."""
    monkeypatch.setattr(OverlapTrial, "WARMUP", 1)
    monkeypatch.setattr(OverlapTrial, "FRAMES", 3)  # auto decides at frame 9, within the video
    monkeypatch.setattr(OverlapTrial, "RETRIAL", 3)  # and tries again: switches back and forth
    folder, _ = video
    results = {}
    for overlap in ("off", "on", "auto"):
        builder = MosaicBuilder(_config(on_failure=on_failure, overlap=overlap))
        with open_frames(folder) as frames:

            def damaged(frames=frames):
                for frame in frames:  # frame 9 unregistrable: flat noise
                    if frame.index == 9:
                        rng = np.random.default_rng(9)
                        frame = Frame(9, rng.integers(0, 255, frame.image.shape, np.uint8))
                    yield frame

            for _ in builder.stream(damaged()):
                if builder.stopped:
                    break
        results[overlap] = builder.finish().report.to_dict()
    serial = results["off"]
    assert serial["summary"]["overlap"] is False and results["on"]["summary"]["overlap"] is True
    if on_failure == "skip":  # all 24 frames: the trial has chosen
        assert results["auto"]["summary"]["overlap"] in (True, False)
    for overlapped in (results["on"], results["auto"]):
        assert (
            len(overlapped["frames"])
            == len(serial["frames"])
            == (24 if on_failure == "skip" else 10)
        )
        for a, b in zip(serial["frames"], overlapped["frames"], strict=True):
            assert (a["index"], a["status"], a["n_keypoints"], a["n_inliers"]) == (
                b["index"],
                b["status"],
                b["n_keypoints"],
                b["n_inliers"],
            )
            if a["H_to_canvas"] is not None:
                np.testing.assert_allclose(a["H_to_canvas"], b["H_to_canvas"], atol=1e-9)
        assert overlapped["frames"][9]["status"] == "failed"


def test_glampoints_taking_turns_with_the_registration_gives_the_serial_result(video, monkeypatch):
    """GLAMpoints on the CPU: the network and the registration take turns (`Turns`) when
    extracting ahead, always or as the trial switches; the numbers stay those of the serial
    run."""
    for name, value in (("WARMUP", 1), ("FRAMES", 3), ("RETRIAL", 3)):
        monkeypatch.setattr(OverlapTrial, name, value)
    folder, _ = video
    reports, turns = {}, {}
    for overlap in ("off", "on", "auto"):
        config = with_overrides(Config(), pipeline={"overlap": overlap})
        builder = MosaicBuilder(config)
        with open_frames(folder) as frames:
            for _ in builder.stream(frames):
                pass
        reports[overlap], turns[overlap] = builder.finish().report.to_dict(), builder._turns.on
    assert turns["on"] == (torch.get_num_threads() > 1) and turns["off"] == turns["on"]
    extraction = {k: r["summary"]["extraction"] for k, r in reports.items()}
    assert extraction["off"] == "serial"
    assert extraction["on"] == ("turns" if turns["on"] else "overlapped")
    assert extraction["auto"] in ("serial", "overlapped", "turns")
    serial = reports["off"]["frames"]
    assert [f["status"] for f in serial] == ["registered"] * 24
    for overlapped in (reports["on"]["frames"], reports["auto"]["frames"]):
        assert [f["status"] for f in overlapped] == ["registered"] * 24
        for a, b in zip(serial, overlapped, strict=True):
            assert a["n_inliers"] == b["n_inliers"]
            np.testing.assert_allclose(a["H_to_canvas"], b["H_to_canvas"], atol=1e-9)


class _Clock:
    """A fake clock: each frame takes `ms(overlapped)` milliseconds."""

    def __init__(self, trial: OverlapTrial, ms):
        self.now, self.trial, self.ms = 0.0, trial, ms

    def __call__(self) -> float:
        return self.now

    def frame(self) -> bool:
        ahead = self.trial.ahead()
        self.now += self.ms(ahead) / 1e3
        self.trial.tick()
        return ahead


@pytest.mark.parametrize(
    ("overlapped_ms", "serial_ms", "chosen"), [(87, 78, False), (47, 55, True)]
)
def test_overlap_trial_keeps_the_faster_way(overlapped_ms, serial_ms, chosen):
    trial = OverlapTrial("auto")
    clock = _Clock(trial, lambda ahead: overlapped_ms if ahead else serial_ms)
    trial._clock = clock
    trial.tick()  # the clock starts at the first frame
    ways = [clock.frame() for _ in range(40)]
    n = OverlapTrial.WARMUP + OverlapTrial.FRAMES
    assert ways[:n] == [False] * n  # serial first, then overlapped until it has timed both
    assert ways[n : n + OverlapTrial.FRAMES + 2] == [True] * (OverlapTrial.FRAMES + 2)
    assert trial.chosen is chosen
    assert ways[-10:] == [chosen] * 10


@pytest.mark.parametrize(
    ("ms", "chosen"),
    [
        ({"serial": 61, "turns": 69, "overlapped": 53}, "overlapped"),
        ({"serial": 54, "turns": 45, "overlapped": 48}, "turns"),
        ({"serial": 50, "turns": 69, "overlapped": 53}, "serial"),
    ],
)
def test_overlap_trial_times_turns_and_free_overlap_where_the_network_takes_every_core(ms, chosen):
    """Where the network takes every core, the trial times three ways (serial, overlapped
    with turns, overlapped freely: which wins depends on the machine) and keeps the fastest;
    the frames right after each switch are not timed."""
    trial = OverlapTrial("auto", turns=True)
    clock, ways = 0.0, []

    def now() -> float:
        return clock

    trial._clock = now
    trial.tick()
    for _ in range(60):
        way = "turns" if trial.turns() else "overlapped" if trial.ahead() else "serial"
        ways.append(way)
        clock += ms[way] / 1e3
        trial.tick()
    first, settled = OverlapTrial.WARMUP + OverlapTrial.FRAMES, OverlapTrial.FRAMES + 2
    assert ways[:first] == ["serial"] * first
    assert ways[first : first + settled] == ["turns"] * settled
    assert ways[first + settled : first + 2 * settled] == ["overlapped"] * settled
    assert trial.way == chosen and trial.chosen is (chosen != "serial")
    assert ways[-10:] == [chosen] * 10


def test_overlap_trial_runs_again_and_follows_a_change(monkeypatch):
    monkeypatch.setattr(OverlapTrial, "RETRIAL", 60)
    trial = OverlapTrial("auto")
    speeds = {"overlapped": 87, "serial": 78}  # ms a frame
    clock = _Clock(trial, lambda ahead: speeds["overlapped" if ahead else "serial"])
    trial._clock = clock
    trial.tick()
    ways = [clock.frame() for _ in range(40)]
    assert trial.chosen is False and ways[-5:] == [False] * 5
    speeds["overlapped"] = 60  # the machine's other load went away
    ways = [clock.frame() for _ in range(90)]  # the next trial: frames 89-118
    assert trial.chosen is True and ways[-5:] == [True] * 5
    for mode in ("on", "off"):  # fixed: never timed, never switched
        fixed = OverlapTrial(mode)
        assert fixed.chosen is (mode == "on") and fixed.ahead() is (mode == "on")


def test_detecting_at_half_scale_still_follows_the_ground_truth(video):
    folder, gt = video
    result = _run(folder, with_overrides(_config(), features={"detect_scale": 0.5}))
    frames = result.report.to_dict()["frames"]
    assert result.report.to_dict()["summary"]["registered"] == 24
    errors = _errors_to_first(frames, gt, SIZE)
    assert np.mean(errors) < 4.0, errors


def _draw_overlay(folder: Path, graduated: bool = False) -> np.ndarray:
    """A fixation cross (black; `graduated`: with white ticks, texture to match) and a text line
    at the same place in every frame; the cross's mask."""
    cross = np.zeros((SIZE[1], SIZE[0]), np.uint8)
    cv2.rectangle(cross, (180, 110), (220, 190), 255, -1)
    cv2.rectangle(cross, (150, 135), (250, 165), 255, -1)
    ticks = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    if graduated:
        ticks[::8] = 255
        ticks[:, ::8] = 255
    for path in sorted(folder.glob("*.png")):
        image = cv2.imread(str(path))
        image[cross > 0] = ticks[cross > 0]
        text = "OD 12:34:56 ID 0042"
        cv2.putText(image, text, (20, 40), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2)
        cv2.imwrite(str(path), image)
    return cross


def test_burned_in_overlay_is_masked_and_registration_follows_the_retina(tmp_path):
    folder, gt = _frames_folder(tmp_path, 24)
    _draw_overlay(folder, graduated=True)  # a flat black cross has no keypoints to pull
    mean_error = {}
    for on in (False, True):
        # the paper's RANSAC homography as it comes (the re-weighted refinement alone takes much
        # of the overlay's pull away: 0.60 px without the mask)
        config = with_overrides(
            _config(strategy="chain"),
            preprocess={"overlay_mask": on},
            registration={"refine": False, "model": "homography"},
        )
        frames = _run(folder, config).report.to_dict()["frames"]
        assert [f["status"] for f in frames] == ["registered"] * 24
        H0 = np.array(frames[0]["H_to_canvas"])
        mean_error[on] = np.mean(
            [
                corner_error(
                    np.linalg.inv(H0) @ np.array(e["H_to_canvas"]),
                    np.linalg.inv(gt[0]) @ gt[e["index"]],
                    SIZE,
                )
                for e in frames[1:]
            ]
        )
    # measured: 0.56 px with the graduated cross's keypoints, 0.45 px without them (0.90 and
    # 0.68 before keypoints kept `border_margin_px` off the frame's edge)
    assert mean_error[True] < 1.0 and mean_error[True] < 0.85 * mean_error[False], mean_error


@pytest.mark.slow
def test_burned_in_overlay_is_left_out_of_the_rendered_mosaic(tmp_path):
    """Keyframes re-render from the video with the whole video's overlay estimate applied to
    every frame: the mosaic comes out close to the one of the same video without overlay."""
    (tmp_path / "clean").mkdir()
    (tmp_path / "marked").mkdir()
    clean, _ = _frames_folder(tmp_path / "clean", 24)
    marked, _ = _frames_folder(tmp_path / "marked", 24)
    _draw_overlay(marked)

    def mosaic_of(folder: Path, overlay_mask: bool) -> tuple[np.ndarray, np.ndarray]:
        config = with_overrides(
            Config(), features={"detector": "sift"}, preprocess={"overlay_mask": overlay_mask}
        )
        result = build_from_folder(folder, config)
        assert result.report.to_dict()["summary"]["tracking"]["rerendered"]
        H_0_to_mosaic = np.array(result.report.to_dict()["frames"][0]["H_to_canvas"])
        # in frame 0's pixels, so that mosaics with different bounding boxes compare
        size = (2 * SIZE[0], 2 * SIZE[1])
        shift = np.array([[1, 0, SIZE[0] / 2], [0, 1, SIZE[1] / 2], [0, 0, 1]])
        M = shift @ np.linalg.inv(H_0_to_mosaic)
        image = cv2.warpPerspective(result.main.image, M, size, flags=cv2.INTER_LINEAR)
        return image.astype(np.float32), image.max(axis=2) > 0

    reference, valid = mosaic_of(clean, False)
    errors = {}
    for on in (False, True):
        image, covered = mosaic_of(marked, on)
        both = valid & covered
        both = cv2.erode(both.view(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        errors[on] = float(np.abs(image - reference).max(axis=2)[both].mean())
    assert errors[True] < 0.5 * errors[False], errors  # measured: 0.66 vs 12.0 grey levels


def _upscaled(folder: Path, gt: list[np.ndarray], out: Path, k: int = 2):
    """The same video from a camera with k x the pixels (same field of view), and its truth."""
    out.mkdir()
    for path in sorted(folder.glob("*.png")):
        image = cv2.imread(str(path))
        cv2.imwrite(str(out / path.name), cv2.resize(image, None, fx=k, fy=k, interpolation=3))
    H_big_to_small = np.array([[1 / k, 0, 0.5 / k - 0.5], [0, 1 / k, 0.5 / k - 0.5], [0, 0, 1]])
    return out, [H @ H_big_to_small for H in gt]


def _shows_frame(mosaic: np.ndarray, frame: np.ndarray, H_frame_to_mosaic: np.ndarray) -> float:
    """Median grey-level difference between the mosaic and a frame put where H_frame_to_mosaic
    says (the frame first brought to about the mosaic's scale), away from the frame's edge."""
    s = float(np.sqrt(abs(np.linalg.det(H_frame_to_mosaic[:2, :2]))))
    small = cv2.resize(frame, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 0.9 else frame
    S = scale_matrix(frame.shape, small.shape)
    H = H_frame_to_mosaic @ np.linalg.inv(S)
    size = (mosaic.shape[1], mosaic.shape[0])
    warped = cv2.warpPerspective(small, H, size)
    inside = cv2.warpPerspective(np.full(small.shape[:2], 255, np.uint8), H, size)
    inside = cv2.erode(inside, np.ones((31, 31), np.uint8)) > 0
    return float(np.median(np.abs(mosaic.astype(int) - warped.astype(int))[inside]))


@pytest.mark.slow
def test_large_frames_register_and_compose_at_the_working_size(video, tmp_path):
    """A 2x camera registered at half size gives what the 1x camera gives, in its own pixels;
    its mosaic is composed at the working size (`[compose] resolution = "working"`), or from
    the frames as decoded (`"full"`), and the report maps the frames' pixels into either."""
    folder, gt = video
    big, gt_big = _upscaled(folder, gt, tmp_path / "big")
    small_result = _run(folder, _config())
    half = with_overrides(_config(), preprocess={"max_side_px": 400})
    result = _run(big, half)
    summary = result.report.to_dict()["summary"]
    assert summary["working_scale"] == 0.5 and summary["registered"] == 24
    frames = result.report.to_dict()["frames"]
    errors = _errors_to_first(frames, gt_big, (2 * SIZE[0], 2 * SIZE[1]))
    assert np.mean(errors) < 6.0 and np.max(errors) < 12.0, errors  # the 1x bounds, doubled
    frame = cv2.imread(str(sorted(big.glob("*.png"))[12]))
    small_mosaic = np.array(small_result.main.image.shape[:2])
    # composed at the working size: the 1x mosaic's size, the frames' pixels where the report
    # puts them
    mosaic = result.main.image
    np.testing.assert_allclose(mosaic.shape[:2], small_mosaic, atol=4)
    assert _shows_frame(mosaic, frame, np.array(frames[12]["H_to_canvas"])) < 6
    # composed from the frames as decoded: twice the 1x mosaic, the same poses
    full_size = _run(big, with_overrides(half, compose={"resolution": "full"}))
    mosaic = full_size.main.image
    np.testing.assert_allclose(mosaic.shape[:2], 2 * small_mosaic, atol=8)
    full_frames = full_size.report.to_dict()["frames"]
    assert _shows_frame(mosaic, frame, np.array(full_frames[12]["H_to_canvas"])) < 6
    np.testing.assert_allclose(
        _errors_to_first(full_frames, gt_big, (2 * SIZE[0], 2 * SIZE[1])), errors, atol=1e-6
    )
    # with the working size off, the same frames register at full size (slower, same answer)
    full = _run(big, with_overrides(_config(), preprocess={"max_side_px": 0}))
    assert full.report.to_dict()["summary"]["working_scale"] == 1.0
    assert full.report.to_dict()["summary"]["registered"] == 24


def test_a_video_of_whole_retinas_is_registered_with_its_retina_at_the_detectors_scale(tmp_path):
    """Fundus video showing the whole retina (the sample photograph, turned and shifted): the
    first frame's retina sets one working scale for all frames, [preprocess] fov_diameter_px
    over its diameter, reported with it; with the rule off, max_side_px applies as before."""
    source = cv2.imread(str(SAMPLE_IMAGE))
    h, w = source.shape[:2]
    folder = tmp_path / "fundus"
    folder.mkdir()
    truth = [similarity(1.5 * k, 1.0, 12.0 * k, -8.0 * k, (w / 2, h / 2)) for k in range(6)]
    for k, G in enumerate(truth):  # H_frame_to_source
        frame = cv2.warpPerspective(source, np.linalg.inv(G), (w, h))
        cv2.imwrite(str(folder / f"frame{k:02d}.png"), frame)
    result = _run(folder, _config())
    summary = result.report.to_dict()["summary"]
    assert summary["retina_diameter_px"] == pytest.approx(1400.0, rel=0.01)  # 1411 px image
    assert summary["working_scale"] == pytest.approx(512 / summary["retina_diameter_px"], 1e-3)
    assert summary["registered"] == 6
    errors = _errors_to_first(result.report.to_dict()["frames"], truth, (w, h))
    assert np.max(errors) < 3.0, errors  # full-resolution pixels
    off = _run(folder, with_overrides(_config(), preprocess={"fov_diameter_px": 0}))
    assert off.report.to_dict()["summary"]["retina_diameter_px"] is None
    assert off.report.to_dict()["summary"]["working_scale"] == pytest.approx(800 / 1411, 1e-3)


def test_the_retina_rule_changes_nothing_where_the_retina_is_under_fov_diameter_px(video):
    """The fixture's 400x300 frames show a whole round view 395 px across: under 512 px, so
    the frames register at full size, exactly as with the rule off."""
    folder, _ = video
    result = _run(folder, _config())
    off = _run(folder, with_overrides(_config(), preprocess={"fov_diameter_px": 0}))
    assert result.report.to_dict()["summary"]["retina_diameter_px"] == pytest.approx(395, abs=5)
    assert off.report.to_dict()["summary"]["retina_diameter_px"] is None
    assert result.report.to_dict()["summary"]["working_scale"] == 1.0
    poses = [f["H_to_canvas"] for f in result.report.to_dict()["frames"]]
    assert poses == [f["H_to_canvas"] for f in off.report.to_dict()["frames"]]


class _Events:
    """A viewer that keeps what it is shown."""

    def __init__(self):
        self.events = []

    def frame(self, event) -> None:
        self.events.append(event)

    def finish(self, report, mosaic=None) -> None:
        pass


def test_viewer_sees_keypoints_and_matches_in_the_pixels_of_the_frame_it_shows(video, tmp_path):
    """Registered at half size, drawn on the full-size frame: points must land on the same
    structures, so the matched points of frame k and their partners in the reference agree
    with the reported homography in full-size pixels."""
    folder, gt = video
    big, _ = _upscaled(folder, gt, tmp_path / "big")
    viewer = _Events()
    config = with_overrides(_config(strategy="chain"), preprocess={"max_side_px": 400})
    builder = MosaicBuilder(config, viewer=viewer)
    with open_frames(big) as frames:
        for frame in frames:
            builder.process(frame.index, frame.image, frame.error)
    event = viewer.events[5]
    assert event.image.shape[:2] == (2 * SIZE[1], 2 * SIZE[0])
    xy = event.features.xy
    assert xy[:, 0].max() > 1.5 * SIZE[0] and xy[:, 1].max() > 1.5 * SIZE[1]  # full-size spread
    inl = event.registration.inliers
    cur = xy[event.matches.idx_b][inl]
    ref = event.reference.xy[event.matches.idx_a][inl]  # chain: the previous frame's points
    H_cur_to_ref = (
        np.linalg.inv(viewer.events[4].record.H_frame_to_ref) @ event.record.H_frame_to_ref
    )
    mapped = cv2.perspectiveTransform(cur[None].astype(np.float64), H_cur_to_ref)[0]
    assert np.median(np.linalg.norm(mapped - ref, axis=1)) < 2.0  # ~1 px at half size, doubled


def _turn_taking(stop_after: int | None = None, skipped: frozenset[int] = frozenset()):
    """Extract 12 fake items ahead and register them with `Turns`: (events, busy overlaps)."""
    turns, events, clash = Turns(on=True), [], []
    busy = {"detect": False, "register": False}

    def extract(k: int) -> int:
        if k not in skipped:  # a skipped frame counts as detected without the network
            turns.before_detect()
            busy["detect"] = True
            clash.append(busy["register"])
            time.sleep(0.003)
            events.append(("detect", k))
            busy["detect"] = False
        turns.detected()
        time.sleep(0.002)  # describing: beside a registration
        return k

    def consume() -> None:
        items = (extract(k) for k in range(12))
        with Lookahead(turns.ended_after(items), depth=2) as it, turns:
            for j, k in enumerate(it):
                assert j == k
                turns.before_register(j, it.ahead)
                busy["register"] = True
                clash.append(busy["detect"])
                events.append(("register", j))
                time.sleep(0.003)
                busy["register"] = False
                turns.registered()
                if stop_after is not None and j == stop_after:
                    return

    runner = threading.Thread(target=consume)
    runner.start()
    runner.join(timeout=10)
    assert not runner.is_alive(), "turn taking deadlocked"
    return events, clash


def test_turns_keep_the_network_and_the_registration_apart():
    events, clash = _turn_taking(skipped=frozenset({4, 5}))
    assert not any(clash)  # never the network while a frame registers, nor the reverse
    order = {event: i for i, event in enumerate(events)}
    detected = [k for kind, k in events if kind == "detect"]
    assert detected == [k for k in range(12) if k not in (4, 5)]
    for j in range(11):  # frame j registers once frame j + 1 is detected (or skipped) ...
        if j + 1 not in (4, 5):
            assert order["detect", j + 1] < order["register", j]
    for k in range(2, 12):  # ... and frame k's network waits for frame k - 2's registration
        if k not in (4, 5):
            assert order["register", k - 2] < order["detect", k]


def test_turns_let_a_stream_stop_early_without_waiting():
    events, _ = _turn_taking(stop_after=3)
    assert ("register", 3) in events and ("register", 4) not in events


@pytest.mark.parametrize("whole_retina", [True, False])
def test_auto_refines_photographs_of_a_whole_retina_whatever_the_coarse_model(
    whole_retina, monkeypatch
):
    """At the working size a similarity can win the coarse model selection on a fundus pair;
    `auto` then still refines to full resolution (the quadratic here, within a pixel of the
    exact truth), while views without a retina's rim (magnified) keep the simpler model."""
    import dataclasses

    from mosaic import pairs
    from mosaic.features import FeatureExtractor
    from mosaic.registration import apply_quadratic
    from mosaic.synthetic.curved import curved_pair

    pair = curved_pair(cv2.imread(str(SAMPLE_IMAGE)), seed=3, size=1024)
    fixed, moving = pair.fixed, pair.moving
    if not whole_retina:
        fixed, moving = fixed[212:812, 212:812], moving[212:812, 212:812]
    estimate = pairs.estimate_motion

    def as_similarity(*args, **kwargs):
        return dataclasses.replace(estimate(*args, **kwargs), model="similarity")

    monkeypatch.setattr(pairs, "estimate_motion", as_similarity)
    config = _config()
    reg = pairs.register_pair(fixed, moving, config, FeatureExtractor(config.features), "auto")
    assert reg.ok
    if not whole_retina:
        assert reg.model == "similarity" and not reg.refined_levels
        return
    assert reg.model == "quadratic" and reg.refined_levels == 3
    cp = pair.control_points
    error = np.linalg.norm(apply_quadratic(reg.Q_moving_to_fixed, cp[:, 2:]) - cp[:, :2], axis=1)
    assert error.mean() < 1.0, error


@pytest.mark.parametrize("vessel_polarity", [True, False])
def test_an_angiogram_is_registered_to_a_colour_photograph_once_inverted(
    vessel_polarity, monkeypatch
):
    """A follow-up pair whose moving photograph has bright vessels (an angiogram's polarity:
    here the colour photograph's negative inside its view) is registered within a pixel of the
    exact truth once that photograph is inverted; without the inversion its descriptors do not
    match the colour photograph's and the pair fails or is placed wildly. Two photographs of
    one kind are registered once, as they are."""
    from mosaic import pairs
    from mosaic.features import FeatureExtractor
    from mosaic.preprocess import invert_in_view
    from mosaic.registration import apply_homography, apply_quadratic
    from mosaic.synthetic.curved import curved_pair

    pair = curved_pair(cv2.imread(str(SAMPLE_IMAGE)), seed=3, size=1024)
    angiogram = invert_in_view(pair.moving)
    config = with_overrides(
        Config(), features={"detector": "sift"}, preprocess={"vessel_polarity": vessel_polarity}
    )
    extractor = FeatureExtractor(config.features)
    reg = pairs.register_pair(pair.fixed, angiogram, config, extractor, "auto")
    cp = pair.control_points
    if not vessel_polarity:
        if reg.ok:
            mapped = apply_homography(reg.H_moving_to_fixed, cp[:, 2:])
            error = np.linalg.norm(mapped - cp[:, :2], 1)
            assert error.mean() > 10.0
        assert reg.inverted == (False, False)
        return
    assert reg.ok and reg.inverted == (True, False)  # (moving, fixed)
    calls = []
    register_once = pairs._register_pair
    monkeypatch.setattr(pairs, "_register_pair", lambda *a: calls.append(a) or register_once(*a))
    same_kind = pairs.register_pair(pair.fixed, pair.moving, config, extractor, "auto")
    assert same_kind.ok and same_kind.inverted == (False, False) and len(calls) == 1
    mapped = (
        apply_quadratic(reg.Q_moving_to_fixed, cp[:, 2:])
        if reg.Q_moving_to_fixed is not None
        else apply_homography(reg.H_moving_to_fixed, cp[:, 2:])
    )
    error = np.linalg.norm(mapped - cp[:, :2], axis=1)
    assert error.mean() < 1.0, error


@pytest.mark.slow
def test_an_interlaced_video_is_registered_on_its_first_fields(video, tmp_path):
    """An interlaced camera's video (odd rows half a frame interval later): with
    `deinterlace` each frame is its first field and the poses follow the truth (the first
    fields' poses) as closely as on the progressive video; without it the report says the
    video looks interlaced. A progressive video looks progressive."""
    folder = tmp_path / "interlaced"
    params = SynthParams(n_frames=24, size=SIZE, seed=3, nuisances=False, interlaced=True)
    gt = load_ground_truth(write_synthetic_video(SAMPLE_IMAGE, folder, params))
    off = build_from_folder(folder, _config())
    on = build_from_folder(folder, with_overrides(_config(), preprocess={"deinterlace": True}))
    summary_off, summary_on = off.report.to_dict()["summary"], on.report.to_dict()["summary"]
    assert summary_off["looks_interlaced"] and summary_off["field_offset_px"] > 3
    assert summary_off["deinterlaced"] == 0
    assert summary_on["deinterlaced"] == 24 and summary_on["registered"] == 24
    assert all(f["deinterlaced"] for f in on.report.to_dict()["frames"])
    errors_off = _errors_to_first(off.report.to_dict()["frames"], gt, SIZE)
    errors_on = _errors_to_first(on.report.to_dict()["frames"], gt, SIZE)
    progressive = build_from_folder(video[0], _config())  # the same seed, progressive
    errors_progressive = _errors_to_first(progressive.report.to_dict()["frames"], video[1], SIZE)
    # measured: combed 3.4 px, first fields 0.9 px, progressive 1.0 px
    assert np.mean(errors_on) < 0.4 * np.mean(errors_off), (errors_on, errors_off)
    assert np.mean(errors_on) < 1.5 * np.mean(errors_progressive) + 0.3
    summary = progressive.report.to_dict()["summary"]
    assert not summary["looks_interlaced"] and summary["field_offset_px"] < 0.5


def test_the_report_says_which_precision_the_network_ran_in(tmp_path):
    """Figures differ between float32 and bfloat16 (single videos by 0.3), and "auto" depends
    on the CPU: the report names the precision that ran, and none for detectors without a
    network."""
    folder, _ = _frames_folder(tmp_path, 3)
    for detector, precision, expected in (
        ("glampoints", "float32", "float32"),
        ("glampoints", "bfloat16", "bfloat16"),
        ("sift", "auto", None),
    ):
        config = with_overrides(Config(), features={"detector": detector, "precision": precision})
        summary = _run(folder, config).report.to_dict()["summary"]
        assert summary["precision"] == expected and summary["registered"] == 3, summary


def test_hazy_frames_lose_the_lifted_surround_and_stay_on_the_truth(tmp_path):
    """Haze lifts the dark aperture's surround into the last frames' view masks: it is left
    out of those frames alone (`[preprocess] surround_mask`), which the report says, and the
    frames are placed by the retina."""
    folder = tmp_path / "hazy"
    params = SynthParams(n_frames=16, size=SIZE, seed=3, haze_frames=5)
    gt = load_ground_truth(write_synthetic_video(SAMPLE_IMAGE, folder, params))
    report = _run(folder, _config()).report.to_dict()
    lifted = [f["index"] for f in report["frames"] if f["surround_lifted"]]
    assert lifted == list(range(11, 16))
    assert report["summary"]["surround_lifted_frames"] == 5
    placed = [f for f in report["frames"] if f["status"] == "registered"]
    assert len(placed) >= 14
    assert max(errors_to_first(placed, gt, SIZE)) < 10.0
