"""Photometry of a video's frames, estimated from the frames themselves: side bands that carry
no retina, the vignetting (flat-field) profile, per-frame exposure gains and a per-pixel
quality (local sharpness, glare, distance to the border) that decides which frame shows a
place of the mosaic.

Everything here is streamed: the estimators keep running sums (column / row profiles, the
flat-field's normal equations, one previous frame) or a few numbers per frame (the overlap
cells of the exposure solve), never the frames.

- `SideBandDetector`: frame-fixed strips along the frame's sides (the adaptive-optics clip's
  striped bands, letterbox bars) show as a step, at the same column (row) in every part of the
  frame, in the time-averaged column (row) profiles of intensity, vertical and horizontal
  gradient energy and frame-to-frame change; moving retina averages to smooth profiles.
- `FlatFieldEstimator`: each frame against the mosaic of earlier frames under it, in log
  space: the retina cancels and the shading's coefficients (a low-order surface in frame
  coordinates, `shading_terms`) are a linear least-squares solution, accumulated frame by
  frame (see the class).
- `GainObservations.solve`: one gain per frame (all channels) from the mean values of coarse
  mosaic cells that several frames cover: least squares in log space, log(value) =
  log(exposure) + log(radiance), with a weak prior exposure = 1 and re-weighting against
  glare and misregistration; `robust_gain` is the live canvas's running estimate.
- `frame_quality`: contrast-normalised Laplacian energy x glare factor x border ramp, at low
  resolution; a frame's weight is its quality relative to the best frame at the same place.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

log = logging.getLogger(__name__)

SATURATED = 250  # grey level from which a pixel counts as saturated (glare)
DARK = 3.0  # mean level under which a pixel says nothing about gain or shading


def shrink(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`image` resized down to (w, h) = `size`: Gaussian halvings (`cv2.pyrDown`, fast) while
    it is at least twice as large, then an area average to the exact size."""
    while image.shape[1] >= 2 * size[0] and image.shape[0] >= 2 * size[1]:
        image = cv2.pyrDown(image)
    if (image.shape[1], image.shape[0]) == size:
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def inside_share(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """float32 share (0-1) of each cell of a (w, h) = `size` grid inside `mask` (nonzero)."""
    valid = (mask > 0).astype(np.uint8) * 255
    return shrink(valid, size).astype(np.float32) / 255.0


def channel_max(image: np.ndarray) -> np.ndarray:
    """Per-pixel maximum over the channels of a BGR (or grey) uint8 image."""
    if image.ndim == 2:
        return image
    b, g, r = cv2.split(image)
    return cv2.max(cv2.max(b, g), r)


# ------------------------------------------------------------------------------ side bands


@dataclass(frozen=True)
class SideBands:
    """Widths (px) of the frame-fixed bands without retina along each side of the frame."""

    left: int = 0
    right: int = 0
    top: int = 0
    bottom: int = 0

    def any(self) -> bool:
        return bool(self.left or self.right or self.top or self.bottom)

    def keep(self, shape: tuple[int, int]) -> np.ndarray:
        """bool (h, w): True outside the bands."""
        h, w = shape
        keep = np.ones((h, w), bool)
        keep[:, : self.left] = False
        keep[:, w - self.right :] = False
        keep[: self.top, :] = False
        keep[h - self.bottom :, :] = False
        return keep


class SideBandDetector:
    """Finds the side bands of a video from time-averaged column and row profiles.

    Per frame: the green channel's intensity, |vertical gradient|, |horizontal gradient| and
    |change since the previous frame|, summed over the valid pixels of each column (row), in
    `PARTS` separate stretches of rows (columns). A band is the strip from a side up to the
    column where these profiles step by more than `MIN_STEP` (relative) in every stretch:
    a full-length, frame-fixed edge, which moving retina does not leave in time averages.
    """

    PARTS = 4  # stretches of the frame a band must run through
    MIN_FRAMES = 8  # frames before any band is reported
    MAX_FRACTION = 0.2  # widest band, as a share of the frame side
    WINDOW_PX = 4  # columns (rows) averaged on each side of a candidate edge
    MIN_STEP = 0.3  # relative step (|a - b| / mean(a, b)) of the strongest feature
    MARGIN_PX = 2  # taken off beyond a detected band

    def __init__(self) -> None:
        self._shape: tuple[int, int] | None = None
        self._n = 0
        self._prev: np.ndarray | None = None
        self._prev_valid: np.ndarray | None = None
        self._cols: np.ndarray | None = None  # (features + count, PARTS, w)
        self._rows: np.ndarray | None = None  # (features + count, PARTS, h)

    @property
    def n_frames(self) -> int:
        return self._n

    @property
    def shape(self) -> tuple[int, int] | None:
        """(h, w) of the frames the bands were measured on (None before the first)."""
        return self._shape

    def add(self, image: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Take one frame (BGR or grey uint8) and its valid mask (nonzero = field of view)."""
        g = image if image.ndim == 2 else cv2.extractChannel(image, 1)
        h, w = g.shape
        m = np.full((h, w), 255, np.uint8) if mask is None else (mask > 0).astype(np.uint8) * 255
        if self._shape != (h, w):
            self._shape, self._n, self._prev = (h, w), 0, None
            self._cols = np.zeros((5, self.PARTS, w))
            self._rows = np.zeros((5, self.PARTS, h))
        assert self._cols is not None and self._rows is not None
        # uint8 features, 0 where not valid (differences: where both pixels are)
        dy = np.zeros((h, w), np.uint8)
        cv2.bitwise_and(cv2.absdiff(g[1:], g[:-1]), cv2.bitwise_and(m[1:], m[:-1]), dst=dy[1:])
        dx = np.zeros((h, w), np.uint8)
        both_x = cv2.bitwise_and(m[:, 1:], m[:, :-1])
        dx[:, 1:] = cv2.bitwise_and(cv2.absdiff(g[:, 1:], g[:, :-1]), both_x)
        dt = np.zeros((h, w), np.uint8)
        if self._prev is not None and self._prev_valid is not None:
            cv2.bitwise_and(
                cv2.absdiff(g, self._prev), cv2.bitwise_and(m, self._prev_valid), dst=dt
            )
        features = (cv2.bitwise_and(g, m), dy, dx, dt, m // 255)
        rows = np.linspace(0, h, self.PARTS + 1).astype(int)
        cols = np.linspace(0, w, self.PARTS + 1).astype(int)
        for k, f in enumerate(features):
            for p in range(self.PARTS):
                part = f[rows[p] : rows[p + 1]]
                self._cols[k, p] += cv2.reduce(part, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S)[0]
                part = f[:, cols[p] : cols[p + 1]]
                self._rows[k, p] += cv2.reduce(part, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S)[:, 0]
        self._prev, self._prev_valid = np.ascontiguousarray(g), m
        self._n += 1

    def estimate(self) -> SideBands:
        """The bands found so far (none before `MIN_FRAMES` frames)."""
        if self._n < self.MIN_FRAMES or self._cols is None or self._rows is None:
            return SideBands()
        left = self._edge(self._cols)
        right = self._edge(self._cols[..., ::-1])
        top = self._edge(self._rows)
        bottom = self._edge(self._rows[..., ::-1])
        bands = SideBands(left, right, top, bottom)
        if bands.any():
            log.debug("side bands (px): %s", bands)
        return bands

    def _edge(self, acc: np.ndarray) -> int:
        """Band width from index 0 of the profiles (features, parts, n): 0 if none."""
        count = acc[4]
        with np.errstate(invalid="ignore", divide="ignore"):
            feats = acc[:4] / count  # (4, parts, n); NaN where never valid
        n = feats.shape[-1]
        k_max = int(self.MAX_FRACTION * n)
        win = self.WINDOW_PX
        if k_max < win + 1:
            return 0
        csum = np.nancumsum(np.nan_to_num(feats, nan=0.0), axis=-1)
        cnt = np.cumsum(np.isfinite(feats), axis=-1)
        ks = np.arange(win, k_max + 1)

        def window_mean(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
            s = csum[..., hi - 1] - np.where(lo > 0, csum[..., np.maximum(lo - 1, 0)], 0.0)
            c = cnt[..., hi - 1] - np.where(lo > 0, cnt[..., np.maximum(lo - 1, 0)], 0)
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.where(c >= win // 2, s / c, np.nan)

        outer = window_mean(ks - win, ks)  # (4, parts, len(ks))
        inner = window_mean(ks, ks + win)
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.abs(outer - inner) / (0.5 * (np.abs(outer) + np.abs(inner)) + 1.0)
        step = np.nanmax(np.nan_to_num(rel, nan=-1.0), axis=0)  # strongest feature per part
        seen = np.isfinite(outer).any(axis=0) & np.isfinite(inner).any(axis=0)
        if seen.sum(axis=0).max(initial=0) < self.PARTS - 1:
            return 0
        # every part that sees this edge must step; parts outside the view do not vote
        step = np.where(seen, step, np.inf).min(axis=0)
        step[seen.sum(axis=0) < self.PARTS - 1] = 0.0
        best = int(np.argmax(step))
        if step[best] < self.MIN_STEP:
            return 0
        return int(ks[best]) + self.MARGIN_PX


# ------------------------------------------------------------------------------ flat-field


@dataclass(frozen=True)
class FlatField:
    """Multiplicative shading of the frames (vignetting): frame = scene x `profile`."""

    profile: np.ndarray  # float32 (h, w), mean 1 over the frames' valid pixels

    def apply(self, image: np.ndarray) -> np.ndarray:
        """`image` (float32 HxW[xC]) divided by the profile."""
        return image * self.inverse(image.shape)

    def resized(self, size: tuple[int, int]) -> np.ndarray:
        """The profile area-averaged to (w, h) = `size` (cached)."""
        cache = self.__dict__.setdefault("_resized", {})
        if size not in cache:
            cache[size] = shrink(self.profile, size)
        return cache[size]

    def inverse(self, shape: tuple[int, ...]) -> np.ndarray:
        """1 / profile, float32, with as many channels as an image of `shape`."""
        key = len(shape) if len(shape) == 2 else shape[2]
        cache = self.__dict__.setdefault("_inverse", {})
        if key not in cache:
            inv = (1.0 / self.profile).astype(np.float32)
            cache[key] = inv if len(shape) == 2 else cv2.merge([inv] * shape[2])
        return cache[key]


def shading_terms(xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
    """Terms of the log-shading model in normalised frame coordinates (centre 0, sides ±1),
    stacked on a new last axis: x², xy, y² (a fall-off, elliptical or not) and r⁴ (its
    curvature). No linear terms: a tilt of the shading (a fall-off centred off the frame's
    centre, to first order) multiplies two views of the same place, shifted against each
    other, by a constant, which the exposure gains take; it cannot be told from them, and
    leaves no seam."""
    r2 = xn * xn + yn * yn
    return np.stack([xn * xn, xn * yn, yn * yn, r2 * r2], axis=-1).astype(np.float32)


def normalised_grid(shape: tuple[int, ...], size: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """(x, y) normalised frame coordinates of the cell centres of a frame of `shape` resized
    to (w, h) = `size` (pixel centres as `preprocess.scale_matrix`)."""
    h, w = shape[:2]
    tw, th = size
    xs = ((np.arange(tw) + 0.5) * w / tw - 0.5 - (w - 1) / 2) / (w / 2)
    ys = ((np.arange(th) + 0.5) * h / th - 0.5 - (h - 1) / 2) / (h / 2)
    return tuple(np.meshgrid(xs, ys))


class FlatFieldEstimator:
    """Vignetting of a video's frames, fitted on the frames against the mosaic under them.

    Model: log frame(u) = log gain + s(u) + log retina(x), with s = c · `shading_terms`(u)
    (what two shifted views of a place can tell apart; see there). Where
    a frame lands on a mosaic of earlier frames (log intensities, each frame's gain taken out,
    averaged) that also holds the mean of the terms at which those frames saw each place,
    log frame - mosaic = c · (terms(u) - mean terms) + a per-frame constant: the retina
    cancels, and c is a linear least-squares solution (the per-frame constant eliminated,
    cells off by more than `MAX_LOG_RATIO` left out). `LiveCompositor` keeps that mosaic and
    feeds `add`. A camera that does not move leaves the terms' differences at 0: no estimate.
    """

    MIN_FRAMES = 8
    MIN_PROFILE = 0.2  # the fitted profile is clipped at this (never divides by ~0)
    MAX_LOG_RATIO = 0.5  # a cell this far off its frame's median is misplaced or glared
    RIDGE = 1e-3  # relative ridge on the normal equations (a barely moving camera)

    def __init__(self) -> None:
        self._shape: tuple[int, int] | None = None  # frames as decoded
        terms = shading_terms(np.zeros(1), np.zeros(1)).shape[-1]
        self._ata = np.zeros((terms, terms))
        self._atb = np.zeros(terms)
        self._n = 0

    @property
    def n_frames(self) -> int:
        return self._n

    def add(self, frame_shape: tuple[int, ...], ratio: np.ndarray, terms: np.ndarray) -> float:
        """One frame of `frame_shape`: per valid cell, the log ratio of frame to mosaic (n,) and
        the frame's terms minus the mosaic's mean terms (n, k). Returns the frame's log gain
        relative to the mosaic (the median log ratio)."""
        shape = (int(frame_shape[0]), int(frame_shape[1]))
        if self._shape != shape:
            self._shape, self._n = shape, 0
            self._ata[:] = 0.0
            self._atb[:] = 0.0
        if len(ratio) < 12:
            return float(np.median(ratio)) if len(ratio) else 0.0
        offset = float(np.median(ratio))
        keep = np.abs(ratio - offset) < self.MAX_LOG_RATIO
        if keep.sum() < 12:
            return offset
        r, D = ratio[keep], terms[keep].astype(np.float64)
        r = r - r.mean()  # the frame's gain, eliminated
        D = D - D.mean(axis=0)
        self._ata += D.T @ D
        self._atb += D.T @ r
        self._n += 1
        return offset

    def estimate(self) -> FlatField | None:
        """The fitted profile at the frames' size (mean 1); None before `MIN_FRAMES` frames."""
        if self._n < self.MIN_FRAMES or self._shape is None:
            return None
        ridge = self.RIDGE * max(float(np.trace(self._ata)) / len(self._atb), 1e-12)
        coef = np.linalg.solve(self._ata + ridge * np.eye(len(self._atb)), self._atb)
        h, w = self._shape
        x = ((np.arange(w) - (w - 1) / 2) / (w / 2)).astype(np.float32)[None, :]
        y = ((np.arange(h) - (h - 1) / 2) / (h / 2)).astype(np.float32)[:, None]
        c = coef.astype(np.float32)  # the terms of `shading_terms`, broadcast over the frame
        log_profile = c[0] * x * x + c[1] * x * y + c[2] * y * y + c[3] * (x * x + y * y) ** 2
        profile = np.exp(log_profile - log_profile.max())
        profile /= float(profile.mean())
        return FlatField(np.maximum(profile, self.MIN_PROFILE).astype(np.float32))


# ------------------------------------------------------------------------------ per video


class VideoPhotometry:
    """The per-video estimates, updated as frames stream: side bands and flat-field."""

    REFRESH_FRAMES = 10  # frames between two live re-estimates

    def __init__(self, bands: bool = True, flatfield: bool = True) -> None:
        self._bands_on, self._flat_on = bands, flatfield
        self.band_detector = SideBandDetector()
        self.flat_estimator = FlatFieldEstimator()
        self._bands = SideBands()
        self._flat: FlatField | None = None
        self._at = -1

    def observe(self, image: np.ndarray, mask: np.ndarray | None) -> None:
        """Take a frame (as decoded, with its field-of-view mask) into the side-band estimate
        (frames in order)."""
        if self._bands_on:
            self.band_detector.add(image, mask)
        self._maybe_refresh()

    def observe_mosaic(self, shape: tuple[int, ...], ratio: np.ndarray, terms: np.ndarray) -> float:
        """Take a frame against the mosaic under it into the flat-field estimate
        (`FlatFieldEstimator.add`); returns the frame's log gain relative to the mosaic."""
        if not self._flat_on:
            return float(np.median(ratio)) if len(ratio) else 0.0
        offset = self.flat_estimator.add(shape, ratio, terms)
        self._maybe_refresh()
        return offset

    def _maybe_refresh(self) -> None:
        n = max(self.band_detector.n_frames, self.flat_estimator.n_frames)
        if self._at < 0 or n - self._at >= self.REFRESH_FRAMES:
            self.refresh()

    def refresh(self) -> None:
        """Re-estimate from all frames seen (e.g. at the end of the video)."""
        if self._bands_on:
            self._bands = self.band_detector.estimate()
        if self._flat_on:
            self._flat = self.flat_estimator.estimate()
        self._at = max(self.band_detector.n_frames, self.flat_estimator.n_frames)

    @property
    def bands(self) -> SideBands:
        return self._bands

    @property
    def flatfield(self) -> FlatField | None:
        return self._flat

    def frame_mask(self, mask: np.ndarray) -> np.ndarray:
        """`mask` (uint8) without the side bands."""
        if not self._bands.any() or mask.shape != self.band_detector.shape:
            return mask
        return np.where(self._bands.keep(mask.shape), mask, np.uint8(0))

    def correct(self, image: np.ndarray, gain: float | None = None) -> np.ndarray:
        """float32 frame divided by the flat-field (if any) and multiplied by `gain`."""
        flat = self._flat if self._flat_on else None
        scale = 1.0 if gain is None else float(gain)
        if flat is not None and flat.profile.shape == image.shape[:2]:
            return cv2.multiply(image, flat.inverse(image.shape), scale=scale, dtype=cv2.CV_32F)
        return cv2.multiply(image, (scale,) * 4, dtype=cv2.CV_32F)

    def shading(self, shape: tuple[int, ...], size: tuple[int, int]) -> np.ndarray | float:
        """The flat-field of frames of `shape` at (w, h) = `size`; 1 without one."""
        flat = self._flat if self._flat_on else None
        if flat is None or flat.profile.shape != shape[:2]:
            return 1.0
        return flat.resized(size)

    def correct_small(self, image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """`image` resized to (w, h) = `size` (area average), float32, divided by the
        flat-field resized likewise."""
        small = shrink(image, size).astype(np.float32)
        flat = self._flat if self._flat_on else None
        if flat is None or flat.profile.shape != image.shape[:2]:
            return small
        profile = flat.resized(size)
        return small / (profile if small.ndim == 2 else profile[..., None])


# ------------------------------------------------------------------------------ quality


def analysis_factor(shape: tuple[int, ...], longer_px: int = 160) -> float:
    """Frame pixels per cell of the low-resolution analysis grid (>= 1)."""
    return max(1.0, max(shape[:2]) / longer_px)


def small_size(shape: tuple[int, ...], factor: float) -> tuple[int, int]:
    """(w, h) of a frame of `shape` resized by 1 / `factor`."""
    h, w = shape[:2]
    return max(round(w / factor), 1), max(round(h / factor), 1)


SHARPNESS_SIGMA_PX = 12.0  # window (Gaussian σ, frame px) of the local sharpness
BAND_SIGMAS_PX = (2.0, 4.0)  # difference of Gaussians (frame px): vessel detail, above noise


def local_detail(gray: np.ndarray, valid: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Local detail amplitude on a grid of (w, h) = `size` cells: the RMS of a band-pass
    (difference of Gaussians of `BAND_SIGMAS_PX`, where vessels are and noise is weak) over a
    `SHARPNESS_SIGMA_PX` window, in grey levels of the frame as decoded; 0 where nothing is
    valid. Blur lowers it; the same place seen by two frames compares their sharpness (after
    their gains and shading are divided out)."""
    half = cv2.pyrDown(gray).astype(np.float32)
    hsize = (half.shape[1], half.shape[0])
    hv = cv2.resize(valid.astype(np.uint8), hsize, interpolation=cv2.INTER_NEAREST)
    hv = cv2.erode(hv, np.ones((7, 7), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    detail = np.zeros((size[1], size[0]), np.float32)
    if not hv.any():
        return detail
    lo, hi = (s / 2 for s in BAND_SIGMAS_PX)  # at half resolution
    band = cv2.GaussianBlur(half, (0, 0), lo) - cv2.GaussianBlur(half, (0, 0), hi)
    v = hv.astype(np.float32)
    sigma = SHARPNESS_SIGMA_PX * size[0] / gray.shape[1]  # in cells

    def local_sum(x: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(shrink(x, size), (0, 0), sigma)

    norm = local_sum(v)
    energy = local_sum(band * band * v)
    ok = norm > 0.05
    detail[ok] = np.sqrt(energy[ok] / norm[ok])
    return detail


@dataclass(frozen=True)
class FrameQuality:
    """What decides a frame's weight, on its analysis grid (float32 maps, 0 outside its
    valid region) and per frame."""

    ramp: np.ndarray  # distance to the frame's border or view edge over border_px, at most 1
    detail: np.ndarray  # local detail amplitude (`local_detail`), grey levels; 1 if not measured
    glare: np.ndarray  # 1 - 3 x the local share of saturated pixels, at least 0
    level: float  # median grey level of the valid pixels (a proxy for the frame's gain)

    def sharpness(self) -> np.ndarray:
        """Local sharpness x glare: detail relative to the frame's level (its gain does not
        count); the same place in two frames compares how sharply they show it."""
        return self.glare * self.detail / self.level


def frame_quality(
    image: np.ndarray, mask: np.ndarray, factor: float, border_px: float, sharpness: bool
) -> FrameQuality:
    """Quality of a frame (BGR or grey uint8 as decoded; `mask` its valid pixels) on its
    analysis grid, 1 / `factor` of its size. Without `sharpness` only the ramp is measured."""
    size = small_size(image.shape, factor)
    valid = mask > 0
    inside = (inside_share(mask, size) > 0.999).astype(np.uint8)
    padded = cv2.copyMakeBorder(inside, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    dist = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_5)[1:-1, 1:-1]
    ramp = np.minimum(dist * factor / max(border_px, 1e-6), 1.0).astype(np.float32)
    ones = np.ones_like(ramp)
    if not sharpness:
        return FrameQuality(ramp, ones, ones, 100.0)
    gray = image if image.ndim == 2 else cv2.extractChannel(image, 1)
    detail = local_detail(gray, valid, size)
    detail[inside == 0] = 0.0
    share = inside_share(channel_max(image) >= SATURATED, size)
    glare = np.clip(1.0 - 3.0 * cv2.GaussianBlur(share, (0, 0), 2.0), 0.0, 1.0)
    small = shrink(gray, size)
    level = float(np.median(small[inside > 0])) if inside.any() else 100.0
    return FrameQuality(ramp, detail, glare.astype(np.float32), max(level, 2 * DARK))


# ------------------------------------------------------------------------------ exposure


def robust_gain(frame: np.ndarray, reference: np.ndarray, both: np.ndarray) -> float:
    """Gain g with g x frame ≈ reference over `both` (bool HxW), on the channels' mean: the
    median log ratio of pixels neither dark nor saturated; 1 where too few pixels say."""
    f = frame if frame.ndim == 2 else frame.mean(axis=2)
    r = reference if reference.ndim == 2 else reference.mean(axis=2)
    ok = both & (f > 2 * DARK) & (r > 2 * DARK) & (f < SATURATED) & (r < SATURATED)
    if ok.sum() < 50:
        return 1.0
    return float(np.clip(np.exp(np.median(np.log(r[ok]) - np.log(f[ok]))), 1 / 3, 3.0))


class GainObservations:
    """Mean values of coarse mosaic cells as each frame sees them, for `solve_gains`."""

    def __init__(self) -> None:
        self._frames: list[np.ndarray] = []
        self._cells: list[np.ndarray] = []
        self._values: list[np.ndarray] = []

    def __len__(self) -> int:
        return sum(len(c) for c in self._cells)

    def add(self, frame: int, cells: np.ndarray, values: np.ndarray) -> None:
        """Cells (ids unique per segment, under 2^31) and their mean values (n,) in one frame:
        12 bytes a cell kept."""
        ok = values > DARK
        if ok.any():
            self._frames.append(np.full(int(ok.sum()), frame, np.int32))
            self._cells.append(cells[ok].astype(np.int32))
            self._values.append(np.log(values[ok]).astype(np.float32))

    def solve(self, prior_sigma: float = 0.2, rounds: int = 4) -> dict[int, float]:
        """Per-frame compensating gains (what to multiply each frame by): the frames'
        exposures e minimise the log-space disagreement of frames on shared cells, with a
        weak prior log e ~ N(0, `prior_sigma`) relative to the residual noise; the gain is
        1 / e (1 for frames with no shared cell)."""
        if not self._cells:
            return {}
        frames = np.concatenate(self._frames)
        cells = np.concatenate(self._cells)
        y = np.concatenate(self._values).astype(np.float64)[:, None]
        frame_ids, f_idx = np.unique(frames, return_inverse=True)
        _, c_idx, c_count = np.unique(cells, return_inverse=True, return_counts=True)
        shared = c_count[c_idx] >= 2  # a cell one frame saw says nothing about gains
        f_idx, c_idx, y = f_idx[shared], c_idx[shared], y[shared]
        gains = {int(f): 1.0 for f in frame_ids}
        if len(y) == 0:
            return gains
        _, c_idx = np.unique(c_idx, return_inverse=True)
        n_f, n_c = len(frame_ids), int(c_idx.max()) + 1
        w = np.ones(len(y))
        a = np.zeros((n_f, y.shape[1]))
        sigma = 0.05
        for _ in range(rounds):
            a, r = _solve_log_gains(f_idx, c_idx, y, w, n_f, n_c, (sigma / prior_sigma) ** 2)
            resid = (y - a[f_idx] - r[c_idx]).mean(axis=1)
            sigma = max(1.4826 * float(np.median(np.abs(resid))), 0.005)
            w = np.minimum(1.0, 1.5 * sigma / np.maximum(np.abs(resid), 1e-12))
        return {int(f): float(np.exp(-a[i, 0])) for i, f in enumerate(frame_ids)}


def _solve_log_gains(
    f_idx: np.ndarray,
    c_idx: np.ndarray,
    y: np.ndarray,
    w: np.ndarray,
    n_f: int,
    n_c: int,
    prior: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares of y = a[f] + r[c] with prior weight `prior` on a (per unit
    observation weight): the cells are eliminated (Schur complement), a sparse solve for a."""
    d_f = np.bincount(f_idx, w, n_f)
    d_c = np.bincount(c_idx, w, n_c)
    b_f = np.stack([np.bincount(f_idx, w * y[:, k], n_f) for k in range(y.shape[1])], 1)
    b_c = np.stack([np.bincount(c_idx, w * y[:, k], n_c) for k in range(y.shape[1])], 1)
    B = sp.csr_matrix((w, (f_idx, c_idx)), shape=(n_f, n_c))
    inv_c = 1.0 / np.maximum(d_c, 1e-12)
    S = sp.diags(d_f + prior) - B @ sp.diags(inv_c) @ B.T
    rhs = b_f - B @ (inv_c[:, None] * b_c)
    a = spsolve(S.tocsc(), rhs)
    a = a.reshape(n_f, -1)
    r = inv_c[:, None] * (b_c - B.T @ a)
    return a, r
