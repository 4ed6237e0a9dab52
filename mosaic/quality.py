"""Registration quality without ground truth: does a placed frame agree with the mosaic?

A frame registered to the right place shows the same vessels as the mosaic under it; a frame
placed a few pixels off shows them beside each other. `agreement` measures this as the local
normalised cross-correlation (NCC) of the two images' band-passed signal (difference of
Gaussians: what gain, gamma, tint, vignetting and the dark aperture change is removed, noise is
smoothed), in windows over the pixels both cover, summarised by the texture-weighted median
over the windows that have enough of both texture and overlap. 1 is perfect agreement, about 0
unrelated content. Everything runs on a copy of the frame at about `ANALYSIS_SIDE_PX` on its
longer side (a few ms per frame).

`frame_vs_canvas` scores a frame against a `Canvas` before it is added; `score_vs_error`
relates the scores of a report to the true error of its poses (synthetic videos).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from typing import Any

import cv2
import numpy as np

from mosaic.canvas import Canvas
from mosaic.config import ComposeConfig, PreprocessConfig
from mosaic.geometry import apply_homography, corner_error, relative_homographies
from mosaic.preprocess import prepare, to_working_size

log = logging.getLogger(__name__)

ANALYSIS_SIDE_PX = 330  # frames are scored at this longer side (smaller ones at their own)
WINDOW_PX = 16  # NCC window side at the analysis size (32 px of a 660 px wide frame)
SIGMA_FINE_PX = 1.0  # DoG: smooths noise ... (analysis pixels)
SIGMA_COARSE_PX = 4.0  # ... and removes illumination; vessels a few px wide stay
MIN_WINDOW_COVERAGE = 0.6  # fraction of a window both images must cover for it to count
MIN_TEXTURE = 0.6  # band-passed std (grey levels) under which a window is textureless ...
TEXTURE_FRACTION = 0.25  # ... or under this fraction of the 90th percentile over windows
MIN_WINDOWS = 4  # fewer judged windows than this: no score (NaN)


def analysis_scale(shape: tuple[int, ...]) -> float:
    """Factor from a frame of `shape` (h, w, ...) to the size it is scored at (<= 1)."""
    return min(1.0, ANALYSIS_SIDE_PX / max(int(shape[0]), int(shape[1]), 1))


def band_pass(images: list[np.ndarray], valid: np.ndarray) -> list[np.ndarray]:
    """Difference of Gaussians of each image over the `valid` pixels only (normalised
    convolution: pixels outside do not pull the blurs), 0 outside; float32."""
    m = valid.astype(np.float32)

    def blur(x: np.ndarray, sigma: float) -> np.ndarray:
        return cv2.GaussianBlur(x, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)

    sigmas = (SIGMA_FINE_PX, SIGMA_COARSE_PX)
    inv_m = [1.0 / np.maximum(blur(m, sigma), 1e-3) for sigma in sigmas]
    out = []
    for image in images:
        x = image.astype(np.float32) * m
        fine, coarse = (blur(x, sigma) * inv for sigma, inv in zip(sigmas, inv_m, strict=True))
        out.append(np.subtract(fine, coarse, out=np.zeros_like(x), where=valid))
    return out


def _window_sums(x: np.ndarray, window: int) -> np.ndarray:
    """Sums over non-overlapping window x window tiles (the ragged right/bottom edge dropped)."""
    ny, nx = x.shape[0] // window, x.shape[1] // window
    tiles = x[: ny * window, : nx * window].reshape(ny, window, nx, window)
    return tiles.sum(axis=(1, 3), dtype=np.float64)


def window_ncc(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, window: int = WINDOW_PX
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window: (NCC of a and b over the valid pixels, texture = geometric mean of their
    standard deviations, fraction of the window valid); flat arrays, one entry per window."""
    m = valid.astype(np.float32)
    a = a * m
    b = b * m
    n = _window_sums(m, window)
    safe_n = np.maximum(n, 1.0)
    mean_a, mean_b = _window_sums(a, window) / safe_n, _window_sums(b, window) / safe_n
    var_a = np.maximum(_window_sums(a * a, window) / safe_n - mean_a**2, 0.0)
    var_b = np.maximum(_window_sums(b * b, window) / safe_n - mean_b**2, 0.0)
    cov = _window_sums(a * b, window) / safe_n - mean_a * mean_b
    std_a, std_b = np.sqrt(var_a), np.sqrt(var_b)
    ncc = cov / np.maximum(std_a * std_b, 1e-12)
    texture = np.sqrt(std_a * std_b)
    return ncc.ravel(), texture.ravel(), (n / (window * window)).ravel()


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def agreement(frame: np.ndarray, mosaic: np.ndarray, valid: np.ndarray) -> float:
    """Photometric agreement in [-1, 1] of two single-channel images of the same pixels (frame
    and the mosaic resampled into it) over `valid` (bool: both cover the pixel); NaN when too
    few windows have both overlap and texture to judge."""
    if frame.shape != mosaic.shape or frame.shape != valid.shape:
        raise ValueError(
            f"frame {frame.shape}, mosaic {mosaic.shape} and valid {valid.shape} must match"
        )
    a, b = band_pass([frame, mosaic], valid)
    ncc, texture, covered = window_ncc(a, b, valid)
    judged = covered >= MIN_WINDOW_COVERAGE
    if judged.sum() < MIN_WINDOWS:
        return math.nan
    floor = max(MIN_TEXTURE, TEXTURE_FRACTION * float(np.percentile(texture[judged], 90)))
    judged &= texture >= floor
    if judged.sum() < MIN_WINDOWS:
        return math.nan
    return _weighted_median(np.clip(ncc[judged], -1.0, 1.0), texture[judged])


