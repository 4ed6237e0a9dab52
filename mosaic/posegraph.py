"""Global refinement of frame poses: a pose graph solved by robust least squares.

Unknowns are the homographies `H_node_to_ref` of all nodes (frames) but one (the reference,
fixed). Each constraint is a pair of nodes with corresponding points (matched inliers, or the
points a registration's chosen motion model predicts); its residual is the transfer error of
those points from one node into the other, scaled by the constraint's weight. A soft-L1
loss limits the pull of bad points; a loop closure that still disagrees with the solution by
more than `max_loop_rms_px` is dropped and the graph solved again, so one wrong closure cannot
bend the whole mosaic.
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
    loop: bool = False  # a loop closure (may be dropped), not a tracking step
    weight: float = 1.0  # residuals are multiplied by this (1 / expected error in px)


@dataclass(frozen=True)
class Refinement:
    """Refined poses and the residual RMS (px) before and after."""

    poses: dict[int, np.ndarray]
    rms_before_px: float
    rms_after_px: float
    n_constraints: int
    dropped_loops: int = 0


def _to_params(H: np.ndarray) -> np.ndarray:
    return (H / H[2, 2]).ravel()[:8]


def _to_matrix(p: np.ndarray) -> np.ndarray:
    return np.append(p, 1.0).reshape(3, 3)


def _project(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = xy @ H[:2, :2].T + H[:2, 2]
    w = xy @ H[2, :2] + H[2, 2]
    return p / w[:, None]


def _residuals(poses: dict[int, np.ndarray], constraints: list[Constraint]) -> np.ndarray:
    """Transfer errors in keyframe b's own pixels: a point of a, mapped a → ref → b, against
    its match in b. Measured in image pixels rather than reference pixels, the residual gives
    the solver no reward for shrinking the mosaic away from the fixed keyframe."""
    return np.concatenate(
        [
            c.weight * (_project(np.linalg.solve(poses[c.b], poses[c.a]), c.xy_a) - c.xy_b).ravel()
            for c in constraints
        ]
    )


def _solve(
    poses: dict[int, np.ndarray],
    constraints: list[Constraint],
    fixed: int,
    loss_scale_px: float,
) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray]:
    """One robust least-squares solve: refined poses, residuals before and after."""
    free = [k for k in sorted(poses) if k != fixed]
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
    return unpack(result.x), before, result.fun


def _rms(residuals: np.ndarray) -> float:
    return float(np.sqrt(np.mean(residuals**2) * 2)) if len(residuals) else 0.0


def refine_poses(
    poses: dict[int, np.ndarray],
    constraints: list[Constraint],
    fixed: int,
    loss_scale_px: float = 2.0,
    max_loop_rms_px: float = 5.0,
) -> Refinement:
    """Least-squares poses consistent with the constraints; `fixed` keeps its pose."""
    constraints = [c for c in constraints if c.a in poses and c.b in poses and len(c.xy_a)]
    if not constraints or len(poses) < 2:
        return Refinement(dict(poses), 0.0, 0.0, len(constraints))
    refined, before, after = _solve(poses, constraints, fixed, loss_scale_px)
    rms_before = _rms(before)
    kept = [
        c
        for c in constraints
        if not c.loop or _rms(_residuals(refined, [c])) / c.weight <= max_loop_rms_px
    ]
    dropped = len(constraints) - len(kept)
    if dropped:
        refined, _, after = _solve(poses, kept, fixed, loss_scale_px)
    log.info(
        "pose graph: %d keyframes, %d constraints (%d loop closures dropped), "
        "residual RMS %.2f -> %.2f px",
        len(poses),
        len(kept),
        dropped,
        rms_before,
        _rms(after),
    )
    return Refinement(refined, rms_before, _rms(after), len(kept), dropped)
