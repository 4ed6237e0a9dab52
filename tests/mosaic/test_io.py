"""Frame streaming from folders and videos, input validation and the output writers."""

from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from mosaic.errors import InputError, OutputError
from mosaic.io import (
    Lookahead,
    check_distinct_paths,
    check_output_path,
    natural_key,
    open_frames,
    read_image,
    sample_image_path,
    write_image,
    write_json,
)
from tests.helpers import locked

W, H = 64, 48


def _pattern(value: int) -> np.ndarray:
    """A BGR frame whose pixel (0, 0) encodes `value`, rest a fixed gradient."""
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = np.arange(W, dtype=np.uint8)[None, :] * 3
    img[..., 1] = np.arange(H, dtype=np.uint8)[:, None] * 5
    img[..., 2] = 100
    img[:4, :4] = value
    return img


def _folder(tmp_path: Path, n: int, name: str = "frame{}.png") -> Path:
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(n):
        assert cv2.imwrite(str(folder / name.format(i)), _pattern(10 * i))
    return folder


def test_folder_is_sorted_naturally_and_indexed(tmp_path):
    folder = _folder(tmp_path, 12)  # frame0 .. frame11: lexical order would put frame10 first
    (folder / "notes.txt").write_text("not a frame")
    with open_frames(folder) as source:
        assert source.info.kind == "folder"
        assert (source.info.n_frames, source.info.width, source.info.height) == (12, W, H)
        assert source.info.fps is None
        frames = list(source)
    assert [f.index for f in frames] == list(range(12))
    # Frame i really is the file frame{i}: its marker pixel is 10 * i.
    assert [int(f.image[0, 0, 0]) for f in frames] == [10 * i for i in range(12)]
    assert all(f.error is None and f.image.shape == (H, W, 3) for f in frames)
    assert sorted(["frame10", "frame2", "frame1"], key=natural_key) == [
        "frame1",
        "frame2",
        "frame10",
    ]


def test_step_and_max_frames_keep_original_indices(tmp_path):
    folder = _folder(tmp_path, 12)
    with open_frames(folder, step=3) as source:
        assert [f.index for f in source] == [0, 3, 6, 9]
        assert source.expected_frames == 4
    with open_frames(folder, step=2, max_frames=4) as source:
        frames = list(source)
        assert source.expected_frames == 4
    assert [f.index for f in frames] == [0, 2, 4, 6]
    assert [int(f.image[0, 0, 0]) for f in frames] == [0, 20, 40, 60]


def test_grey_and_16bit_images_become_bgr8(tmp_path):
    folder = tmp_path / "grey"
    folder.mkdir()
    grey = _pattern(7)[..., 1]
    cv2.imwrite(str(folder / "a1.png"), grey)
    cv2.imwrite(str(folder / "a2.png"), grey.astype(np.uint16) * 257)  # 16-bit, same content
    with open_frames(folder) as source:
        frames = list(source)
    for frame in frames:
        assert frame.image.dtype == np.uint8 and frame.image.shape == (H, W, 3)
        for c in range(3):
            np.testing.assert_array_equal(frame.image[..., c], grey)
    rgba = np.dstack([_pattern(5), np.full((H, W), 128, np.uint8)])
    cv2.imwrite(str(tmp_path / "alpha.png"), rgba)
    np.testing.assert_array_equal(read_image(tmp_path / "alpha.png"), _pattern(5))


def test_corrupt_image_in_folder_is_reported_and_iteration_goes_on(tmp_path, caplog):
    folder = _folder(tmp_path, 5)
    (folder / "frame2.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage, not an image")
    caplog.set_level(logging.INFO, logger="mosaic.io")  # the pipeline warns when it skips it
    with open_frames(folder) as source:
        frames = list(source)
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    bad = frames[2]
    assert bad.image is None and bad.error and "frame2.png" in bad.error
    assert all(f.image is not None and f.error is None for f in frames if f.index != 2)
    assert int(frames[4].image[0, 0, 0]) == 40
    assert any("frame 2" in r.getMessage() for r in caplog.records)


def test_frame_of_a_different_size_is_reported(tmp_path):
    folder = _folder(tmp_path, 3)
    cv2.imwrite(str(folder / "frame1.png"), np.zeros((10, 10, 3), np.uint8))
    with open_frames(folder) as source:
        frames = list(source)
    assert frames[1].image is None and "10x10" in frames[1].error
    assert frames[2].image is not None


