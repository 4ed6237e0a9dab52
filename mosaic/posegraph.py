"""Global refinement of frame poses: a pose graph solved by robust least squares.

Unknowns are the homographies `H_node_to_ref` of all nodes (frames) but one (the reference,
fixed). Each constraint is a pair of nodes with corresponding points (matched inliers, or the
points a registration's chosen motion model predicts); its residual is the transfer error of
those points from one node into the other, scaled by the constraint's weight. A soft-L1
loss limits the pull of bad points; a loop closure that still disagrees with the solution by
more than `max_loop_rms_px` is dropped and the graph solved again, so one wrong closure cannot
bend the whole mosaic.

`refine_tilted_poses` (the default on tracked links) models each view instead as a similarity
times a slowly varying tilt, fitted to the links' inlier points: see the section below.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix, diags
from scipy.sparse.linalg import spsolve

from mosaic.geometry import frame_normaliser

log = logging.getLogger(__name__)

MAX_ITERATIONS = 30  # Levenberg-Marquardt steps: bounded time on long videos


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
    pose_model: str = "homography"  # "tilted" or "similarity" from `refine_tilted_poses`
    tilt_gain: float = float("nan")  # the tilt's relative drop of the squared residual RMS


def _matrices(params: np.ndarray) -> np.ndarray:
    """(N, 3, 3) homographies from their 8 free entries (H22 = 1)."""
    return np.concatenate([params, np.ones((len(params), 1))], 1).reshape(-1, 3, 3)


@dataclass(frozen=True)
class _Problem:
    """All constraint points stacked: node of each side, the points, the residual scale."""

    a: np.ndarray  # (M,) node index (row of the params array) of the point's frame
    b: np.ndarray  # (M,) node index of its match's frame
    xy_a: np.ndarray  # (M, 3) homogeneous, normalised coordinates
    xy_b: np.ndarray  # (M, 2) normalised coordinates
    scale: np.ndarray  # (M,) the constraint's weight, times the normalisation back to pixels
    constraint: np.ndarray  # (M,) which constraint each point belongs to


def _problem(
    constraints: list[Constraint], row: dict[int, int], N: np.ndarray, S: float
) -> _Problem:
    """The stacked problem in normalised coordinates (points mapped by N, residuals times S,
    so that they stay in pixels)."""
    sizes = [len(c.xy_a) for c in constraints]
    xy_a = np.concatenate([c.xy_a for c in constraints]).astype(np.float64) * N[0, 0] + N[:2, 2]
    xy_b = np.concatenate([c.xy_b for c in constraints]).astype(np.float64) * N[0, 0] + N[:2, 2]
    return _Problem(
        np.repeat([row[c.a] for c in constraints], sizes),
        np.repeat([row[c.b] for c in constraints], sizes),
        np.hstack([xy_a, np.ones((len(xy_a), 1))]),
        xy_b,
        S * np.repeat([c.weight for c in constraints], sizes),
        np.repeat(np.arange(len(constraints)), sizes),
    )


def _transfer(params: np.ndarray, pb: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """Each point of a mapped a → ref → b (homogeneous, (M, 3)) and inv(P_b) per point."""
    P = _matrices(params)
    B_inv = np.linalg.inv(P)[pb.b]
    u = np.einsum("mij,mj->mi", B_inv, np.einsum("mij,mj->mi", P[pb.a], pb.xy_a))
    return u, B_inv


def _residuals(params: np.ndarray, pb: _Problem) -> np.ndarray:
    """Transfer errors in b's own pixels: a point of a, mapped a → ref → b, against its match
    in b. Measured in image pixels rather than reference pixels, the residual gives the solver
    no reward for shrinking the mosaic away from the fixed frame."""
    u, _ = _transfer(params, pb)
    return ((u[:, :2] / u[:, 2:] - pb.xy_b) * pb.scale[:, None]).ravel()


def _jacobian(params: np.ndarray, pb: _Problem, column: np.ndarray) -> csr_matrix:
    """Sparse derivative of the residuals by the free nodes' parameters (column[node] is the
    node's first column, -1 for the fixed node). With u = inv(P_b) P_a x: du/dP_a[i, j] =
    inv(P_b)[:, i] x_j and du/dP_b[i, j] = -inv(P_b)[:, i] u_j."""
    u, B_inv = _transfer(params, pb)
    m = len(pb.a)
    w = u[:, 2]
    d_pi = np.zeros((m, 2, 3))  # derivative of the projection (u1/u3, u2/u3) by u
    d_pi[:, 0, 0] = d_pi[:, 1, 1] = 1 / w
    d_pi[:, :, 2] = -u[:, :2] / w[:, None] ** 2
    G = np.einsum("mdk,mki->mdi", d_pi, B_inv) * pb.scale[:, None, None]
    Ja = np.einsum("mdi,mj->mdij", G, pb.xy_a).reshape(m, 2, 9)[:, :, :8]
    Jb = -np.einsum("mdi,mj->mdij", G, u).reshape(m, 2, 9)[:, :, :8]
    rows = np.repeat(np.arange(2 * m), 8).reshape(m, 2, 8)
    blocks = []
    for node, J in ((pb.a, Ja), (pb.b, Jb)):
        first = column[node]
        keep = first >= 0
        cols = np.broadcast_to(first[:, None, None] + np.arange(8)[None, None, :], (m, 2, 8))
        blocks.append((rows[keep].ravel(), cols[keep].ravel(), J[keep].ravel()))
    r, c, v = (np.concatenate(parts) for parts in zip(*blocks, strict=True))
    n_cols = 8 * int((column >= 0).sum())
    return coo_matrix((v, (r, c)), shape=(2 * m, n_cols)).tocsr()


def _consistent(
    constraints: list[Constraint], point_residuals: np.ndarray, constraint_of: np.ndarray,
    max_loop_rms_px: float,
) -> list[Constraint]:  # fmt: skip
    """The constraints without the loop closures whose points' RMS transfer error (px, without
    the weights; `point_residuals` weighted, one (x, y) pair per point of `constraint_of`)
    exceeds `max_loop_rms_px`."""
    weights = np.array([c.weight for c in constraints])
    sq = point_residuals.reshape(-1, 2) ** 2
    total = np.bincount(constraint_of, sq.sum(1), minlength=len(weights))
    count = np.bincount(constraint_of, minlength=len(weights))
    rms = np.sqrt(total / np.maximum(count, 1)) / weights
    return [c for c, r in zip(constraints, rms, strict=True) if not c.loop or r <= max_loop_rms_px]


def _solve(
    poses: dict[int, np.ndarray],
    constraints: list[Constraint],
    fixed: int,
    loss_scale_px: float,
) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray, _Problem]:
    """One robust least-squares solve: refined poses, residuals before and after."""
    nodes = sorted(poses)
    # Conditioning: points centred and scaled to ~1, poses conjugated accordingly.
    xy = np.concatenate([c.xy_a for c in constraints])
    S = max(float(xy.std()), 1.0)
    N = np.array([[1 / S, 0, -xy[:, 0].mean() / S], [0, 1 / S, -xy[:, 1].mean() / S], [0, 0, 1]])
    N_inv = np.linalg.inv(N)
    normalised = [N @ poses[k] @ N_inv for k in nodes]
    P0 = np.stack([(H / H[2, 2]).ravel()[:8] for H in normalised])
    pb = _problem(constraints, {k: i for i, k in enumerate(nodes)}, N, S)
    free = np.array([k != fixed for k in nodes])
    column = np.full(len(nodes), -1)
    column[free] = 8 * np.arange(int(free.sum()))

    def full(x: np.ndarray) -> np.ndarray:
        params = P0.copy()
        params[free] = x.reshape(-1, 8)
        return params

    x0 = P0[free].ravel()
    before = _residuals(P0, pb)
    x = _levenberg_marquardt(
        lambda x: _residuals(full(x), pb),
        lambda x: _jacobian(full(x), pb, column),
        x0,
        loss_scale_px,
    )
    params = full(x)
    refined = {k: N_inv @ np.append(params[i], 1.0).reshape(3, 3) @ N for i, k in enumerate(nodes)}
    refined = {k: H / H[2, 2] for k, H in refined.items()}
    refined[fixed] = poses[fixed]
    return refined, before, _residuals(params, pb), pb


def _robust_weights(r: np.ndarray, scale: float) -> np.ndarray:
    """Soft-L1 weights of each residual pair (one point): 1 / sqrt(1 + (|r| / scale)^2)."""
    sq = (r.reshape(-1, 2) ** 2).sum(1) / scale**2
    return np.repeat(1.0 / np.sqrt(1.0 + sq), 2)


def _robust_cost(r: np.ndarray, scale: float) -> float:
    sq = (r.reshape(-1, 2) ** 2).sum(1) / scale**2
    return float(scale**2 * np.sum(2.0 * (np.sqrt(1.0 + sq) - 1.0)))


def _levenberg_marquardt(
    fun: Callable[[np.ndarray], np.ndarray],
    jac: Callable[[np.ndarray], csr_matrix],
    x: np.ndarray,
    scale: float,
) -> np.ndarray:
    """Robust (soft-L1, re-weighted) Levenberg-Marquardt with sparse normal equations: the
    graph is a chain with a few shortcuts, so a sparse direct solve is fast and exact."""
    r = fun(x)
    cost = _robust_cost(r, scale)
    damping = 1e-4
    for _ in range(MAX_ITERATIONS):
        J = jac(x)
        w = _robust_weights(r, scale)
        Jw = J.multiply(w[:, None]).tocsr()
        A = (J.T @ Jw).tocsc()
        g = Jw.T @ r
        diag = A.diagonal()
        improved = False
        while damping < 1e10:
            D = diags(damping * np.maximum(diag, 1e-9) + 1e-12)
            try:
                step = spsolve((A + D).tocsc(), -g)
            except RuntimeError:
                step = np.full_like(x, np.nan)
            if np.isfinite(step).all():
                r_new = fun(x + step)
                cost_new = _robust_cost(r_new, scale)
                if np.isfinite(cost_new) and cost_new < cost:
                    improved = True
                    break
            damping *= 10
        if not improved:
            break
        x, r, gain = x + step, r_new, cost - cost_new
        cost, damping = cost_new, max(damping / 10, 1e-9)
        if gain < 1e-9 * max(cost, 1e-12):
            break
    return x


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
    refined, before, after, pb = _solve(poses, constraints, fixed, loss_scale_px)
    rms_before = _rms(before)
    kept = _consistent(constraints, after, pb.constraint, max_loop_rms_px)
    dropped = len(constraints) - len(kept)
    if dropped:
        refined, _, after, _ = _solve(poses, kept, fixed, loss_scale_px)
    log.info(
        "pose graph: %d poses, %d constraints (%d loop closures dropped), "
        "residual RMS %.2f -> %.2f px",
        len(poses),
        len(kept),
        dropped,
        rms_before,
        _rms(after),
    )
    return Refinement(refined, rms_before, _rms(after), len(kept), dropped)


# -- poses with a slowly varying tilt ------------------------------------------------------
# A view of the retina is a similarity of the mosaic plane times a perspective in the frame's
# own coordinates (the camera's tilt against the retina, which changes slowly along a video):
# H_frame_to_plane = S P, P = [[1, 0, 0], [0, 1, 0], [p, q, 1]] in frame-centred coordinates
# of unit half-diagonal. Between two views H = P_b^-1 S_b^-1 S_a P_a is not a similarity, and
# a similarity fitted to each link is biased by the tilt in a way that adds up along the path;
# homographies fitted per link are too noisy where the matches sit on one side. Here the tilt
# is a per-frame state with a smoothness prior, fitted jointly with the similarities to all
# links' inlier points, so each frame's tilt is set by many links at once.

# per node: the similarity (a, b, tx, ty), S = [[1 + a, -b, tx], [b, 1 + a, ty]]; the tilt (p, q)
TILT_PARAMS = 6
# The tilt is kept only where it lowers the squared RMS of the links' point residuals by this
# share: freeing two parameters per frame always lowers it a little (untilted tuning videos:
# 0.008-0.028; tilted ones mostly 0.018-0.41; docs/pipeline.md).
TILT_MIN_GAIN = 0.016


def _tilted_matrices(params: np.ndarray) -> np.ndarray:
    """(N, 3, 3) S P of each node from its six parameters."""
    a, b, tx, ty, p, q = params.T
    S = np.zeros((len(params), 3, 3))
    S[:, 0, 0] = S[:, 1, 1] = 1 + a
    S[:, 0, 1], S[:, 1, 0] = -b, b
    S[:, 0, 2], S[:, 1, 2], S[:, 2, 2] = tx, ty, 1.0
    P = np.tile(np.eye(3), (len(params), 1, 1))
    P[:, 2, 0], P[:, 2, 1] = p, q
    return S @ P


def _tilted_point_residuals(
    pa: np.ndarray, pb: np.ndarray, xy_a: np.ndarray, xy_b: np.ndarray
) -> np.ndarray:
    """(M, 2) transfer errors of points a → plane → b (P_b^-1 S_b^-1 S_a P_a), the nodes'
    parameters given per point; written out element by element (a batched 3x3 product per
    point is ten times slower)."""
    x, y = xy_a[:, 0], xy_a[:, 1]
    w = pa[:, 4] * x + pa[:, 5] * y + 1.0  # P_a
    c, d = 1.0 + pa[:, 0], pa[:, 1]  # S_a
    X, Y = c * x - d * y + pa[:, 2] * w, d * x + c * y + pa[:, 3] * w
    c, d = 1.0 + pb[:, 0], pb[:, 1]  # S_b^-1, up to scale
    X, Y = X - pb[:, 2] * w, Y - pb[:, 3] * w
    X, Y, w = c * X + d * Y, c * Y - d * X, (c * c + d * d) * w
    w = w - pb[:, 4] * X - pb[:, 5] * Y  # P_b^-1
    return np.stack([X / w, Y / w], 1) - xy_b


def _tilted_point_derivatives(pa: np.ndarray, pb: np.ndarray, xy_a: np.ndarray) -> np.ndarray:
    """(M, 2, 12) derivatives of `_tilted_point_residuals` by node a's six parameters, then
    node b's, per point (the same chain of products, differentiated step by step)."""
    x, y = xy_a[:, 0], xy_a[:, 1]
    w0 = pa[:, 4] * x + pa[:, 5] * y + 1.0
    c0, d0 = 1.0 + pa[:, 0], pa[:, 1]
    X2 = c0 * x - d0 * y + (pa[:, 2] - pb[:, 2]) * w0
    Y2 = d0 * x + c0 * y + (pa[:, 3] - pb[:, 3]) * w0
    c1, d1, p1, q1 = 1.0 + pb[:, 0], pb[:, 1], pb[:, 4], pb[:, 5]
    X, Y = c1 * X2 + d1 * Y2, c1 * Y2 - d1 * X2
    n2 = c1 * c1 + d1 * d1
    W = n2 * w0 - p1 * X - q1 * Y
    zero = np.zeros_like(x)
    # d(X2, Y2) and d(W0) by node a's parameters; node b's act after S_b^-1 or on W directly
    dX2 = [x, -y, w0, zero, (pa[:, 2] - pb[:, 2]) * x, (pa[:, 2] - pb[:, 2]) * y]
    dY2 = [y, x, zero, w0, (pa[:, 3] - pb[:, 3]) * x, (pa[:, 3] - pb[:, 3]) * y]
    dW0 = [zero, zero, zero, zero, n2 * x, n2 * y]
    dX = [c1 * dx + d1 * dy for dx, dy in zip(dX2, dY2, strict=True)]
    dY = [c1 * dy - d1 * dx for dx, dy in zip(dX2, dY2, strict=True)]
    # node b: c1, d1 (scale and sign of S_b^-1), tx1, ty1 (through X2, Y2), p1, q1 (on W)
    dX += [X2, Y2, -c1 * w0, -d1 * w0, zero, zero]
    dY += [Y2, -X2, d1 * w0, -c1 * w0, zero, zero]
    dW0 += [2 * c1 * w0, 2 * d1 * w0, zero, zero, zero, zero]
    out = np.empty((len(x), 2, 2 * TILT_PARAMS))
    for k in range(2 * TILT_PARAMS):
        dW = dW0[k] - p1 * dX[k] - q1 * dY[k]
        if k == 10:
            dW = dW - X
        elif k == 11:
            dW = dW - Y
        out[:, 0, k] = (dX[k] - X / W * dW) / W
        out[:, 1, k] = (dY[k] - Y / W * dW) / W
    return out


