"""Synthetic training pairs: random homographies and appearance changes of one base image.

Paper ("Dataset" and supplementary "Method for homography generation"): from a base image B,
each step warps B by two random homographies g, g' (each a composition of scaling,
perspective, translation, shearing and rotation, ranges in `HomographyRanges`) into images I
and I', related by H_I_to_I' = g' g^-1; on top, a random subset of gaussian noise, contrast,
illumination, gamma, motion blur and image inversion is applied to each image independently.
Training uses 256x256 crops of the warped images.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class HomographyRanges:
    """Parameter ranges of one random homography (the paper's supplementary table)."""

    scale: tuple[float, float] = (0.7, 1.3)  # isotropic scaling factor
    perspective: tuple[float, float] = (1e-6, 8e-4)  # |h20|, |h21| per pixel, random sign
    max_translation_px: float = 100.0  # per axis, uniform in [-max, max]
    shear: float = 0.2  # horizontal and vertical shear, uniform in [-shear, shear]
    max_rotation_deg: float = 25.0  # uniform in [-max, max]


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def random_homography(
    rng: np.random.Generator,
    shape: tuple[int, ...],
    ranges: HomographyRanges = HomographyRanges(),
) -> np.ndarray:
    """A random 3x3 float64 homography g mapping base-image pixels to warped-image pixels.

    g = C T R Sh S P C^-1: perspective P, isotropic scaling S, shear Sh, rotation R and
    translation T, all about the centre of an image of `shape` (C moves the centre to the
    origin), so that scaling/rotation do not shift the image away.
    """
    h, w = shape[:2]
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    s = rng.uniform(*ranges.scale)
    S = np.diag([s, s, 1.0])
    shx, shy = rng.uniform(-ranges.shear, ranges.shear, size=2)
    Sh = np.array([[1.0, shx, 0.0], [shy, 1.0, 0.0], [0.0, 0.0, 1.0]])
    a = np.deg2rad(rng.uniform(-ranges.max_rotation_deg, ranges.max_rotation_deg))
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    p = rng.uniform(*ranges.perspective, size=2) * rng.choice([-1.0, 1.0], size=2)
    P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [p[0], p[1], 1.0]])
    t = rng.uniform(-ranges.max_translation_px, ranges.max_translation_px, size=2)
    g = _translation(cx, cy) @ _translation(*t) @ R @ Sh @ S @ P @ _translation(-cx, -cy)
    return g / g[2, 2]


def make_pair(
    base: np.ndarray,
    rng: np.random.Generator,
    crop: int = 256,
    ranges: HomographyRanges = HomographyRanges(),
    max_offset_frac: float = 0.25,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(I, I', H_I_to_I'): two crop x crop views of grey uint8 `base` under random homographies.

    A centre point c is drawn in the central half of the base image; I is the crop of g(B)
    around g(c) and I' the crop of g'(B) around g'(c), each shifted by a random offset of at
    most `max_offset_frac * crop / 2` per axis, so the crops overlap substantially. Only the
    crops are rendered (the crop offsets are folded into the warps): H = A' A^-1 with
    A = T(-o) g, A' = T(-o') g'. Pixels from outside the base image are black.
    No appearance change is applied here (see `augment`).
    """
    if base.ndim != 2 or base.dtype != np.uint8:
        raise ValueError(f"base must be uint8 HxW grey, got {base.dtype} of shape {base.shape}")
    h, w = base.shape
    g1 = random_homography(rng, base.shape, ranges)
    g2 = random_homography(rng, base.shape, ranges)
    c = np.array([rng.uniform(0.25, 0.75) * (w - 1), rng.uniform(0.25, 0.75) * (h - 1), 1.0])
    jitter = max_offset_frac * crop / 2.0
    warps = []
    for g in (g1, g2):
        q = g @ c
        centre = q[:2] / q[2] + rng.uniform(-jitter, jitter, size=2)
        top_left = centre - (crop - 1) / 2.0
        warps.append(_translation(-top_left[0], -top_left[1]) @ g)
    A1, A2 = warps
    I1, I2 = (
        cv2.warpPerspective(base, A, (crop, crop), flags=cv2.INTER_LINEAR, borderValue=0)
        for A in (A1, A2)
    )
    H = A2 @ np.linalg.inv(A1)
    return I1, I2, H / H[2, 2]


def _motion_blur(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    length = int(rng.choice([3, 5, 7, 9]))
    kernel = np.zeros((length, length), dtype=np.float32)
    a = rng.uniform(0.0, np.pi)
    r = (length - 1) / 2.0
    p0 = (round(r - r * np.cos(a)), round(r - r * np.sin(a)))
    p1 = (round(r + r * np.cos(a)), round(r + r * np.sin(a)))
    cv2.line(kernel, p0, p1, 1.0, thickness=1)
    return cv2.filter2D(image, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)


def _illumination(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """A smooth multiplicative gain: a linear gradient or a vignette about a random centre."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    if rng.random() < 0.5:
        a = rng.uniform(0.0, 2.0 * np.pi)
        ramp = np.cos(a) * (x / max(w - 1, 1) - 0.5) + np.sin(a) * (y / max(h - 1, 1) - 0.5)
        return 1.0 + rng.uniform(0.3, 0.8) * ramp  # gain in about [0.6, 1.4]
    cx, cy = rng.uniform(0.25, 0.75) * w, rng.uniform(0.25, 0.75) * h
    r2 = ((x - cx) ** 2 + (y - cy) ** 2) / float(max(h, w) ** 2)
    return np.clip(1.0 - rng.uniform(0.5, 1.5) * r2, 0.2, 1.0)


