"""Compositing: what a frame is corrected and weighted by before it goes on the canvas
(`mosaic.canvas`), and the live compositor of the streamed frames.

Frames are divided by the video's flat-field (`[compose] flatfield`), scaled by their exposure
gain (`exposure`: live, against the canvas under the frame; in the re-render, `mosaic.render`,
a global least-squares solution over all frames from a first pass over the video) and weighted
by their sharpness against the other frames at the same places and by glare
(`sharpness_weighting`; live, against the recent frames), and by the noise their correction
amplified (`PRECISION`). The weights are measured on a frame's analysis grid
(`photometry.FrameQuality`) and resized to the frame (`weights_from_small`).
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np

from mosaic.canvas import Canvas, CanvasPlanes
from mosaic.config import ComposeConfig
from mosaic.geometry import pixel_scale, scale_matrix
from mosaic.photometry import (
    DARK,
    SATURATED,
    FrameQuality,
    VideoPhotometry,
    analysis_factor,
    channel_max,
    frame_quality,
    inside_share,
    normalised_grid,
    robust_gain,
    shading_terms,
    shrink,
    small_size,
)

# feather / average / multiband: weight x min(1, relative sharpness / knee)^power
SHARPNESS_KNEE = 0.8  # frames at least this sharp (relative to the others there) count fully
SHARPNESS_POWER = 4.0  # ... blurrier ones fall off fast: half the knee weighs 1/16
PRECISION = True  # weights x (shading / gain)^2: the corrected frame's inverse noise variance


def weights_from_small(small: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A per-cell weight map of the analysis grid, resized to the frame's (h, w)."""
    h, w = shape
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def measure_quality(config: ComposeConfig, image: np.ndarray, mask: np.ndarray) -> FrameQuality:
    """A frame's quality maps on its analysis grid (`photometry.frame_quality`), as the
    compositing weighs them: the feather ramp of `feather_px`, sharpness where weighted."""
    factor = analysis_factor(image.shape)
    return frame_quality(image, mask, factor, config.feather_px, config.sharpness_weighting)


def precision_weights(
    photometry: VideoPhotometry,
    shape: tuple[int, ...],
    size: tuple[int, int],
    gain: float | None,
) -> np.ndarray:
    """How much the correction amplified a frame's noise, inverted: (shading / gain)^2 on its
    analysis grid of (w, h) = `size` (a vignetted corner, a dark frame brightened weigh less)."""
    shading = np.asarray(photometry.shading(shape, size), np.float32)
    return (shading / (1.0 if gain is None else gain)) ** 2 * np.ones(size[::-1], np.float32)


class _ShadingMosaic:
    """A low-resolution mosaic (the frames' analysis grids) of the frames' log intensity, each
    frame's gain taken out, and of the shading terms at which they saw each place: what each
    new frame is compared with for the flat-field estimate (`photometry.FlatFieldEstimator`)."""

    def __init__(self, config: ComposeConfig) -> None:
        self._planes = CanvasPlanes(config, 2)  # log I, 4 terms, 1 unused
        self._terms: tuple[tuple[int, ...], np.ndarray] | None = None

    def observe(
        self,
        photometry: VideoPhotometry,
        image: np.ndarray,
        H_frame_to_ref: np.ndarray,
        mask: np.ndarray,
    ) -> None:
        factor = analysis_factor(image.shape)
        size = small_size(image.shape, factor)
        small = shrink(image, size)
        lum = _mean(small.astype(np.float32))
        valid = inside_share(mask, size) > 0.999
        valid &= (lum > 2 * DARK) & (channel_max(small) < SATURATED)
        if self._terms is None or self._terms[0] != image.shape:
            self._terms = (image.shape, shading_terms(*normalised_grid(image.shape, size)))
        terms = self._terms[1]
        k = factor  # reference pixels per cell of the low-resolution mosaic
        K = pixel_scale(1 / k)
        M = (
            K
            @ np.asarray(H_frame_to_ref, np.float64)
            @ np.linalg.inv(scale_matrix(image.shape, size[::-1]))
        )
        log_lum = np.log(np.maximum(lum, DARK))
        offset = 0.0
        if self._planes.n_frames:
            planes, seen = self._planes.planes_in_frame(M, lum.shape)
            ok = valid & seen
            if ok.any():
                mosaic = np.concatenate(planes, axis=2)[ok]
                ratio = log_lum[ok] - mosaic[:, 0]
                n = terms.shape[-1]
                offset = photometry.observe_mosaic(
                    image.shape, ratio, terms[ok] - mosaic[:, 1 : 1 + n]
                )
        zeros = np.zeros((*lum.shape, 5 - terms.shape[-1]), np.float32)
        stack = np.concatenate([(log_lum - offset)[..., None], terms, zeros], axis=2)
        small_mask = valid.astype(np.uint8) * 255
        planes = [np.ascontiguousarray(stack[..., 3 * i : 3 * i + 3]) for i in range(2)]
        self._planes.add_planes(planes, M, small_mask)


