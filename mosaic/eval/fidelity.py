"""Mosaic fidelity against the truth (issue 16): how faithfully a mosaic shows the retina.

A synthetic video (`mosaic synth`) knows the photograph it was rendered from and each frame's
`H_frame_to_source`. The source is warped into the mosaic's canvas by one canvas-to-source
homography, fitted by least squares over a grid of points of every registered frame (its
reported pose places them in the canvas, the truth in the source): the mosaic is judged as a
whole, in the frame the user sees. Both green channels are high-passed (a Gaussian blur of sigma
8 px subtracted) and compared by local normalised cross-correlation over a 21 px box window, so
gain, vignetting and slow illumination changes do not count; misplaced, doubled or blurred
vessels do.

- fidelity: mean local NCC over the pixels where the mosaic has content and the warped source
  is valid (inside the source photograph's field of view);
- good area: share of the truly scanned retina (the union of the frames' true footprints,
  inside the source's field of view, in the canvas by the fitted map) whose local NCC is above
  0.5; retina the mosaic does not cover counts as not good;
- oracle (`oracle_fidelity`): the same scores for the plain mean of the decoded frames placed
  by the true transforms, composed one frame at a time on an `average` `Canvas`.

Every statistic is masked: both high-passes and the window means are taken over the pixels
where both images are valid only (blurs normalised by the blurred mask), so neither the canvas'
empty part nor the source's black border enters a score as an edge.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from mosaic.canvas import Canvas
from mosaic.config import ComposeConfig
from mosaic.errors import CanvasLimitError
from mosaic.geometry import pixel_centre_corners, translation
from mosaic.preprocess import erode_by_disc
from mosaic.registration import apply_homography as transform

log = logging.getLogger(__name__)

HIGHPASS_SIGMA_PX = 8.0  # Gaussian blur subtracted before correlating (issue 16)
NCC_WINDOW_PX = 21  # side of the local NCC's box window (issue 16)
GOOD_NCC = 0.5  # local NCC above which a pixel of scanned retina counts as good
GRID_POINTS = 5  # points per side of each frame for the canvas-to-source fit
ROBUST_SCALE_PX = 2.0  # soft-L1 scale of the fit's transfer error, in canvas pixels
SOURCE_FOV_THRESHOLD = 15  # grey level under which the source photograph's border is outside
SOURCE_FOV_ERODE_PX = 3  # margin kept off the source's field-of-view edge
_MIN_WINDOW_SHARE = 0.25  # a window needs this share of valid pixels for its NCC to count
_VARIANCE_EPS = 1e-2  # grey levels squared added to each local variance (flat windows -> 0)
_MIN_BLUR_WEIGHT = 1e-3  # normalised blur: weight under which a pixel has no valid neighbour
_MIN_W = 1e-9  # homogeneous coordinate under which a point counts as sent to infinity


@dataclass(frozen=True)
class FidelityScores:
    """Fidelity (mean local NCC) and good area (share of scanned retina with NCC > 0.5)."""

    fidelity: float = math.nan
    good_area: float = math.nan


@dataclass(frozen=True)
class SourceTruth:
    """The source photograph as the metric uses it: green channel and field of view."""

    green: np.ndarray  # float32 HxW
    fov: np.ndarray  # uint8 HxW, 255 inside the field of view


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------


def green_channel(image: np.ndarray) -> np.ndarray:
    """float32 green channel of a BGR image (a grey image as it is)."""
    channel = image if image.ndim == 2 else image[..., 1]
    return channel.astype(np.float32)


def prepare_source(image: np.ndarray) -> SourceTruth:
    """Green channel and field-of-view mask of a source photograph (BGR or grey uint8).

    The view is the region brighter than SOURCE_FOV_THRESHOLD after a light blur, holes
    (vessels, lesions) filled, eroded by SOURCE_FOV_ERODE_PX (as `mosaic synth` finds it).
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    fov = (cv2.GaussianBlur(gray, (0, 0), 2.0) > SOURCE_FOV_THRESHOLD).astype(np.uint8)
    n, labels = cv2.connectedComponents(1 - fov, connectivity=4)
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    outside = np.zeros(n, bool)
    outside[edge] = True
    outside[0] = True  # label 0: the bright region itself
    fov = np.where(outside[labels] & (fov == 0), 0, 255).astype(np.uint8)
    fov = erode_by_disc(fov, SOURCE_FOV_ERODE_PX, edge_counts=True)
    return SourceTruth(green=green_channel(image), fov=fov)