def frame_vs_canvas(
    canvas: Canvas,
    frame: np.ndarray,
    H_frame_to_ref: np.ndarray,
    mask: np.ndarray | None = None,
) -> float:
    """`agreement` of a frame (grey or BGR uint8; BGR is scored on its green channel) placed
    by `H_frame_to_ref` with what `canvas` holds under it (its green channel), over the
    frame's `mask` (nonzero = valid; None: all); NaN without enough overlap."""
    gray = frame if frame.ndim == 2 else frame[..., 1]
    s = analysis_scale(gray.shape)
    mosaic, mosaic_valid = canvas.content_in_frame(H_frame_to_ref, gray.shape, s)
    size = mosaic.shape[::-1]  # (w, h) of the analysis copy
    if size != gray.shape[::-1]:
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    frame_valid = np.ones(gray.shape, bool)
    if mask is not None:
        if mask.shape != frame.shape[:2]:
            raise ValueError(f"mask shape {mask.shape} does not match frame shape {frame.shape}")
        inside = (mask != 0).astype(np.uint8) * 255
        if size != inside.shape[::-1]:
            inside = cv2.resize(inside, size, interpolation=cv2.INTER_AREA)
        frame_valid = inside == 255  # analysis pixels wholly inside the mask
    return agreement(gray, mosaic, frame_valid & mosaic_valid)


def _first_segment(report: dict[str, Any]) -> int:
    """The segment of the report's first placed frame (the one its error is measured in)."""
    for entry in report["frames"]:
        if entry.get("H_to_canvas") is not None:
            return int(entry["segment"])
    raise ValueError("the report has no registered frame")


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman rank correlation (average ranks for ties) of the finite pairs; NaN under 3 or
    when either side is constant."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    finite = np.isfinite(x) & np.isfinite(y)
    x, y = x[finite], y[finite]
    if len(x) < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return math.nan
    from scipy.stats import spearmanr

    return float(spearmanr(x, y).statistic)


def _aperture_points(size: tuple[int, int], step_px: float = 10.0) -> np.ndarray:
    """(n, 2) grid of frame points inside the ellipse inscribed in a (w, h) frame (shrunk to
    0.9: where fundus frames show retina)."""
    w, h = size
    xs, ys = np.meshgrid(np.arange(0.0, w, step_px), np.arange(0.0, h, step_px))
    cx, cy = (w - 1) / 2, (h - 1) / 2
    inside = ((xs - cx) / (0.9 * w / 2)) ** 2 + ((ys - cy) / (0.9 * h / 2)) ** 2 <= 1.0
    return np.stack([xs[inside], ys[inside]], axis=1)


def _misalignment(
    i: int, est: list[np.ndarray], true: list[np.ndarray], points: np.ndarray, size: tuple[int, int]
) -> float:
    """Median true distance (px of the reference frame) between what pixels of frame i show and
    what the frames before it show at the same place of the mosaic, over their overlap (the
    median: what most of the mosaic under the frame shows)."""
    w, h = size
    cx, cy = (w - 1) / 2, (h - 1) / 2
    in_ref = apply_homography(est[i], points)  # where the frame's points are drawn
    truth_i = apply_homography(true[i], points)  # what they show
    distances = []
    for j in range(i):
        q = apply_homography(np.linalg.inv(est[j]), in_ref)  # in frame j
        inside = ((q[:, 0] - cx) / (0.9 * w / 2)) ** 2 + ((q[:, 1] - cy) / (0.9 * h / 2)) ** 2
        inside = inside <= 1.0
        if inside.any():
            mapped = apply_homography(true[j], q[inside])
            distances.append(np.linalg.norm(truth_i[inside] - mapped, axis=1))
    return float(np.median(np.concatenate(distances))) if distances else math.nan


def _catch(scores: np.ndarray, errors: np.ndarray, threshold: float, bad_px: float) -> dict:
    """How many frames with error > bad_px the flag catches, how many others it flags."""
    flagged, bad = scores < threshold, errors > bad_px
    good = ~bad & ~np.isnan(errors)
    return {
        "bad_px": bad_px,
        "n_bad": int(bad.sum()),
        "caught": int((bad & flagged).sum()),
        "catch_rate": float((bad & flagged).sum() / bad.sum()) if bad.any() else math.nan,
        "n_good": int(good.sum()),
        "false_flags": int((good & flagged).sum()),
        "false_flag_rate": float((good & flagged).sum() / good.sum()) if good.any() else math.nan,
    }