@dataclass(frozen=True)
class _TiltedProblem:
    a: np.ndarray  # (M,) node row of each point's frame
    b: np.ndarray  # (M,) node row of its match's frame
    xy_a: np.ndarray  # (M, 2) normalised
    xy_b: np.ndarray  # (M, 2) normalised
    scale: np.ndarray  # (M,) weight times the normalisation back to pixels
    constraint: np.ndarray  # (M,) constraint of each point
    prev: np.ndarray  # (K,) node rows of consecutive frames' pairs (tilt smoothness) ...
    next: np.ndarray  # (K,) ... and their partners
    smooth: np.ndarray  # (K,) weight of each pair's tilt difference (normalised units -> sd)
    prior: float  # weight of each tilt's absolute value


def _tilted_residuals(params: np.ndarray, pb: _TiltedProblem) -> np.ndarray:
    r = _tilted_point_residuals(params[pb.a], params[pb.b], pb.xy_a, pb.xy_b)
    smooth = (params[pb.next, 4:] - params[pb.prev, 4:]) * pb.smooth[:, None]
    return np.concatenate(
        [(r * pb.scale[:, None]).ravel(), smooth.ravel(), (params[:, 4:] * pb.prior).ravel()]
    )


def _tilted_jacobian(params: np.ndarray, pb: _TiltedProblem, column: np.ndarray) -> csr_matrix:
    """Sparse Jacobian: each point's residual depends on its two nodes only; the priors are
    linear."""
    m = len(pb.a)
    pa, pbb = params[pb.a], params[pb.b]
    rows, cols, vals = [], [], []
    point_rows = np.arange(2 * m).reshape(m, 2)
    deriv = _tilted_point_derivatives(pa, pbb, pb.xy_a) * pb.scale[:, None, None]
    for side, nodes in ((0, pb.a), (1, pb.b)):
        for k in range(TILT_PARAMS):
            col = column[nodes, k]
            keep = col >= 0
            if not keep.any():
                continue
            rows.append(point_rows[keep].ravel())
            cols.append(np.repeat(col[keep], 2))
            vals.append(deriv[keep, :, side * TILT_PARAMS + k].ravel())
    base = 2 * m
    for j in range(2):  # smoothness rows: (tilt_next - tilt_prev) * w
        r = base + 2 * np.arange(len(pb.prev)) + j
        for nodes, sign in ((pb.next, 1.0), (pb.prev, -1.0)):
            col = column[nodes, 4 + j]
            keep = col >= 0
            rows.append(r[keep])
            cols.append(col[keep])
            vals.append(sign * pb.smooth[keep])
    base += 2 * len(pb.prev)
    n = len(params)
    for j in range(2):
        r = base + 2 * np.arange(n) + j
        col = column[:, 4 + j]
        keep = col >= 0
        rows.append(r[keep])
        cols.append(col[keep])
        vals.append(np.full(int(keep.sum()), pb.prior))
    n_rows = base + 2 * n
    n_cols = int(column.max()) + 1
    r, c, v = (np.concatenate(x) for x in (rows, cols, vals))
    return coo_matrix((v, (r, c)), shape=(n_rows, n_cols)).tocsr()