def test_input_errors_name_the_path(tmp_path):
    missing = tmp_path / "nope.mp4"
    with pytest.raises(InputError, match="not found") as err:
        open_frames(missing)
    assert str(missing) in str(err.value)

    text = tmp_path / "notes.mp4"
    text.write_text("this is not a video\n" * 20)
    with pytest.raises(InputError, match="not a video OpenCV can read") as err:
        open_frames(text)
    assert str(text) in str(err.value)

    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no images") as err:
        open_frames(empty)
    assert str(empty) in str(err.value)

    (empty / "readme.txt").write_text("x")
    with pytest.raises(InputError, match="no images"):
        open_frames(empty)

    with pytest.raises(InputError, match="step"):
        open_frames(_folder(tmp_path, 1), step=0)

    with pytest.raises(InputError, match=str(tmp_path / "missing.png")):
        read_image(tmp_path / "missing.png")
    with pytest.raises(InputError, match="cannot read image"):
        read_image(text)


def test_video_round_trip_frame_count_size_step(tmp_path):
    path = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), 20.0, (W, H))
    assert writer.isOpened()
    for i in range(15):
        writer.write(_pattern(16 * i))
    writer.release()

    with open_frames(path) as source:
        info = source.info
        frames = list(source)
    assert (info.kind, info.n_frames, info.width, info.height) == ("video", 15, W, H)
    assert info.fps == pytest.approx(20.0)
    assert [f.index for f in frames] == list(range(15))
    assert all(f.image.shape == (H, W, 3) and f.image.dtype == np.uint8 for f in frames)
    # Lossy codec, but the marker block still identifies the frame.
    markers = [int(f.image[1, 1].mean()) for f in frames]
    assert np.allclose(markers, [16 * i for i in range(15)], atol=12)

    with open_frames(path, step=4, max_frames=3) as source:
        picked = list(source)
        again = [f.index for f in source]  # a second iteration starts over
    assert [f.index for f in picked] == [0, 4, 8] == again
    assert abs(int(picked[2].image[1, 1].mean()) - 128) <= 12


def test_corrupt_frame_mid_video_is_reported_with_its_index(tmp_path):
    path = tmp_path / "clip.avi"  # MJPG: one JPEG per frame, easy to damage a single one
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (W, H))
    for i in range(8):
        writer.write(np.full((H, W, 3), 20 * i + 10, np.uint8))
    writer.release()
    data = bytearray(path.read_bytes())
    starts = [0]
    for _ in range(4):  # start of the 4th JPEG (frame 3)
        starts.append(data.index(b"\xff\xd8\xff", starts[-1] + 1))
    data[starts[-1] : starts[-1] + 200] = bytes(200)
    path.write_bytes(bytes(data))

    with open_frames(path) as source:
        frames = list(source)
    assert [f.index for f in frames] == list(range(8))
    assert frames[3].image is None and frames[3].error
    means = [round(float(f.image.mean())) for f in frames if f.image is not None]
    assert np.allclose(means, [20 * i + 10 for i in (0, 1, 2, 4, 5, 6, 7)], atol=3)
    with open_frames(path, step=3) as source:
        assert [(f.index, f.image is None) for f in source] == [(0, False), (3, True), (6, False)]


def test_closed_source_refuses_iteration(tmp_path):
    source = open_frames(_folder(tmp_path, 2))
    source.close()
    with pytest.raises(ValueError, match="closed"):
        iter(source)


def test_check_output_path(tmp_path):
    with pytest.raises(OutputError, match="output folder does not exist") as err:
        check_output_path(tmp_path / "missing" / "mosaic.png")
    assert str(tmp_path / "missing") in str(err.value)
    with pytest.raises(OutputError, match="unsupported output format"):
        check_output_path(tmp_path / "mosaic.xyz")
    with pytest.raises(OutputError, match="folder"):
        check_output_path(tmp_path)
    assert check_output_path(tmp_path / "mosaic.png") == tmp_path / "mosaic.png"
    assert check_output_path(tmp_path / "report.json") == tmp_path / "report.json"
    with pytest.raises(OutputError):
        check_output_path(tmp_path / "report.json", suffixes=frozenset({".png"}))
    folder = tmp_path / "locked"
    folder.mkdir()
    with locked(folder), pytest.raises(OutputError, match="not writable"):
        check_output_path(folder / "mosaic.png")
    earlier = tmp_path / "earlier.png"
    earlier.write_bytes(b"kept")
    with locked(earlier), pytest.raises(OutputError, match=str(earlier)):
        check_output_path(earlier)  # read-only (a user) or immutable (root): refused now
    assert earlier.read_bytes() == b"kept"
    with pytest.raises(OutputError, match="cannot write"):
        check_output_path(tmp_path / ("m" * 300 + ".png"))  # a name too long, for anyone


