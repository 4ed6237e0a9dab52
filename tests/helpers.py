"""Geometry helpers for tests: known-homography views and corner errors."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from mosaic.geometry import corner_error
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from mosaic.synthetic.truth import gt_path_for, load_ground_truth
from tests.conftest import SAMPLE_IMAGE


def crop_pair(
    image: np.ndarray, H_b_to_a: np.ndarray, origin: tuple[int, int], size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Two views a, b of `image`: a is a plain crop at `origin`; b maps into a by `H_b_to_a`."""
    x0, y0 = origin
    w, h = size
    T = np.array([[1.0, 0, x0], [0, 1.0, y0], [0, 0, 1.0]])
    a = image[y0 : y0 + h, x0 : x0 + w].copy()
    H_b_to_image = T @ H_b_to_a
    b = cv2.warpPerspective(
        image, H_b_to_image, (w, h), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR
    )
    return a, b


def similarity(
    angle_deg: float, scale: float, tx: float, ty: float, center=(0.0, 0.0)
) -> np.ndarray:
    """3x3 rotation+scale about `center`, then translation."""
    A = cv2.getRotationMatrix2D(center, angle_deg, scale)
    H = np.vstack([A, [0, 0, 1]])
    H[0, 2] += tx
    H[1, 2] += ty
    return H


def noisy_magnified_views(
    fundus: np.ndarray, zoom_error: float, shift_error_px: float
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Four noise draws of two 400x300 views of the photograph magnified 4x (noise sd 8 on
    both, the second blurred by 2 px and 20 % brighter), for registrations a → b that are
    off: (a, b, corner points of a, the truth H_a_to_b, a start that is `zoom_error` too
    zoomed about the points' centre and `shift_error_px` off in x)."""
    g = cv2.resize(fundus, None, fx=4.0, fy=4.0, interpolation=cv2.INTER_CUBIC)[..., 1]
    H_b_to_a = similarity(1.5, 1.01, 7.3, -4.6, center=(200, 150))
    a0, b0 = crop_pair(g, H_b_to_a, (1400, 1000), (400, 300))
    H_a_to_b = np.linalg.inv(H_b_to_a)
    xy = cv2.goodFeaturesToTrack(a0, 100, 0.01, 8).reshape(-1, 2).astype(np.float64)
    xy = xy[(xy > 30).all(1) & (xy < [370, 270]).all(1)]
    c = xy.mean(0)
    z, dx, dy = 1.0 + zoom_error, shift_error_px - zoom_error * c[0], -zoom_error * c[1]
    off = np.array([[z, 0, dx], [0, z, dy], [0, 0, 1]])
    for seed in range(4):
        rng = np.random.default_rng(seed)
        a = np.clip(a0 + rng.normal(0, 8, a0.shape), 0, 255).astype(np.uint8)
        b = cv2.GaussianBlur(b0.astype(np.float32), (0, 0), 2.0) * 1.2
        b = np.clip(b + rng.normal(0, 8, b.shape), 0, 255).astype(np.uint8)
        yield a, b, xy, H_a_to_b, off @ H_a_to_b


def errors_to_first(
    frames: list[dict], truth: list[np.ndarray], size: tuple[int, int]
) -> np.ndarray:
    """Corner error (px) of each reported frame's pose relative to the report's first frame,
    against the truth (`H_frame_to_source` per input index); inf where a frame is not placed."""
    H0 = np.array(frames[0]["H_to_canvas"])
    G0_inv = np.linalg.inv(truth[frames[0]["index"]])
    return np.array(
        [
            np.inf
            if e["H_to_canvas"] is None
            else corner_error(
                np.linalg.inv(H0) @ np.array(e["H_to_canvas"]), G0_inv @ truth[e["index"]], size
            )
            for e in frames
        ]
    )


def build_from_folder(folder, config):
    """`mosaic build` of a folder of frames, streamed, re-read for the re-render."""
    from mosaic.io import open_frames
    from mosaic.pipeline import MosaicBuilder

    builder = MosaicBuilder(config)
    with open_frames(folder) as frames:
        for _ in builder.stream(frames):
            pass

    def reread():
        with open_frames(folder) as again:
            for frame in again:
                yield frame.index, frame.image

    return builder.finish(reread=reread)


def empty_report():
    """The report of a builder that has seen no frame (a `BuildReport` for viewer tests)."""
    from mosaic.config import Config, with_overrides
    from mosaic.pipeline import MosaicBuilder

    return MosaicBuilder(with_overrides(Config(), features={"detector": "orb"})).snapshot().report


def chattr(path, flag: str) -> bool:
    """`chattr FLAG PATH` (e.g. "+i": immutable); False where the tool or the right is missing."""
    import shutil
    import subprocess

    tool = shutil.which("chattr")
    if tool is None:
        return False
    return subprocess.run([tool, flag, str(path)], capture_output=True).returncode == 0


@contextlib.contextmanager
def locked(path):
    """`path` (a file or folder) made unwritable for the duration: no write permission for a
    user; immutable for root, whom permissions do not stop. Fails (never skips) where neither
    is possible, so an "unwritable" test always runs."""
    import os

    import pytest

    if os.geteuid() != 0:
        mode = path.stat().st_mode
        path.chmod(0o500 if path.is_dir() else 0o444)
        try:
            yield path
        finally:
            path.chmod(mode)
        return
    if not chattr(path, "+i"):
        pytest.fail("running as root without chattr +i: cannot make a path unwritable")
    try:
        yield path
    finally:
        chattr(path, "-i")


def left_and_back(
    tmp_path: Path, folder: Path, truth: list[np.ndarray], size: tuple[int, int]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A camera that leaves the mapped area and comes back: frames 0-11 of the video in
    `folder` (24 frames, `truth` its H_frame_to_source), 16 frames of another retina (the
    shipped sample upside down: no match with the first), then frames 12-23 of the video.
    The images and the truth per input index."""
    upside_down = tmp_path / "upside_down.png"
    cv2.imwrite(str(upside_down), cv2.rotate(cv2.imread(str(SAMPLE_IMAGE)), cv2.ROTATE_180))
    params = SynthParams(n_frames=16, size=size, seed=5, nuisances=False)
    other_truth = load_ground_truth(write_synthetic_video(upside_down, tmp_path / "b", params))
    first = [cv2.imread(str(p)) for p in sorted(folder.glob("*.png"))]
    second = [cv2.imread(str(p)) for p in sorted((tmp_path / "b").glob("*.png"))]
    return first[:12] + second + first[12:], truth[:12] + other_truth + truth[12:]


def leaving_clip(tmp_path: Path, size: tuple[int, int]) -> Path:
    """A folder of 28 frames (with its `.gt.json`) whose camera leaves the mapped area and does
    not come back: frames 0-11 of a synthetic video of the sample, then 16 frames of another
    retina (`left_and_back` without the way back)."""
    params = SynthParams(n_frames=24, size=size, seed=3, nuisances=False)
    truth = load_ground_truth(write_synthetic_video(SAMPLE_IMAGE, tmp_path / "a", params))
    images, truth = left_and_back(tmp_path, tmp_path / "a", truth, size)
    clip = tmp_path / "clip"
    clip.mkdir()
    for index, image in enumerate(images[:28]):
        cv2.imwrite(str(clip / f"{index:04d}.png"), image)
    frames = [{"index": i, "H_frame_to_source": H.tolist()} for i, H in enumerate(truth[:28])]
    gt_path_for(clip).write_text(json.dumps({"frames": frames}))
    return clip