def highpass(
    gray: np.ndarray, valid: np.ndarray, sigma_px: float = HIGHPASS_SIGMA_PX
) -> np.ndarray:
    """`gray` minus its Gaussian blur, both over `valid` pixels only (0 elsewhere), float32.

    The blur is normalised by the blurred mask: the edge of the valid region (empty canvas,
    the source's black border) is not taken for structure.
    """
    m = valid.astype(np.float32)
    g = gray.astype(np.float32) * m
    num = cv2.GaussianBlur(g, (0, 0), sigma_px)
    den = cv2.GaussianBlur(m, (0, 0), sigma_px)
    low = np.divide(num, den, out=np.zeros_like(num), where=den > _MIN_BLUR_WEIGHT)
    return (g - low) * m


def local_ncc(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, window_px: int = NCC_WINDOW_PX
) -> tuple[np.ndarray, np.ndarray]:
    """Local NCC of `a` and `b` over a box window, from valid pixels only: (ncc, defined).

    Means, variances and covariance of each window are taken over its valid pixels; the NCC
    is defined (float32, 0 elsewhere) at valid pixels whose window is at least
    _MIN_WINDOW_SHARE valid. A tiny variance floor makes flat windows score 0, not noise.
    """
    m = valid.astype(np.float32)
    size = (window_px, window_px)

    def box(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, cv2.CV_32F, size, borderType=cv2.BORDER_CONSTANT)

    am, bm = a.astype(np.float32) * m, b.astype(np.float32) * m
    share = box(m)
    n = np.maximum(share, 1e-6)
    mean_a, mean_b = box(am) / n, box(bm) / n
    var_a = np.maximum(box(am * a) / n - mean_a * mean_a, 0.0)
    var_b = np.maximum(box(bm * b) / n - mean_b * mean_b, 0.0)
    cov = box(am * b) / n - mean_a * mean_b
    ncc = cov / np.sqrt((var_a + _VARIANCE_EPS) * (var_b + _VARIANCE_EPS))
    defined = valid & (share >= _MIN_WINDOW_SHARE)
    return np.where(defined, np.clip(ncc, -1.0, 1.0), 0.0).astype(np.float32), defined


# --------------------------------------------------------------------------------------------
# Canvas-to-source homography
# --------------------------------------------------------------------------------------------


def frame_grid(frame_size: tuple[int, int], n: int = GRID_POINTS) -> np.ndarray:
    """An n x n grid of points (N, 2) spanning a frame of (width, height), corners included."""
    w, h = frame_size
    xs, ys = np.meshgrid(np.linspace(0.0, w - 1.0, n), np.linspace(0.0, h - 1.0, n))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def _hartley_normaliser(xy: np.ndarray) -> np.ndarray:
    """Hartley's normalisation of a point cloud: centroid to 0, mean distance to it sqrt(2)
    (not `geometry.frame_normaliser`, which a frame's shape fixes)."""
    centre = xy.mean(axis=0)
    spread = float(np.linalg.norm(xy - centre, axis=1).mean())
    s = math.sqrt(2.0) / max(spread, 1e-12)
    return np.array([[s, 0.0, -s * centre[0]], [0.0, s, -s * centre[1]], [0.0, 0.0, 1.0]])


def fit_homography(
    src_xy: np.ndarray, dst_xy: np.ndarray, robust_px: float = ROBUST_SCALE_PX
) -> np.ndarray:
    """Least-squares H_src_to_dst of point correspondences (N >= 4), robust to a few outliers.

    Least squares (OpenCV), then Levenberg-Marquardt style refinement (scipy's trust region) of the
    transfer error in dst pixels with a soft-L1 loss of scale `robust_px` src pixels (converted
    by the ratio of the two point clouds' spreads). Normalised to H[2, 2] = 1.
    """
    src, dst = np.asarray(src_xy, np.float64), np.asarray(dst_xy, np.float64)
    if len(src) < 4 or src.shape != dst.shape:
        raise ValueError(f"need >= 4 point pairs of equal shape, got {src.shape}, {dst.shape}")
    T_src, T_dst = _hartley_normaliser(src), _hartley_normaliser(dst)
    H0, _ = cv2.findHomography(src, dst, 0)  # least squares: the start
    if H0 is None:
        raise ValueError("degenerate point pairs: no homography")
    Hn = T_dst @ H0 @ np.linalg.inv(T_src)
    Hn = Hn / Hn[2, 2]
    T_dst_inv = np.linalg.inv(T_dst)

    def full(p: np.ndarray) -> np.ndarray:
        return T_dst_inv @ np.append(p, 1.0).reshape(3, 3) @ T_src

    def residuals(p: np.ndarray) -> np.ndarray:
        return (transform(full(p), src) - dst).ravel()

    scale = T_src[0, 0] / T_dst[0, 0]  # dst pixels per src pixel, roughly
    fit = least_squares(
        residuals, Hn.ravel()[:8], loss="soft_l1", f_scale=robust_px * scale, x_scale="jac"
    )
    H = full(fit.x)
    return H / H[2, 2]


