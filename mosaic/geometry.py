"""Points and transforms, written once: homographies and quadratics applied to points, a
frame's corners, translations, pixel-centre rescaling, the frame-centred normalisation that fits are
conditioned in, Huber weights and the loop of re-weighted fits, and the corner error that scores an
estimate against the truth.

Conventions: points are (N, 2) arrays of (x, y); a transform named `H_a_to_b` maps pixels of a
into b; pixel centres are integers, so resizing by s maps x to (x + 0.5) s - 0.5. Points are
computed in float64 here (the fits and the pose graph need it) and stored as float32 where
they are kept per keypoint (`features.Features`). Runtime stages, the evaluation and the
synthetic data share these helpers, so they live here (the runtime stages import neither
`mosaic.eval` nor `mosaic.synthetic`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numpy as np

Fit = TypeVar("Fit")


def apply_homography(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points (N, 2) mapped by a 3x3 homography (float64)."""
    p = np.column_stack([xy.astype(np.float64), np.ones(len(xy))]) @ H.T
    return p[:, :2] / p[:, 2:]


def quadratic_terms(xy: np.ndarray) -> np.ndarray:
    """(N, 6) monomials x^2, x y, y^2, x, y, 1 of points (N, 2)."""
    x, y = xy[:, 0].astype(np.float64), xy[:, 1].astype(np.float64)
    return np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])


def apply_quadratic(Q: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points (N, 2) mapped by a 2x6 quadratic transform (the retina's curvature between two
    views, `registration`)."""
    return quadratic_terms(xy) @ np.asarray(Q, np.float64).T


def frame_corners(shape: tuple[int, ...]) -> np.ndarray:
    """The four corners (x, y) of an image of `shape` (h, w): its outline, (0, 0) to (w, h)."""
    h, w = shape[:2]
    return np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)


def pixel_centre_corners(shape: tuple[int, ...]) -> np.ndarray:
    """The centres of the four corner pixels (x, y) of an image of `shape` (h, w): (0, 0) to
    (w - 1, h - 1), where a warp samples them (`frame_corners` is the outline)."""
    h, w = shape[:2]
    return np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)


def rescaled(xy: np.ndarray, s: float | np.ndarray) -> np.ndarray:
    """Points of an image in the pixels of that image resized by `s` (a factor or (sx, sy)):
    pixel centres map as (x + 0.5) s - 0.5."""
    return (xy + 0.5) * s - 0.5


def scale_matrix(shape_full: tuple[int, ...], shape_scaled: tuple[int, ...]) -> np.ndarray:
    """H_full_to_scaled of a resize: pixel centres map as x' = (x + 0.5) * s - 0.5."""
    sy = shape_scaled[0] / shape_full[0]
    sx = shape_scaled[1] / shape_full[1]
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def circle_unscaled(circle: tuple[float, float, float], s: float) -> tuple[float, float, float]:
    """A circle (cx, cy, r) found in an image resized by `s`, in the original's pixels."""
    cx, cy, r = circle
    return (cx + 0.5) / s - 0.5, (cy + 0.5) / s - 0.5, r / s


def pixel_scale(s: float) -> np.ndarray:
    """H of a resize by the factor `s` (3x3 float64): pixel centres map as x' = (x + 0.5) s - 0.5,
    as `cv2.resize` samples."""
    return np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5], [0.0, 0.0, 1.0]])


def translation(tx: float, ty: float) -> np.ndarray:
    """3x3 float64 translation matrix by (tx, ty) pixels."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def frame_normaliser(shape: tuple[int, int]) -> np.ndarray:
    """A similarity taking frame pixels to coordinates centred on the frame, unit half-diagonal
    (keeps each model class: a similarity stays a similarity)."""
    h, w = shape
    s = 2.0 / np.hypot(w, h)
    return np.array([[s, 0, -s * (w - 1) / 2], [0, s, -s * (h - 1) / 2], [0, 0, 1.0]])


def normalised(T: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points (N, 2) in the coordinates of a normaliser `T` (a scale and a shift), float64."""
    return xy.astype(np.float64) * T[0, 0] + T[:2, 2]