def _similarity_params(G: np.ndarray) -> np.ndarray:
    """(N, 4) (a, b, tx, ty) of the similarity nearest each normalised homography of (N, 3, 3),
    least squares on a centred 3x3 grid: in complex numbers, (1 + a + ib) = sum(conj(z) w) /
    sum(|z|^2) and t = mean(w) for grid points z mapped to w."""
    g = np.stack(np.meshgrid(np.linspace(-0.7, 0.7, 3), np.linspace(-0.7, 0.7, 3)), -1)
    z = g.reshape(-1, 2) @ np.array([1.0, 1j])
    p = np.einsum("nij,kj->nki", G, np.hstack([g.reshape(-1, 2), np.ones((9, 1))]))
    w = (p[..., :2] / p[..., 2:]) @ np.array([1.0, 1j])
    t = w.mean(1)
    m = (np.conj(z) * w).sum(1) / (np.abs(z) ** 2).sum()
    return np.stack([m.real - 1, m.imag, t.real, t.imag], 1)


def _numbered(free: np.ndarray) -> np.ndarray:
    """Each free parameter's column in the solve, -1 for those held."""
    column = np.full(free.shape, -1)
    column[free] = np.arange(int(free.sum()))
    return column


class _TiltedGraph:
    """One video's poses as tilted-view parameters in frame-centred coordinates of unit
    half-diagonal, and the solves of `refine_tilted_poses` over them."""

    def __init__(
        self,
        poses: dict[int, np.ndarray],
        fixed: int,
        shape: tuple[int, int],
        tilt_step_px: float,
        tilt_prior_px: float,
        loss_scale_px: float,
    ):
        self.nodes = sorted(poses)
        self.row = {k: i for i, k in enumerate(self.nodes)}
        self.T = frame_normaliser(shape)
        self.s = self.T[0, 0]
        self.loss_scale_px = loss_scale_px
        self.tilt_prior_px = tilt_prior_px
        T_inv = np.linalg.inv(self.T)
        H_fixed_inv = np.linalg.inv(poses[fixed])
        stacked = np.stack([poses[k] for k in self.nodes])
        self.P0 = np.zeros((len(self.nodes), TILT_PARAMS))
        self.P0[:, :4] = _similarity_params(self.T @ H_fixed_inv @ stacked @ T_inv)
        self.P0[self.row[fixed], :4] = 0.0
        free = np.ones((len(self.nodes), TILT_PARAMS), bool)
        free[self.row[fixed], :4] = False  # the reference's similarity is the identity
        self.tilted_columns = _numbered(free)
        self.untilted_columns = _numbered(free & (np.arange(TILT_PARAMS) < 4))  # tilts held at 0
        gaps = np.diff(np.array(self.nodes, dtype=np.float64))
        # the tilts' residuals in the points' units (px / sd): a tilt change dp moves the
        # corner by about dp / s px
        self.smooth = 1.0 / (tilt_step_px * self.s * np.sqrt(gaps))

    def problem(self, kept: list[Constraint]) -> _TiltedProblem:
        s, T, row = self.s, self.T, self.row
        sizes = [len(c.xy_a) for c in kept]
        xy_a = np.concatenate([c.xy_a for c in kept]).astype(np.float64) * s + T[:2, 2]
        xy_b = np.concatenate([c.xy_b for c in kept]).astype(np.float64) * s + T[:2, 2]
        return _TiltedProblem(
            np.repeat([row[c.a] for c in kept], sizes),
            np.repeat([row[c.b] for c in kept], sizes),
            xy_a,
            xy_b,
            np.repeat([c.weight for c in kept], sizes) / s,
            np.repeat(np.arange(len(kept)), sizes),
            np.arange(len(self.nodes) - 1),
            np.arange(1, len(self.nodes)),
            self.smooth,
            1.0 / (self.tilt_prior_px * s),
        )

    def solve(
        self, kept: list[Constraint], column: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, _TiltedProblem]:
        """Parameters, residuals before and after, and the problem solved."""
        pb = self.problem(kept)
        free = column >= 0
        P0 = self.P0

        def full(x: np.ndarray) -> np.ndarray:
            params = P0.copy()
            params[free] = x
            return params

        before = _tilted_residuals(P0, pb)
        x = _levenberg_marquardt(
            lambda x: _tilted_residuals(full(x), pb),
            lambda x: _tilted_jacobian(full(x), pb, column),
            P0[free],
            self.loss_scale_px,
        )
        return full(x), before, _tilted_residuals(full(x), pb), pb

    def fit(
        self, constraints: list[Constraint], column: np.ndarray, max_loop_rms_px: float
    ) -> tuple[np.ndarray, float, float, int]:
        """Parameters, residual RMS (px) of the points before and after, and the number of
        constraints kept (loop closures that disagree dropped, solved again)."""
        params, before, after, pb = self.solve(constraints, column)
        n_points = 2 * len(pb.a)
        kept = _consistent(constraints, after[:n_points], pb.constraint, max_loop_rms_px)
        if len(kept) < len(constraints):
            params, _, after, pb = self.solve(kept, column)
        return params, _rms(before[:n_points]), _rms(after[: 2 * len(pb.a)]), len(kept)

    def poses(
        self, params: np.ndarray, poses: dict[int, np.ndarray], fixed: int
    ) -> dict[int, np.ndarray]:
        """H_frame_to_ref of every node from the parameters, the reference's kept as given."""
        M = _tilted_matrices(params)
        to_ref = np.linalg.inv(M[self.row[fixed]])
        T, T_inv = self.T, np.linalg.inv(self.T)
        refined = {}
        for k in self.nodes:
            H = poses[fixed] @ T_inv @ to_ref @ M[self.row[k]] @ T
            refined[k] = H / H[2, 2]
        refined[fixed] = poses[fixed]
        return refined