def fit_canvas_to_source(
    H_frames_to_canvas: Sequence[np.ndarray],
    H_frames_to_source: Sequence[np.ndarray],
    frame_size: tuple[int, int],
) -> np.ndarray:
    """H_canvas_to_source over all registered frames: a grid of each frame placed by its pose
    in the canvas and by the truth in the source, fitted by `fit_homography`."""
    if not H_frames_to_canvas or len(H_frames_to_canvas) != len(H_frames_to_source):
        raise ValueError("need one truth per pose, at least one frame")
    grid = frame_grid(frame_size)
    canvas = np.concatenate([transform(np.asarray(H, float), grid) for H in H_frames_to_canvas])
    source = np.concatenate([transform(np.asarray(H, float), grid) for H in H_frames_to_source])
    return fit_homography(canvas, source)


# --------------------------------------------------------------------------------------------
# Scores
# --------------------------------------------------------------------------------------------


def _footprint_corners(
    H_frames_to_canvas: Sequence[np.ndarray], frame_size: tuple[int, int]
) -> list[np.ndarray]:
    """Each frame's four corners in the canvas; frames sent (partly) to infinity are left out."""
    corners = np.c_[pixel_centre_corners(frame_size[::-1]), np.ones(4)]
    out = []
    for H in H_frames_to_canvas:
        mapped = corners @ np.asarray(H, np.float64).T
        if np.all(np.isfinite(mapped)) and np.all(mapped[:, 2] > _MIN_W):
            out.append(mapped[:, :2] / mapped[:, 2:])
    return out