AUGMENTATIONS = ("noise", "contrast", "illumination", "gamma", "motion_blur", "inverse")
JPEG_QUALITY_MIN, JPEG_QUALITY_MAX = 15, 60  # the optional compression change (see augment)


def augment(
    image: np.ndarray,
    rng: np.random.Generator,
    p: float = 0.5,
    p_inverse: float = 0.1,
    p_jpeg: float = 0.0,
) -> np.ndarray:
    """Apply a random subset of the paper's appearance changes to a grey uint8 image.

    Each of illumination, contrast, gamma, motion blur and gaussian noise is chosen with
    probability `p` (applied in that order), then the image is inverted with probability
    `p_inverse`; inversion is kept rare because upright SIFT cannot match an inverted image
    to a normal one, so such pairs give no reward. With probability `p_jpeg` (not in the paper;
    0 draws nothing, so the other changes stay as they were) the result is JPEG-compressed at a
    random quality in [JPEG_QUALITY_MIN, JPEG_QUALITY_MAX], like frames of a compressed video.
    """
    chosen = rng.random(6) < np.array([p, p, p, p, p, p_inverse])
    use_illum, use_contrast, use_gamma, use_blur, use_noise, use_inverse = chosen
    out = image.astype(np.float32)
    if use_illum:
        out *= _illumination(image.shape, rng)
    if use_contrast:
        mean = float(out.mean())
        out = (out - mean) * rng.uniform(0.5, 1.5) + mean
    if use_gamma:
        out = 255.0 * (np.clip(out, 0.0, 255.0) / 255.0) ** rng.uniform(0.5, 2.0)
    if use_blur:
        out = _motion_blur(out, rng)
    if use_noise:
        out += rng.normal(0.0, rng.uniform(2.0, 12.0), size=out.shape).astype(np.float32)
    out = np.clip(out + 0.5, 0.0, 255.0).astype(np.uint8)
    if use_inverse:
        out = 255 - out
    if p_jpeg > 0 and rng.random() < p_jpeg:
        quality = int(rng.integers(JPEG_QUALITY_MIN, JPEG_QUALITY_MAX + 1))
        encoded = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, quality])[1]
        out = cv2.imdecode(encoded, cv2.IMREAD_GRAYSCALE)
    return out


def fixed_pairs(
    images: Sequence[np.ndarray],
    seed: int,
    n_per_image: int,
    crop: int = 256,
    ranges: HomographyRanges = HomographyRanges(),
    appearance: bool = True,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Deterministic validation pairs: the same (I, I', H) for the same images and seed.

    Pair k of image i uses its own generator seeded with (seed, i, k), so the set does not
    depend on call order.
    """
    pairs = []
    for i, base in enumerate(images):
        for k in range(n_per_image):
            rng = np.random.default_rng([seed, i, k])
            I1, I2, H = make_pair(base, rng, crop, ranges)
            if appearance:
                I1, I2 = augment(I1, rng), augment(I2, rng)
            pairs.append((I1, I2, H))
    return pairs


def green_clahe(image: np.ndarray, clip_limit: float = 2.0, tile_grid: int = 8) -> np.ndarray:
    """Grey uint8 input the way the app pre-processes fundus frames: green channel + CLAHE.

    A BGR colour image (OpenCV order) gives its green channel; a grey image is used as is.
    """
    grey = image
    if image.ndim == 3:
        grey = image[..., 1] if image.shape[2] >= 3 else image[..., 0]
    grey = np.ascontiguousarray(grey, dtype=np.uint8)
    clahe = cv2.createCLAHE(clipLimit=clip_limit, tileGridSize=(tile_grid, tile_grid))
    return clahe.apply(grey)


def frame_preprocess(
    grey: np.ndarray,
    clip_limit: float = 2.0,
    tile_grid: int = 8,
    bilateral: tuple[int, float, float] | None = (5, 25.0, 5.0),
) -> np.ndarray:
    """CLAHE then a bilateral filter (diameter, sigma colour, sigma space) on a grey uint8 image.

    The application's per-frame pre-processing with its default settings (mosaic's
    `[preprocess]` table), so training can show the network exactly what it sees at inference.
    """
    out = green_clahe(grey, clip_limit, tile_grid)
    if bilateral is not None:
        d, sigma_color, sigma_space = bilateral
        out = cv2.bilateralFilter(out, d, sigma_color, sigma_space)
    return out