def refine_tilted_poses(
    poses: dict[int, np.ndarray],
    constraints: list[Constraint],
    fixed: int,
    shape: tuple[int, int],
    tilt_step_px: float = 0.4,
    tilt_prior_px: float = 30.0,
    loss_scale_px: float = 2.0,
    max_loop_rms_px: float = 5.0,
) -> Refinement:
    """Poses H_frame_to_ref = P_fixed^-1 S P (see above) consistent with the constraints; the
    tilt's effect at the frame corner changes by about `tilt_step_px` per frame and stays
    within about `tilt_prior_px`. `fixed` is the reference (identity). The tilted views are
    kept where they lower the residual by TILT_MIN_GAIN over similarities alone."""
    constraints = [c for c in constraints if c.a in poses and c.b in poses and len(c.xy_a)]
    if not constraints or len(poses) < 2:
        return Refinement(dict(poses), 0.0, 0.0, len(constraints))
    graph = _TiltedGraph(poses, fixed, shape, tilt_step_px, tilt_prior_px, loss_scale_px)
    tilted = graph.fit(constraints, graph.tilted_columns, max_loop_rms_px)
    similar = graph.fit(constraints, graph.untilted_columns, max_loop_rms_px)
    gain = 1.0 - tilted[2] ** 2 / max(similar[2] ** 2, 1e-12)
    model = "tilted" if gain >= TILT_MIN_GAIN else "similarity"
    params, rms_before, rms_after, n_kept = tilted if model == "tilted" else similar
    refined = graph.poses(params, poses, fixed)
    log.info(
        "pose graph (%s views, tilt gain %.3f): %d poses, %d constraints (%d loop closures "
        "dropped), residual RMS %.2f -> %.2f px",
        model,
        gain,
        len(poses),
        n_kept,
        len(constraints) - n_kept,
        rms_before,
        rms_after,
    )
    dropped = len(constraints) - n_kept
    return Refinement(refined, rms_before, rms_after, n_kept, dropped, model, gain)