def score_vs_error(
    report: dict[str, Any],
    gt: list[np.ndarray],
    frame_size: tuple[int, int],
    threshold: float | None = None,
    bad_error_px: float = 10.0,
    bad_misalignment_px: float = 5.0,
) -> dict[str, Any]:
    """How a report's per-frame `quality` relates to the true error of its poses.

    `gt`: H_frame_to_source per frame (`truth.load_ground_truth`); `frame_size` (w, h). Frames
    of the report's first segment with a score are compared, against two errors:
    - `corner`: the corner error of inv(H_0_to_canvas) @ H_i_to_canvas against the truth, 0
      being the segment's first frame. It includes what the score cannot see: the drift of the
      whole mosaic away from frame 0, and the frame corners, which lie outside the retina and
      are extrapolated by the homography;
    - `misalignment`: the median true distance between what the frame's retina pixels show
      and what the frames placed before it show at the same mosaic position, over their
      overlap (what the score measures: doubled vessels).
    `threshold` (default: the report's `[compose] quality_threshold`) flags frames; a frame is
    bad when an error exceeds `bad_error_px` (corner) or `bad_misalignment_px`. Returns the
    Spearman correlations of score and each error (negative: lower score, larger error), per
    error the bad frames caught and the good frames flagged, and per frame (index, score,
    corner error, misalignment).
    """
    if threshold is None:
        threshold = float(report["config"]["compose"]["quality_threshold"])
    segment = _first_segment(report)
    frames = [f for f in report["frames"] if f.get("H_to_canvas") and f["segment"] == segment]
    H0_inv = np.linalg.inv(np.asarray(frames[0]["H_to_canvas"], np.float64))
    truth = relative_homographies(gt, ref=frames[0]["index"])
    est = [H0_inv @ np.asarray(f["H_to_canvas"], np.float64) for f in frames]
    est = [H / H[2, 2] for H in est]
    true = [truth[f["index"]] for f in frames]
    points = _aperture_points(frame_size)
    rows = []
    for k, entry in enumerate(frames):
        if k == 0 or entry.get("quality") is None:
            continue
        corner = corner_error(est[k], true[k], frame_size)
        rows.append(
            (
                int(entry["index"]),
                float(entry["quality"]),
                corner,
                _misalignment(k, est, true, points, frame_size),
            )
        )
    scores, corners, misaligned = (np.array([r[c] for r in rows], float) for c in (1, 2, 3))
    return {
        "n_frames": len(rows),
        "threshold": threshold,
        "spearman": spearman(scores, corners),
        "spearman_misalignment": spearman(scores, misaligned),
        "corner": _catch(scores, corners, threshold, bad_error_px),
        "misalignment": _catch(scores, misaligned, threshold, bad_misalignment_px),
        "frames": rows,
    }


def shift_response(
    frames: Iterable[tuple[int, np.ndarray | None]],
    report: dict[str, Any],
    shifts_px: Sequence[float] = (0.0, 5.0, 10.0, 20.0),
    seed: int = 0,
) -> dict[float, np.ndarray]:
    """Scores of a report's frames moved off their poses: for each shift d, per frame of the
    first segment but its first, the score with its pose translated by d px (in mosaic
    pixels, a random direction per frame) against the mosaic of the frames before it at their
    reported poses, rebuilt from `frames` ((index, BGR image) in order, e.g. a re-read video).
    Shows how the score falls with a known error, on any video (no ground truth needed)."""
    entries = {
        int(f["index"]): np.asarray(f["H_to_canvas"], np.float64)
        for f in report["frames"]
        if f.get("H_to_canvas") is not None and f["segment"] == _first_segment(report)
    }
    config = report.get("config", {})
    canvas = Canvas(ComposeConfig(**config.get("compose", {})))
    preprocess = PreprocessConfig(**config.get("preprocess", {}))
    rng = np.random.default_rng(seed)
    scores: dict[float, list[float]] = {float(d): [] for d in shifts_px}
    for index, image in frames:
        if index not in entries or image is None:
            continue
        H = entries[index]
        work, S = to_working_size(image, preprocess.max_side_px)
        mask = prepare(work, preprocess).mask
        if S is not None:
            mask = cv2.resize(mask, image.shape[1::-1], interpolation=cv2.INTER_NEAREST)
        if canvas.n_frames:
            angle = rng.uniform(0.0, 2.0 * np.pi)
            for d in scores:
                T = np.array([[1.0, 0, d * np.cos(angle)], [0, 1.0, d * np.sin(angle)], [0, 0, 1]])
                scores[d].append(frame_vs_canvas(canvas, image, T @ H, mask))
        canvas.add(image, H, mask)
    return {d: np.array(v) for d, v in scores.items()}
