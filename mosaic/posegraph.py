"""Global refinement of keyframe poses: a pose graph solved by robust least squares.

Unknowns are the homographies `H_kf_to_ref` of all keyframes but the first (the reference,
fixed to identity). Each constraint is a pair of keyframes with matched inlier points; its
residual is the distance, in reference-frame pixels, between the two keyframes' images of the
same retinal point. A soft-L1 loss keeps a bad loop closure from bending the whole mosaic.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Constraint:
    """Inlier correspondences between keyframes `a` and `b` (points in each one's pixels)."""

    a: int
    b: int
    xy_a: np.ndarray  # (K, 2) float
    xy_b: np.ndarray  # (K, 2) float


@dataclass(frozen=True)
class Refinement:
    """Refined poses and the residual RMS (px) before and after."""

    poses: dict[int, np.ndarray]
    rms_before_px: float
    rms_after_px: float
    n_constraints: int


def _to_params(H: np.ndarray) -> np.ndarray:
    return (H / H[2, 2]).ravel()[:8]


def _to_matrix(p: np.ndarray) -> np.ndarray:
    return np.append(p, 1.0).reshape(3, 3)


def _project(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = xy @ H[:2, :2].T + H[:2, 2]
    w = xy @ H[2, :2] + H[2, 2]
    return p / w[:, None]


def _residuals(poses: dict[int, np.ndarray], constraints: list[Constraint]) -> np.ndarray:
    return np.concatenate(
        [(_project(poses[c.a], c.xy_a) - _project(poses[c.b], c.xy_b)).ravel() for c in constraints]
    )


def refine_poses(
    poses: dict[int, np.ndarray],
    constraints: list[Constraint],
    fixed: int,
    loss_scale_px: float = 2.0,
) -> Refinement:
    """Least-squares poses consistent with all constraints; `fixed` keeps its pose."""
    constraints = [c for c in constraints if c.a in poses and c.b in poses and len(c.xy_a)]
    free = [k for k in sorted(poses) if k != fixed]
    if not constraints or not free:
        return Refinement(dict(poses), 0.0, 0.0, len(constraints))
    column = {k: 8 * i for i, k in enumerate(free)}

    def unpack(x: np.ndarray) -> dict[int, np.ndarray]:
        out = {fixed: poses[fixed]}
        out.update({k: _to_matrix(x[column[k] : column[k] + 8]) for k in free})
        return out

    def fun(x: np.ndarray) -> np.ndarray:
        return _residuals(unpack(x), constraints)

    n_res = 2 * sum(len(c.xy_a) for c in constraints)
    sparsity = lil_matrix((n_res, 8 * len(free)), dtype=np.int8)
    row = 0
    for c in constraints:
        rows = slice(row, row + 2 * len(c.xy_a))
        for k in (c.a, c.b):
            if k in column:
                sparsity[rows, column[k] : column[k] + 8] = 1
        row += 2 * len(c.xy_a)

    x0 = np.concatenate([_to_params(poses[k]) for k in free])
    before = fun(x0)
    result = least_squares(
        fun,
        x0,
        jac_sparsity=sparsity,
        loss="soft_l1",
        f_scale=loss_scale_px,
        x_scale="jac",
        method="trf",
        max_nfev=200,
    )
    refined = unpack(result.x)
    rms_before = float(np.sqrt(np.mean(before**2) * 2))
    rms_after = float(np.sqrt(np.mean(result.fun**2) * 2))
    log.info(
        "pose graph: %d keyframes, %d constraints, residual RMS %.2f -> %.2f px",
        len(poses),
        len(constraints),
        rms_before,
        rms_after,
    )
    return Refinement(refined, rms_before, rms_after, len(constraints))
