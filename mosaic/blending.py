"""Burt-Adelson multiband blending over a canvas of known size, fed one frame at a time.

Each frame (already warped into its box of the canvas, with a per-pixel weight that is 0
where it has no valid pixel) is split into a Laplacian pyramid; every level is accumulated
with the Gaussian pyramid of the frame's weights, and the blended mosaic is the collapse of
the per-level weighted means (Burt & Adelson, "A multiresolution spline with application to
image mosaics", 1983). Fine detail then comes from the frames with the largest weight at that
place (sharp seams, no ghosting), coarse shading from a wide neighbourhood (no visible steps).

Memory: the per-level accumulators hold (channels + 1) floats per canvas pixel over all
levels (4/3 of the canvas); frames are never kept, and the collapse goes strip by strip
(`render_rows`), never through whole float images. The pixels outside a frame's valid region
are filled from the valid ones (push-pull) before its pyramid is built, so a dark field-of-view
border never leaks into the coarse levels.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

log = logging.getLogger(__name__)

_EPS = 1e-30  # accumulated weight under which a level's pixel counts as empty


def _spread(m: np.ndarray, channels: int) -> np.ndarray:
    """A single-channel map as `channels` channels (OpenCV's element-wise kernels want equal
    channels, and run several times faster than numpy's broadcasting on these sizes)."""
    return m if channels == 1 else cv2.merge([m] * channels)


def fill_invalid(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`image` (float32 HxW[xC]) with the pixels where `valid` (bool HxW) is False filled
    smoothly from the valid ones (push-pull over a Gaussian pyramid); valid pixels unchanged.

    At the finest level the mask is 0 / 1: the push is a masked copy and the pull takes each
    pixel from itself or from the coarser estimate, one masked copy again."""
    if not valid.any() or valid.all():
        return image
    if image.ndim == 3 and image.shape[2] == 1:  # OpenCV drops a single channel's axis
        return fill_invalid(image[..., 0], valid)[..., None]
    channels = 1 if image.ndim == 2 else image.shape[2]
    inside = valid.astype(np.uint8)
    first = np.zeros_like(image)
    cv2.copyTo(image, inside, dst=first)  # = image x mask
    levels = [(first, inside.astype(np.float32))]
    # push: pre-multiplied means, down to where every pixel has some valid support
    while levels[-1][1].min() <= 1e-6 and min(levels[-1][1].shape) > 1:
        a, m = levels[-1]
        levels.append((cv2.pyrDown(a), cv2.pyrDown(m)))
    if len(levels) == 1:  # a side of 1 px: nothing coarser to pull from
        return first
    a, m = levels[-1]
    estimate = cv2.divide(a, _spread(np.maximum(m, 1e-6), channels))
    # pull: each level's valid share m from its own mean, the rest from the coarser estimate
    for a, m in reversed(levels[1:-1]):
        up = cv2.pyrUp(estimate, dstsize=(a.shape[1], a.shape[0]))
        rest = _spread(1.0 - np.clip(m, 0.0, 1.0), channels)
        estimate = cv2.accumulateProduct(up.reshape(a.shape), rest, a)
    up = cv2.pyrUp(estimate, dstsize=(image.shape[1], image.shape[0])).reshape(image.shape)
    cv2.copyTo(image, inside, dst=up)
    return up


class LaplacianBlender:
    """Per-level accumulators of a multiband blend over a (height, width) canvas."""

    def __init__(self, height: int, width: int, channels: int, levels: int = 5) -> None:
        if levels < 1:
            raise ValueError(f"levels must be >= 1, got {levels}")
        self.levels = levels
        self.channels = channels
        self.height, self.width = height, width
        step = 1 << levels
        # padded to whole multiples of 2^levels: every aligned box maps exactly onto each level
        ph, pw = -(-height // step) * step, -(-width // step) * step
        self._num = [np.zeros((ph >> k, pw >> k, channels), np.float32) for k in range(levels + 1)]
        self._den = [np.zeros((ph >> k, pw >> k), np.float32) for k in range(levels + 1)]

    @property
    def nbytes(self) -> int:
        """Memory held by the accumulators."""
        return sum(a.nbytes for a in self._num) + sum(a.nbytes for a in self._den)

    @staticmethod
    def bytes_for(height: int, width: int, channels: int, levels: int = 5) -> int:
        """`nbytes` of a blender of these arguments, without making one."""
        step = 1 << levels
        ph, pw = -(-height // step) * step, -(-width // step) * step
        return sum(4 * (channels + 1) * (ph >> k) * (pw >> k) for k in range(levels + 1))

    def add(
        self,
        image: np.ndarray,
        weight: np.ndarray,
        x0: int,
        y0: int,
        trusted: float = 1e-3,
    ) -> None:
        """Blend in a frame warped into the canvas box with top-left (x0, y0): `image` float32
        (h, w[, C]), `weight` float32 (h, w), 0 (or negative) where the frame is not valid.

        Pixels weighing under `trusted` x the frame's largest weight (glare) keep their tiny
        weight but not their values: those are filled from the rest of the frame before its
        pyramid is built, so that the coarse levels, whose weights spread, carry no halo."""
        boxed = self.boxed(image, weight, x0, y0)
        if boxed is not None:
            self.add_boxed(boxed, trusted)

    def boxed(
        self, image: np.ndarray, weight: np.ndarray, x0: int, y0: int
    ) -> tuple[np.ndarray, np.ndarray, int, int] | None:
        """The first half of `add`: the frame and its weight (0 where invalid) copied into an
        aligned box of the canvas, (image, weight, box x0, box y0), None when nothing of it is
        inside. A copy: the caller may reuse its buffers while `add_boxed` runs elsewhere."""
        h, w = weight.shape
        image = image.reshape(h, w, self.channels)
        step = 1 << self.levels
        ph, pw = self._den[0].shape
        # aligned box around the frame with a margin of 2 coarsest pixels: the coarse weights
        # spread into it, and the frame's own pyramid is then exact where the canvas collapses it
        margin = 2 * step
        bx0 = max((x0 - margin) // step * step, 0)
        by0 = max((y0 - margin) // step * step, 0)
        bx1 = min(-(-(x0 + w + margin) // step) * step, pw)
        by1 = min(-(-(y0 + h + margin) // step) * step, ph)
        # the part of the frame's box inside the canvas
        sx0, sy0 = max(bx0 - x0, 0), max(by0 - y0, 0)
        sx1, sy1 = min(bx1 - x0, w), min(by1 - y0, h)
        if bx1 <= bx0 or by1 <= by0 or sx1 <= sx0 or sy1 <= sy0:
            return None
        box_img = np.zeros((by1 - by0, bx1 - bx0, self.channels), np.float32)
        box_w = np.zeros((by1 - by0, bx1 - bx0), np.float32)
        dst = (slice(y0 + sy0 - by0, y0 + sy1 - by0), slice(x0 + sx0 - bx0, x0 + sx1 - bx0))
        box_img[dst] = image[sy0:sy1, sx0:sx1]
        box_w[dst] = np.maximum(weight[sy0:sy1, sx0:sx1], 0.0)
        return box_img, box_w, bx0, by0

    def add_boxed(
        self, boxed: tuple[np.ndarray, np.ndarray, int, int], trusted: float = 1e-3
    ) -> None:
        """The second half of `add`: the boxed frame's pyramid into the accumulators."""
        box_img, box_w, bx0, by0 = boxed
        by1, bx1 = by0 + box_w.shape[0], bx0 + box_w.shape[1]
        valid = box_w > trusted * float(box_w.max())
        if not valid.any():
            return
        gauss = fill_invalid(box_img if self.channels > 1 else box_img[..., 0], valid)
        weights = box_w
        for k in range(self.levels + 1):
            rows = slice(by0 >> k, by1 >> k)
            cols = slice(bx0 >> k, bx1 >> k)
            num = self._num[k][rows, cols]
            if k < self.levels:
                down = cv2.pyrDown(gauss)
                up = cv2.pyrUp(down, dstsize=(gauss.shape[1], gauss.shape[0]))
                band = cv2.subtract(gauss, up, dst=up)
            else:
                band = gauss
            # OpenCV's accumulators: one pass each, into the views (no temporaries)
            cv2.accumulateProduct(band, _spread(weights, self.channels), num.reshape(band.shape))
            cv2.accumulate(weights, self._den[k][rows, cols])
            if k < self.levels:
                gauss = down
                weights = cv2.pyrDown(weights)

    def render(self) -> np.ndarray:
        """The blended canvas, float32 (height, width, C); 0 where no frame had weight."""
        return self.render_rows(0, self.height)

    def render_rows(self, y0: int, y1: int) -> np.ndarray:
        """Rows [y0, y1) of `render`, float32 (y1 - y0, width, C), identical to its rows, in
        memory for those rows only (a few rows more per level): a large canvas is collapsed
        strip by strip, never as whole float images."""
        y0, y1 = max(y0, 0), min(y1, self.height)
        if y1 <= y0:
            return np.zeros((0, self.width, self.channels), np.float32)
        return self._collapse(0, y0, y1)[:, : self.width]

    def _collapse(self, k: int, a: int, b: int) -> np.ndarray:
        """Rows [a, b) of level k of the collapsed pyramid (the blended image at 1 / 2^k).

        Row 2i of `cv2.pyrUp` reads coarse rows i - 1 .. i + 1, row 2i + 1 rows i .. i + 1:
        the coarse rows [a // 2 - 1, (b + 1) // 2 + 1) give rows [a, b) exactly, the rows at
        the strip's own edges (where pyrUp reflects) falling outside them; at the canvas' edges
        the strip's border is the canvas' border, reflected alike."""
        den = self._den[k][a:b, :, None]
        num = self._num[k][a:b]
        level = np.divide(num, den, out=np.zeros_like(num), where=den > _EPS)
        if k == self.levels:
            return level
        ca, cb = max(a // 2 - 1, 0), min((b + 1) // 2 + 1, self._den[k + 1].shape[0])
        coarse = self._collapse(k + 1, ca, cb)
        w = self._den[k].shape[1]
        up = cv2.pyrUp(coarse, dstsize=(w, 2 * (cb - ca))).reshape(-1, w, self.channels)
        level += up[a - 2 * ca : b - 2 * ca]
        return level


# -- the noise blending leaves ---------------------------------------------------------------
DENOISE_SIGMA_PX = 1.0  # the finest band: the mosaic minus its Gaussian blur of this sigma
DENOISE_WINDOW_PX = 7  # the band's local energy is its mean square over this window
DENOISE_QUIET_PERCENTILE = 10.0  # the noise level: the energy of the mosaic's quietest places ...
DENOISE_QUIET_SHARE = 0.735  # ... which for noise alone is this share of its variance (measured)
_DENOISE_HALO = 8  # rows a strip reads beyond its own: 3 sigma of the blur + half the window
DENOISE_KEEP_BYTES = 64 * 2**20  # the bands kept between the two passes up to this


def _band_energy(strip: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The finest band of a strip (float32: the strip minus its Gaussian blur, both over the
    content only, so the empty canvas is not taken for detail at the content's edge) and its
    local energy (mean square over `DENOISE_WINDOW_PX`, over the content only)."""
    m = inside.astype(np.float32)

    def per_channel(a: np.ndarray) -> np.ndarray:  # an HxW map against the strip's channels
        return a[..., None] if strip.ndim == 3 else a

    x = strip.astype(np.float32) * per_channel(m)
    low = cv2.GaussianBlur(x, (0, 0), DENOISE_SIGMA_PX)
    den = np.maximum(cv2.GaussianBlur(m, (0, 0), DENOISE_SIGMA_PX), 1e-6)
    band = (x - low / per_channel(den)) * per_channel(m)
    window = (DENOISE_WINDOW_PX, DENOISE_WINDOW_PX)
    share = np.maximum(cv2.boxFilter(m, -1, window), 1e-6)
    return band, cv2.boxFilter(band * band, -1, window) / per_channel(share)


def shrink_noise(
    image: np.ndarray,
    content: np.ndarray,
    rows: int = 256,
    threads: int = 1,
    keep_bytes: int = DENOISE_KEEP_BYTES,
) -> np.ndarray:
    """The mosaic (uint8 HxW[xC]) with the noise its frames left shrunk: its finest band
    (`DENOISE_SIGMA_PX`) multiplied by the local Wiener gain max(0, 1 - noise² / energy).
    Where vessels and edges make the band's local energy well above the noise they stay as they
    are; where the band is mostly noise (a place few frames averaged, a magnified view whose
    pixels are finer than its optics) it is smoothed. The noise level (per channel) is read
    from the quietest places of the `content` (bool HxW): the 10th percentile of the energy, so
    that a texture covering the whole mosaic (an adaptive-optics or SLO view of photoreceptors)
    is not taken for noise, as a median over all places would. In strips of `rows` rows,
    `threads` at a time; the strips' bands are kept from the noise estimate for the
    smoothing when they take at most `keep_bytes` (else made again): no float image of a
    large mosaic."""
    h = image.shape[0]
    if not content.any():
        return image
    starts = range(0, h, rows)
    kept = 8 * image.size <= keep_bytes  # the band and its energy, float32

    def strip(r0: int) -> tuple[np.ndarray, np.ndarray]:
        r1 = min(r0 + rows, h)
        a, b = max(r0 - _DENOISE_HALO, 0), min(r1 + _DENOISE_HALO, h)
        band, energy = _band_energy(image[a:b], content[a:b])
        return band[r0 - a : r1 - a], energy[r0 - a : r1 - a]

    def sampled(r0: int) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        band, energy = strip(r0)
        sample = energy[::4][content[r0 : r0 + rows : 4]]  # every 4th row
        return sample, (band, energy) if kept else None

    out = image.copy()
    with ThreadPoolExecutor(threads, thread_name_prefix="denoise") as pool:
        samples, bands = zip(*pool.map(sampled, starts), strict=True)
        quiet = np.percentile(np.concatenate(samples), DENOISE_QUIET_PERCENTILE, axis=0)
        noise2 = quiet / DENOISE_QUIET_SHARE

        def smooth(r0: int, made: tuple[np.ndarray, np.ndarray] | None) -> None:
            band, energy = made if made is not None else strip(r0)
            r1 = r0 + len(band)
            gain = np.clip(1.0 - noise2 / np.maximum(energy, 1e-6), 0.0, 1.0)
            smoothed = np.rint(image[r0:r1].astype(np.float32) - band * (1.0 - gain))
            inside = content[r0:r1][..., None] if image.ndim == 3 else content[r0:r1]
            np.copyto(out[r0:r1], np.clip(smoothed, 0, 255).astype(np.uint8), where=inside)

        list(pool.map(smooth, starts, bands))
    return out