def huber_weights(residuals: np.ndarray, k: float) -> np.ndarray:
    """Re-weighted least squares' weights of Huber's loss: 1 within `k`, k / |r| beyond."""
    return np.where(residuals <= k, 1.0, k / np.maximum(residuals, 1e-12))


def reweighted_rounds(
    fit: Callable[[int, Fit | None, np.ndarray, np.ndarray], Fit | None],
    errors: Callable[[Fit], np.ndarray],
    inliers: np.ndarray,
    weights: np.ndarray,
    *,
    rounds: int,
    threshold: float,
    huber_k: float,
    min_points: int,
    prior_weights: np.ndarray | None = None,
) -> tuple[Fit | None, np.ndarray, np.ndarray, np.ndarray | None]:
    """Iteratively re-weighted least squares, the one loop of the robust fits: each of
    `rounds` rounds fits the model to the inliers with their weights (`fit(round, previous,
    inliers, weights)`; None: the fit failed, and so does the whole), then takes as inliers the
    points within `threshold` of it, weighted by Huber at `huber_k` (times `prior_weights`).
    Stops early where fewer than `min_points` are inliers. Returns the last fit (None when
    there was none), its inliers, weights and errors (None before a first fit)."""
    state: Fit | None = None
    err: np.ndarray | None = None
    for round_ in range(rounds):
        if inliers.sum() < min_points:
            break
        new = fit(round_, state, inliers, weights)
        if new is None:
            return None, inliers, weights, err
        state = new
        err = errors(state)
        inliers = err < threshold
        weights = huber_weights(err, huber_k)
        if prior_weights is not None:
            weights = prior_weights * weights
    return state, inliers, weights, err


def relative_homographies(gt: list[np.ndarray] | np.ndarray, ref: int = 0) -> list[np.ndarray]:
    """H_i_to_ref = inv(H_ref_to_source) @ H_i_to_source for every frame i (normalised)."""
    G = np.asarray(gt, np.float64)
    rel = np.linalg.inv(G[ref])[None] @ G
    rel /= rel[:, 2:3, 2:3]
    return list(rel)


def corner_error(H_est_i_to_0: np.ndarray, H_gt_i_to_0: np.ndarray, size: tuple[int, int]) -> float:
    """Mean distance (px) between the four frame corners mapped by the estimate and the truth."""
    w, h = size
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
    Hs = np.stack([np.asarray(H_est_i_to_0, float), np.asarray(H_gt_i_to_0, float)])
    mapped = corners[None] @ Hs.transpose(0, 2, 1)
    xy = mapped[..., :2] / mapped[..., 2:]
    return float(np.linalg.norm(xy[0] - xy[1], axis=1).mean())


def view_error(
    H_est_i_to_0: np.ndarray, H_gt_i_to_0: np.ndarray, size: tuple[int, int]
) -> tuple[float, float, float]:
    """How an estimate misplaces a frame, at the frame's centre: the shift (px), the zoom
    (log of the area scale's square root) and the roll (radians) of H_gt^-1 H_est, which takes
    the frame to itself (the identity when the estimate is right). Drift on a long path is
    mostly zoom and roll (a 1 % zoom error moves a corner of a 660x350 frame by 3.7 px)."""
    w, h = size
    A = np.linalg.solve(np.asarray(H_gt_i_to_0, float), np.asarray(H_est_i_to_0, float))
    centre = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    p = A @ centre
    xy = p[:2] / p[2]
    J = (A[:2, :2] - np.outer(xy, A[2, :2])) / p[2]  # the map's derivative at the centre
    zoom = 0.5 * float(np.log(abs(np.linalg.det(J))))
    roll = float(np.arctan2(J[1, 0] - J[0, 1], J[0, 0] + J[1, 1]))
    return float(np.linalg.norm(xy - centre[:2])), zoom, roll


__all__ = [
    "apply_homography",
    "apply_quadratic",
    "corner_error",
    "frame_corners",
    "frame_normaliser",
    "huber_weights",
    "normalised",
    "quadratic_terms",
    "relative_homographies",
    "rescaled",
    "scale_matrix",
    "translation",
    "view_error",
]