class LiveCompositor:
    """Puts streamed frames on a growing (live) canvas and feeds the flat-field estimate.

    Each frame is compared with what the frames before it show under it: on a low-resolution
    mosaic of log intensities, for the video's flat-field estimate (`_ShadingMosaic`), and on
    the canvas, for its running exposure gain. With `correct` the frame is then flat-fielded,
    gain-compensated and weighted by its own quality before it is added (`best` and
    `multiband` feather here; the re-render, `render_segments`, does them); without, it is
    added as decoded (a preview the re-render replaces). Its sharpness factor is relative to
    the recent frames' (the re-render compares frames at the same places).
    """

    HISTORY = 15  # recent frames whose median sharpness is the reference
    # Every SHADING_EVERY-th frame feeds the flat-field estimate: consecutive frames see much
    # the same places at the same shading, and the observation costs ~5 ms a frame
    SHADING_EVERY = 2

    def __init__(
        self, config: ComposeConfig, photometry: VideoPhotometry, correct: bool = True
    ) -> None:
        self._config = config
        self.photometry = photometry
        self._correct = correct and (
            config.flatfield or config.exposure or config.sharpness_weighting
        )
        self._shading = _ShadingMosaic(config) if config.flatfield else None
        self._recent: deque[float] = deque(maxlen=self.HISTORY)
        self.frame_shape: tuple[int, int] | None = None  # (h, w) of the frames as decoded
        self._added = 0

    def add(
        self, canvas: Canvas, image: np.ndarray, H_frame_to_ref: np.ndarray, mask: np.ndarray
    ) -> float | None:
        """Observe, correct, weight and add a frame to `canvas` (raises `CanvasLimitError` like
        `Canvas.add`, before anything is observed); returns the gain applied (None: none)."""
        cfg = self._config
        if not canvas.fits(H_frame_to_ref, image.shape[:2]):
            canvas.add(image, H_frame_to_ref, mask)  # raises, naming the cap
        self.frame_shape = (int(image.shape[0]), int(image.shape[1]))
        if self._shading is not None and self._added % self.SHADING_EVERY == 0:
            self._shading.observe(self.photometry, image, H_frame_to_ref, mask)
        self._added += 1
        if not self._correct:
            canvas.add(image, H_frame_to_ref, mask)
            return None
        gain = None
        if cfg.exposure and canvas.n_frames:
            factor = analysis_factor(image.shape)
            mosaic, valid = canvas.content_in_frame(
                H_frame_to_ref, image.shape, 1.0 / factor, channel=None
            )
            size = mosaic.shape[1::-1]
            valid &= inside_share(mask, size) > 0.999
            gain = robust_gain(self.photometry.correct_small(image, size), mosaic, valid)
        corrected = self.photometry.correct(image, gain)
        weights = None
        if cfg.sharpness_weighting:
            quality = measure_quality(cfg, image, mask)
            sharp = quality.sharpness()
            median = float(np.median(sharp[quality.ramp > 0])) if quality.ramp.any() else 0.0
            reference = float(np.median(self._recent)) if self._recent else median
            self._recent.append(median)
            rho = median / reference if reference > 0 else 1.0
            small = quality.glare * np.float32(min(1.0, rho / SHARPNESS_KNEE) ** SHARPNESS_POWER)
            if PRECISION:
                cells = small.shape[::-1]
                small = small * precision_weights(self.photometry, image.shape, cells, gain)
            weights = weights_from_small(small, image.shape[:2])
        canvas.add(corrected, H_frame_to_ref, mask, weights)
        return gain


def _mean(image: np.ndarray) -> np.ndarray:
    """Mean over the channels (a grey image as it is)."""
    return image if image.ndim == 2 else image.mean(axis=2)