def footprints_mask(quads: Sequence[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """bool (H, W): union of the frames' footprints (quadrilaterals (4, 2), canvas pixels)."""
    mask = np.zeros(shape, np.uint8)
    shift = 4  # sub-pixel vertices
    for quad in quads:
        pts = np.rint(np.clip(quad, -1e6, 1e6) * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=shift)
    return mask.astype(bool)


def _warp_fov(
    source: SourceTruth, H_canvas_to_source: np.ndarray, shape: tuple[int, int]
) -> np.ndarray:
    """bool (H, W): canvas pixels whose every bilinear tap is inside the source's view."""
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    warped = cv2.warpPerspective(source.fov, H_canvas_to_source, shape[::-1], flags=flags)
    return warped == 255


def score_mosaic(
    mosaic: np.ndarray,
    content: np.ndarray,
    H_canvas_to_source: np.ndarray,
    source: SourceTruth,
    scanned_to_source: Sequence[np.ndarray],
    frame_size: tuple[int, int],
) -> FidelityScores:
    """Fidelity and good area of a mosaic whose canvas maps to the source by
    `H_canvas_to_source`; `scanned_to_source` are the true H_frame_to_source of every frame
    the video scanned (the good area's denominator), `content` (bool) where the mosaic has any.

    The scanned retina may reach beyond the mosaic's canvas; it is counted on a larger
    (uint8) box, at most the mosaic's size again on each side, while the float work stays on
    the mosaic's own canvas.
    """
    h, w = mosaic.shape[:2]
    H_c2s = np.asarray(H_canvas_to_source, np.float64)
    H_s2c = np.linalg.inv(H_c2s)
    quads = _footprint_corners([H_s2c @ G for G in scanned_to_source], frame_size)

    # Scanned retina over the canvas grown to the footprints (bounded).
    x0, y0, x1, y1 = 0, 0, w, h
    if quads:
        pts = np.concatenate(quads)
        margin = max(w, h)
        lo = np.maximum(np.floor(pts.min(axis=0)), [-margin, -margin]).astype(int)
        hi = np.minimum(np.ceil(pts.max(axis=0)) + 1, [w + margin, h + margin]).astype(int)
        if (pts.min(axis=0) < -margin).any() or (pts.max(axis=0) > [w + margin, h + margin]).any():
            log.warning(
                "scanned retina clipped to %d px around the mosaic: good area too high", margin
            )
        x0, y0 = min(x0, int(lo[0])), min(y0, int(lo[1]))
        x1, y1 = max(x1, int(hi[0])), max(y1, int(hi[1]))
    T = translation(-float(x0), -float(y0))  # canvas -> box pixels
    box_shape = (y1 - y0, x1 - x0)
    scanned = footprints_mask([transform(T, q) for q in quads], box_shape)
    scanned &= _warp_fov(source, H_c2s @ np.linalg.inv(T), box_shape)
    n_scanned = int(scanned.sum())
    scanned_here = scanned[-y0 : h - y0, -x0 : w - x0]

    # Local NCC on the mosaic's canvas.
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    warped = cv2.warpPerspective(source.green, H_c2s, (w, h), flags=flags)
    source_valid = _warp_fov(source, H_c2s, (h, w))
    both = np.asarray(content, bool) & source_valid
    ncc, defined = local_ncc(highpass(green_channel(mosaic), both), highpass(warped, both), both)
    fidelity = float(ncc[defined].mean()) if defined.any() else math.nan
    good = int((scanned_here & defined & (ncc > GOOD_NCC)).sum())
    good_area = good / n_scanned if n_scanned else math.nan
    return FidelityScores(fidelity, good_area)


def mosaic_fidelity(
    mosaic: np.ndarray,
    content: np.ndarray,
    poses: Mapping[int, np.ndarray],
    truth: Sequence[np.ndarray],
    source: SourceTruth,
    frame_size: tuple[int, int],
    scanned: Iterable[int],
) -> FidelityScores:
    """Scores of a mosaic from its frames' poses (`poses`: index -> H_frame_to_canvas).

    The canvas-to-source map is fitted over the posed frames that have a truth
    (`truth[index]` = H_frame_to_source); `scanned` lists every frame the video scanned (read),
    whose true footprints make the good area's denominator. NaN scores without a posed frame.
    """
    indices = [i for i in poses if 0 <= i < len(truth)]
    if not indices:
        return FidelityScores()
    H_c2s = fit_canvas_to_source(
        [poses[i] for i in indices], [truth[i] for i in indices], frame_size
    )
    scanned_to_source = [truth[i] for i in scanned if 0 <= i < len(truth)]
    return score_mosaic(mosaic, content, H_c2s, source, scanned_to_source, frame_size)


def mean_mosaic_fidelity(
    frames: Iterable[tuple[int, np.ndarray | None]],
    H_frame_to_ref: Mapping[int, np.ndarray],
    truth: Sequence[np.ndarray],
    source: SourceTruth,
    mask_of: Callable[[np.ndarray], np.ndarray | None] | None = None,
    max_canvas_px: int = ComposeConfig.max_canvas_px,
) -> FidelityScores:
    """Scores of the plain mean of `frames` placed by `H_frame_to_ref` (index -> pose).

    Frames are added one at a time to an `average` canvas (never kept); `mask_of(image)` gives
    each frame's valid pixels (None: all). Frames without a pose or a truth are left out, as
    are frames the canvas cap refuses (a warning).
    """
    canvas = Canvas(ComposeConfig(blend="average", max_canvas_px=max_canvas_px))
    placed: list[int] = []
    frame_size: tuple[int, int] | None = None
    for index, image in frames:
        if image is None or index not in H_frame_to_ref or not 0 <= index < len(truth):
            continue
        try:
            canvas.add(image, H_frame_to_ref[index], None if mask_of is None else mask_of(image))
        except CanvasLimitError as exc:
            log.warning("frame %d left out of the mean mosaic: %s", index, exc)
            continue
        placed.append(index)
        frame_size = (image.shape[1], image.shape[0])
    if not placed or frame_size is None:
        return FidelityScores()
    H_ref_to_canvas = canvas.H_ref_to_canvas
    poses = {i: H_ref_to_canvas @ H_frame_to_ref[i] for i in placed}
    content = canvas.coverage() > 0
    return mosaic_fidelity(canvas.render(), content, poses, truth, source, frame_size, placed)


def oracle_fidelity(
    frames: Iterable[tuple[int, np.ndarray | None]],
    truth: Sequence[np.ndarray],
    source: SourceTruth,
    mask_of: Callable[[np.ndarray], np.ndarray | None] | None = None,
    max_canvas_px: int = ComposeConfig.max_canvas_px,
) -> FidelityScores:
    """The oracle: the plain mean of all frames placed by the true transforms (relative to
    frame 0), whose canvas-to-source map is then exact."""
    if not truth:
        return FidelityScores()
    G = np.asarray(truth, np.float64)
    rel = np.linalg.inv(G[0])[None] @ G
    poses = {i: rel[i] / rel[i, 2, 2] for i in range(len(G))}
    return mean_mosaic_fidelity(frames, poses, truth, source, mask_of, max_canvas_px)


__all__ = [
    "GOOD_NCC",
    "HIGHPASS_SIGMA_PX",
    "NCC_WINDOW_PX",
    "FidelityScores",
    "SourceTruth",
    "fit_canvas_to_source",
    "fit_homography",
    "footprints_mask",
    "frame_grid",
    "green_channel",
    "highpass",
    "local_ncc",
    "mean_mosaic_fidelity",
    "mosaic_fidelity",
    "oracle_fidelity",
    "prepare_source",
    "score_mosaic",
    "transform",
]