def test_outputs_must_be_distinct_files_and_not_an_input(tmp_path):
    """Two outputs of one command, or an output and an input, naming one file (spelt another
    way, through a symbolic or a hard link) are refused: the later write would replace the
    earlier one after the whole run (issue 40)."""
    mosaic, report = tmp_path / "m.png", tmp_path / "m.json"
    check_distinct_paths({"--output": mosaic, "--report": report}, {"VIDEO": tmp_path / "v.mp4"})
    same = tmp_path / "sub" / ".." / "m.png"
    with pytest.raises(OutputError, match=r"--output and --report are the same file.*m\.png"):
        check_distinct_paths({"--output": mosaic, "--report": same})
    mosaic.write_bytes(b"x")
    (tmp_path / "soft.png").symlink_to(mosaic)
    os.link(mosaic, tmp_path / "hard.png")
    for other in ("soft.png", "hard.png"):
        with pytest.raises(OutputError, match="same file"):
            check_distinct_paths({"--warp": mosaic, "--matches": tmp_path / other})
    with pytest.raises(OutputError, match="--warp would write over the input FIXED"):
        check_distinct_paths({"--warp": tmp_path / "hard.png"}, {"FIXED": mosaic})


def test_write_json_round_trip_with_numpy_values(tmp_path):
    obj = {
        "H": np.eye(3) * 2.5,
        "n": np.int64(7),
        "x": np.float32(0.5),
        "ok": np.bool_(True),
        "pts": np.arange(4, dtype=np.float32).reshape(2, 2),
        "path": tmp_path,
    }
    path = write_json(tmp_path / "r.json", obj)
    data = json.loads(path.read_text())
    assert data == {
        "H": (np.eye(3) * 2.5).tolist(),
        "n": 7,
        "x": 0.5,
        "ok": True,
        "pts": [[0.0, 1.0], [2.0, 3.0]],
        "path": str(tmp_path),
    }
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temporary left behind
    with pytest.raises(OutputError, match="does not exist"):
        write_json(tmp_path / "missing" / "r.json", {})


def test_write_image_and_read_back(tmp_path):
    img = _pattern(200)
    np.testing.assert_array_equal(read_image(write_image(tmp_path / "m.png", img)), img)
    jpg = read_image(write_image(tmp_path / "m.jpg", img))
    assert jpg.shape == img.shape and np.abs(jpg.astype(int) - img).mean() < 4
    with pytest.raises(OutputError):
        write_image(tmp_path / "missing" / "m.png", img)
    with pytest.raises(OutputError):
        write_image(tmp_path / "m.xyz", img)


def test_sample_image_is_shipped():
    path = sample_image_path()
    assert path.is_file() and path.name == "retina.jpg"
    assert read_image(path).shape == (1411, 1411, 3)


def test_lookahead_produces_in_order_ahead_or_not_and_reraises_at_the_item():
    producers: list[str] = []

    def items():
        for i in range(8):
            producers.append(threading.current_thread().name)
            if i == 6:
                raise ValueError("frame 6")
            yield i

    got = []
    with Lookahead(items(), depth=2) as it:
        for ahead in (True, True, False, False, True, True):  # switched between items
            got.append(next(it))
            it.ahead = ahead
        with pytest.raises(ValueError, match="frame 6"):
            next(it)
    assert got == list(range(6))
    # ahead: 1-4 by the worker; switched off after 2: 3-4 were already asked for, 5 by the
    # caller; on again: 6 by the worker, whose exception comes with that item
    by_worker = [name.startswith("lookahead") for name in producers[:7]]
    assert by_worker == [False, True, True, True, True, False, True]


def test_lookahead_ends_and_stops_its_thread():
    it = Lookahead(iter(range(3)), depth=2)
    assert list(it) == [0, 1, 2]
    it.close()
    assert not any(t.name.startswith("lookahead") for t in threading.enumerate())
