"""Robust motion between two frames, the choice of motion model, and the paper's failure rules.

`estimate_homography` is the paper's step: a RANSAC homography. `estimate_motion` is the
pipeline's: on the same RANSAC consensus it fits a hierarchy of models (translation, similarity,
affine, homography) and keeps the one expected to place the frame's corners best. A homography
fitted to inliers that sit on one side of the frame (vessels on one side, a dark or featureless
region on the other) extrapolates its perspective terms into the empty side; a similarity fitted
to the same points does not. The criterion is the expected squared corner error of each model:
its variance at the corners (the least-squares covariance, which grows where no inlier is) plus
its bias there. A model whose residuals are not significantly worse than the homography's (a
nested chi-square test) has none; otherwise the bias is how far it departs from the homography
at the corners, less what the two models' variances explain (Mallows' Cp where the error is
measured). Parameters are charged by the test, coverage is rewarded by the variances. The
chosen model is then refined by re-weighted least squares on all matches within the threshold.

Last, with `perspective_prior` > 0, a model below the homography is relaxed into a homography
whose departure from that model has a Gaussian prior (a MAP fit): where the matches span the
frame they pull the perspective terms to the truth, where they sit on one side the prior keeps
the simpler model's extrapolation. Consecutive views of a curved retina differ by a few pixels
of perspective at the corners; a similarity that ignores them biases each step's scale the
same way, and those biases add up along the video.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from mosaic.config import RegistrationConfig
from mosaic.features import failure_reason
from mosaic.geometry import (
    apply_homography,
    apply_quadratic,
    frame_corners,
    frame_normaliser,
    huber_weights,
    normalised,
    quadratic_terms,
    reweighted_rounds,
)

METHODS = {
    "ransac": cv2.RANSAC,
    "usac_default": cv2.USAC_DEFAULT,
    "usac_magsac": cv2.USAC_MAGSAC,
    "usac_accurate": cv2.USAC_ACCURATE,
    "usac_fast": cv2.USAC_FAST,
}
MODELS = ("translation", "similarity", "affine", "homography")  # nested, fewest parameters first
N_PARAMS = {"translation": 2, "similarity": 4, "affine": 6, "homography": 8}
REFINE_ROUNDS = 3  # re-weighted least-squares rounds of the chosen model
# Gauss-Newton stops after a step this small (normalised units, ~0.004 px at 660 px); the
# next step would be ~1e-8: 2-3 steps instead of 5 (measured on the bench video)
GN_STEP_TOL = 1e-5
ROBUST_ROUNDS = 4  # `robust_fit`'s re-weighted rounds per model
ROBUST_HUBER_DIVISOR = 3  # ... with Huber's k at the residual bound over this
ROBUST_MIN_POINTS = 8  # ... stopping where fewer matches lie within the bound
HUBER_PX = 1.0  # residual beyond which a match's weight falls as 1/residual
# A simpler model whose extra residual (in units of the richer model's noise) stays under this
# bound of its chi-square law (k + 5 sqrt(2k), beyond the 0.999 quantile for k = 2-6) is
# adequate: it has no bias. Matches' errors are not independent, so be slow to call a bias real.
ADEQUATE_Z = 5.0


@dataclass(frozen=True)
class Registration:
    """Outcome of registering the current frame to a reference frame."""

    H_moving_to_fixed: np.ndarray | None  # 3x3 float64, None when failed
    n_matches: int
    n_inliers: int
    inliers: np.ndarray  # (n_matches,) bool
    reproj_error_px: float  # mean transfer error of the inliers; nan when failed
    reason: str | None  # why it failed; None when registered
    model: str = "homography"  # the motion model of H_moving_to_fixed
    coverage: float = float("nan")  # share of the current frame inside the inliers' hull
    corner_sd_px: float = float("nan")  # expected corner error of the chosen model (1 sigma)
    # pairs (`pairs.register_pair`): the quadratic transform (2x6, `apply_quadratic`) when
    # the model is "quadratic", each image's working scale, the refinement's levels, and which
    # image was inverted so that both show dark vessels (`[preprocess] vessel_polarity`)
    Q_moving_to_fixed: np.ndarray | None = None
    working_scales: tuple[float, float] | None = None  # (current, reference)
    refined_levels: int = 0
    inverted: tuple[bool, bool] = (False, False)  # (current, reference) inverted: one polarity
    points: tuple[np.ndarray, np.ndarray] | None = None  # inlier (cur, prev) points
    # how much a homography explains beyond the model (`perspective_evidence`); nan: not asked
    perspective_evidence: float = float("nan")
    # video tracking: how far the windows' alignment moved the fit at the frame's corners
    # (mean px) before the points were tracked from it (`tracking._tracked`); nan: not aligned
    aligned_px: float = float("nan")

    @property
    def ok(self) -> bool:
        return self.reason is None


def _failed(n: int, inliers: np.ndarray, reason: str, model: str = "homography") -> Registration:
    return Registration(None, n, int(inliers.sum()), inliers, float("nan"), reason, model)


def transfer_errors(H: np.ndarray, xy_cur: np.ndarray, xy_prev: np.ndarray) -> np.ndarray:
    """Distance (px) between each current point mapped by `H` and its match."""
    x, y = xy_cur[:, 0].astype(np.float64), xy_cur[:, 1].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
        dx = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w - xy_prev[:, 0]
        dy = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w - xy_prev[:, 1]
        err = np.sqrt(dx * dx + dy * dy)
    return np.where(np.isfinite(err), err, np.inf)


def _checked(
    H: np.ndarray | None,
    inliers: np.ndarray,
    xy_cur: np.ndarray,
    xy_prev: np.ndarray,
    config: RegistrationConfig,
    model: str = "homography",
    **extra: float,
) -> Registration:
    """The paper's failure rules and `min_inliers` on an estimate; its mean inlier error."""
    n, n_inliers = len(xy_cur), int(inliers.sum())
    reason = failure_reason(H, n)
    if reason is None and n_inliers < config.min_inliers:
        reason = f"too few inliers ({n_inliers} < {config.min_inliers})"
    if reason is not None:
        return _failed(n, inliers, reason, model)
    assert H is not None
    H = H / H[2, 2]
    err = transfer_errors(H, xy_cur[inliers], xy_prev[inliers])
    return Registration(
        H,
        n,
        n_inliers,
        inliers,
        float(err.mean()),
        None,
        model,
        points=(xy_cur[inliers], xy_prev[inliers]),
        **extra,
    )


def estimate_homography(
    xy_cur: np.ndarray, xy_prev: np.ndarray, config: RegistrationConfig
) -> Registration:
    """The paper's RANSAC homography mapping matched points of the current frame onto the
    previous one (the pair evaluation's protocol)."""
    n = len(xy_cur)
    no_inliers = np.zeros(n, bool)
    reason = failure_reason(None, n) if n < 4 else None
    if reason is not None:
        return _failed(n, no_inliers, reason)
    H, mask = cv2.findHomography(
        xy_cur.astype(np.float32),
        xy_prev.astype(np.float32),
        METHODS[config.method],
        config.reproj_threshold_px,
        maxIters=config.max_iters,
        confidence=config.confidence,
    )
    inliers = mask.ravel().astype(bool) if mask is not None else no_inliers
    return _checked(H, inliers, xy_cur, xy_prev, config)


def _linear_consensus(
    xy_cur: np.ndarray, xy_prev: np.ndarray, config: RegistrationConfig, model: str
) -> Registration:
    """RANSAC consensus of a similarity (translation, similarity) or an affine model: fewer
    points per sample than a homography, so far fewer iterations for the same confidence."""
    n = len(xy_cur)
    no_inliers = np.zeros(n, bool)
    reason = failure_reason(None, n) if n < 4 else None
    if reason is not None:
        return _failed(n, no_inliers, reason, model)
    estimate = cv2.estimateAffine2D if model == "affine" else cv2.estimateAffinePartial2D
    A, mask = estimate(
        xy_cur.astype(np.float32),
        xy_prev.astype(np.float32),
        method=cv2.RANSAC,
        ransacReprojThreshold=config.reproj_threshold_px,
        maxIters=config.max_iters,
        confidence=config.confidence,
        refineIters=0,
    )
    inliers = mask.ravel().astype(bool) if mask is not None else no_inliers
    H = None if A is None else np.vstack([A, [0.0, 0.0, 1.0]])
    return _checked(H, inliers, xy_cur, xy_prev, config, model)


# -- the model hierarchy ---------------------------------------------------------------------


def _design(model: str, xy: np.ndarray) -> np.ndarray:
    """(N, 2, k) derivative of the mapped points by the parameters of a linear model."""
    x, y = xy[:, 0], xy[:, 1]
    k = N_PARAMS[model]
    A = np.zeros((len(xy), 2, k))
    if model == "translation":
        A[:, 0, 0] = A[:, 1, 1] = 1.0
    elif model == "similarity":  # x' = a x - b y + tx, y' = b x + a y + ty
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = x, -y, 1.0
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 3] = y, x, 1.0
    else:  # affine
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = x, y, 1.0
        A[:, 1, 3], A[:, 1, 4], A[:, 1, 5] = x, y, 1.0
    return A


def _linear_matrix(model: str, p: np.ndarray) -> np.ndarray:
    if model == "translation":
        return np.array([[1.0, 0, p[0]], [0, 1.0, p[1]], [0, 0, 1.0]])
    if model == "similarity":
        a, b, tx, ty = p
        return np.array([[a, -b, tx], [b, a, ty], [0, 0, 1.0]])
    return np.vstack([p.reshape(2, 3), [0, 0, 1.0]])


def _homography_jacobian(H: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mapped points (N, 2) and their derivative by the 8 free entries of H (N, 2, 8)."""
    x, y = xy[:, 0], xy[:, 1]
    u = H[0, 0] * x + H[0, 1] * y + H[0, 2]
    v = H[1, 0] * x + H[1, 1] * y + H[1, 2]
    w = H[2, 0] * x + H[2, 1] * y + 1.0
    px, py = u / w, v / w
    J = np.zeros((len(x), 2, 8))  # filled in place: this runs in every Gauss-Newton step
    J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = x / w, y / w, 1 / w
    J[:, 1, 3:6] = J[:, 0, 0:3]
    J[:, 0, 6], J[:, 0, 7] = -px * x / w, -px * y / w
    J[:, 1, 6], J[:, 1, 7] = -py * x / w, -py * y / w
    return np.stack([px, py], 1), J


def _departure(model: str) -> tuple[np.ndarray, np.ndarray]:
    """(D, d): the homography's 8 free entries p lie on `model`'s manifold where D p = d."""
    rows: list[tuple[dict[int, float], float]] = [({6: 1.0}, 0.0), ({7: 1.0}, 0.0)]
    if model == "similarity":  # h00 = h11, h01 = -h10
        rows += [({0: 0.5, 4: -0.5}, 0.0), ({1: 0.5, 3: 0.5}, 0.0)]
    elif model == "translation":  # the linear part is the identity
        rows += [({0: 1.0}, 1.0), ({1: 1.0}, 0.0), ({3: 1.0}, 0.0), ({4: 1.0}, 1.0)]
    D = np.zeros((len(rows), 8))
    for i, (coefficients, _) in enumerate(rows):
        for j, c in coefficients.items():
            D[i, j] = c
    return D, np.array([target for _, target in rows])


@dataclass(frozen=True)
class _Fit:
    """A model fitted by weighted least squares in normalised coordinates."""

    model: str
    M: np.ndarray  # 3x3, normalised current -> normalised reference
    JtJ_inv: np.ndarray  # (k, k) unscaled parameter covariance
    rss: float  # weighted sum of squared residuals (normalised units)

    def predict(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mapped points and the unscaled variance (trace of the 2x2 covariance) at each."""
        if self.model == "homography":
            mapped, A = _homography_jacobian(self.M, q)
        else:
            A = _design(self.model, q)
            mapped = q @ self.M[:2, :2].T + self.M[:2, 2]
        var = np.einsum("nik,kl,nil->n", A, self.JtJ_inv, A)
        return mapped, var


def _fit(model: str, a: np.ndarray, b: np.ndarray, w: np.ndarray, M0: np.ndarray) -> _Fit | None:
    """Weighted least-squares fit of `model` mapping points a onto b (normalised units); the
    homography by Gauss-Newton from M0."""
    if model == "homography":
        return _fit_homography(a, b, w, M0)
    sw = np.sqrt(w)[:, None, None]
    A = _design(model, a) * sw
    k = A.shape[2]
    target = b - a if model == "translation" else b  # x' = x + t
    A2, rhs = A.reshape(-1, k), (target[:, :, None] * sw).reshape(-1)
    try:  # normal equations: normalised coordinates keep them well conditioned
        JtJ_inv = np.linalg.inv(A2.T @ A2)
    except np.linalg.LinAlgError:
        return None
    p = JtJ_inv @ (A2.T @ rhs)
    M = _linear_matrix(model, p)
    r = rhs - A2 @ p
    if not np.isfinite(M).all() or not np.isfinite(JtJ_inv).all():
        return None
    return _Fit(model, M, JtJ_inv, float(r @ r))


def _fit_homography(
    a: np.ndarray,
    b: np.ndarray,
    w: np.ndarray,
    M0: np.ndarray,
    prior: tuple[np.ndarray, np.ndarray, float] | None = None,
) -> _Fit | None:
    """Homography by Gauss-Newton from M0 on the weighted transfer error; with `prior` (D, d,
    lam) plus lam |D p - d|^2 on its 8 free entries p (a MAP fit: lam in units of the noise)."""
    D, d, lam = prior if prior is not None else (np.zeros((0, 8)), np.zeros(0), 0.0)
    P = lam * D.T @ D  # the prior's information
    sw = np.sqrt(w)[:, None, None]
    M = M0 / M0[2, 2]
    for _ in range(5):
        mapped, J = _homography_jacobian(M, a)
        r = ((b - mapped)[:, :, None] * sw).reshape(-1)
        J2 = (J * sw).reshape(-1, 8)
        gradient = J2.T @ r - lam * D.T @ (D @ M.ravel()[:8] - d)
        try:
            step = np.linalg.solve(J2.T @ J2 + P + 1e-9 * np.eye(8), gradient)
        except np.linalg.LinAlgError:
            return None
        M = M + np.append(step, 0.0).reshape(3, 3)
        if np.abs(step).max() < GN_STEP_TOL:
            break
    mapped, J = _homography_jacobian(M, a)
    r = ((b - mapped)[:, :, None] * sw).reshape(-1)
    J2 = (J * sw).reshape(-1, 8)
    try:
        cov = np.linalg.inv(J2.T @ J2 + P)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(M).all() or not np.isfinite(cov).all():
        return None
    return _Fit("homography", M, cov, float(r @ r))


def _fit_with_prior(
    base: _Fit, a: np.ndarray, b: np.ndarray, w: np.ndarray, sigma2: float, prior_sd: float
) -> _Fit | None:
    """MAP homography: weighted least squares of the transfer error plus a Gaussian prior of
    sd `prior_sd` (normalised units) on the departure from `base`'s model; from `base`."""
    D, d = _departure(base.model)
    return _fit_homography(a, b, w, base.M, (D, d, sigma2 / prior_sd**2))


def perspective_evidence(fit: _Fit, a: np.ndarray, b: np.ndarray, w: np.ndarray) -> float:
    """How much better a homography explains the points than `fit`'s model: the residuals'
    drop per extra parameter, in units of the points' noise (from the homography's fit). About
    1 where the model is right (1.3-1.7 measured: the errors are not quite independent), 4-6
    between views with perspective (the tilted realistic videos, 8-20 frames apart)."""
    top = _fit_homography(a, b, w, fit.M)
    if top is None:
        return float("nan")
    extra = N_PARAMS["homography"] - N_PARAMS[fit.model]
    sigma2 = max(top.rss / max(2 * len(a) - 8, 1), 1e-12)
    return float((fit.rss - top.rss) / sigma2 / extra)


def perspective_needed(evidence: float, model: str) -> bool:
    """One registration's chi-square test: does the homography's gain exceed the noise's?"""
    extra = N_PARAMS["homography"] - N_PARAMS[model]
    return evidence * extra >= extra + ADEQUATE_Z * np.sqrt(2 * extra)


def select_model(
    a: np.ndarray,
    b: np.ndarray,
    w: np.ndarray,
    M_h: np.ndarray,
    corners: np.ndarray,
    inflation: float = 1.0,
) -> tuple[_Fit, float]:
    """The model of the hierarchy with the least expected squared corner error (normalised
    points a → b, weights w, the RANSAC homography M_h as a start); also its corner sd."""
    fits = {m: _fit(m, a, b, w, M_h) for m in MODELS}
    top = fits["homography"]
    ok = {m: f for m, f in fits.items() if f is not None}
    if top is None:  # degenerate for a homography: fall back on the richest linear model
        richest = [m for m in MODELS if m in ok]
        if not richest:
            raise np.linalg.LinAlgError("no motion model could be fitted")
        f = ok[richest[-1]]
        return f, float("nan")
    dof = max(2 * len(a) - 8, 1)
    sigma2 = max(top.rss / dof, 1e-12) * inflation  # noise of a point, from the most general model
    top_xy, top_var = top.predict(corners)
    best, best_cost = top, float(np.mean(sigma2 * top_var))
    for m in MODELS[:-1]:
        f = ok.get(m)
        if f is None:
            continue
        xy, var = f.predict(corners)
        extra = N_PARAMS["homography"] - N_PARAMS[m]
        adequate = (f.rss - top.rss) / sigma2 < extra + ADEQUATE_Z * np.sqrt(2 * extra)
        bias2 = 0.0
        if not adequate:  # Mallows' Cp at the corners: the departure less the variances' part
            diff2 = np.sum((xy - top_xy) ** 2, axis=1)
            bias2 = np.maximum(diff2 - sigma2 * (top_var - var), 0.0)
        cost = float(np.mean(bias2 + sigma2 * var))
        if cost < best_cost:
            best, best_cost = f, cost
    return best, float(np.sqrt(best_cost))


CELL_PX = 48.0  # matches closer than this share their localisation error (descriptor support)


def _inflation(a: np.ndarray, T: np.ndarray) -> float:
    """Variance inflation: matches' errors are correlated over a descriptor's support, so the
    points count only as many as the cells of CELL_PX they occupy."""
    cells = np.floor(a / (CELL_PX * T[0, 0])).astype(np.int64)
    n_eff = len(np.unique(cells[:, 0] * 100003 + cells[:, 1]))
    return max(len(a) / max(n_eff, 1), 1.0)


def estimate_motion(
    xy_cur: np.ndarray,
    xy_prev: np.ndarray,
    config: RegistrationConfig,
    shape: tuple[int, int],
    model: str | None = None,
    relax: bool | Callable[[float, np.ndarray, str], bool] = True,
) -> Registration:
    """Motion mapping matched points of the current frame (of `shape` (h, w)) onto the
    reference: RANSAC consensus, the model (`model`, else `[registration] model`; "auto"
    selects), refined on all matches within the threshold; the paper's failure rules. With
    `perspective_prior` the model is relaxed into a MAP homography when `relax` is True; when
    False, the pure model and its `perspective_evidence`; when a function, it decides from that
    evidence, the pure model's H_moving_to_fixed and the model's name."""
    model = model or config.model
    # a 2x6 quadratic is for pairs (`pixel_refine.refine_pair`): its homography here
    if model == "quadratic":
        model = "homography"
    n = len(xy_cur)
    if model in ("translation", "similarity", "affine"):
        consensus = _linear_consensus(xy_cur, xy_prev, config, model)
    else:
        consensus = estimate_homography(xy_cur, xy_prev, config)
    if consensus.H_moving_to_fixed is None or not config.refine:
        return consensus
    T = frame_normaliser(shape)
    a_all, b_all = normalised(T, xy_cur), normalised(T, xy_prev)
    corners = normalised(T, frame_corners(shape))
    M0 = T @ consensus.H_moving_to_fixed @ np.linalg.inv(T)
    corner_sd = float("nan")

    def fit_round(round_: int, previous: _Fit | None, inl: np.ndarray, w: np.ndarray):
        nonlocal corner_sd
        a, b, M = a_all[inl], b_all[inl], previous.M if previous else M0
        if model == "auto" and round_ < 2:  # select on the consensus, then on its refinement
            fit, corner_sd = select_model(a, b, w[inl], M, corners, _inflation(a, T))
            return fit
        return _fit(previous.model if previous else model, a, b, w[inl], M)

    try:
        fit, inliers, w_all, _ = reweighted_rounds(
            fit_round,
            lambda fit: transfer_errors(fit.M, a_all, b_all),
            consensus.inliers,
            np.ones(n),
            rounds=REFINE_ROUNDS,
            threshold=config.reproj_threshold_px * T[0, 0],
            huber_k=HUBER_PX * T[0, 0],
            min_points=4,
        )
    except np.linalg.LinAlgError:
        fit = None
    if fit is None:
        return consensus
    chosen = fit.model
    evidence = float("nan")
    if inliers.sum() >= 4:
        a, b, w = a_all[inliers], b_all[inliers], w_all[inliers]
        fit, evidence, sigma2 = _relaxed(fit, a, b, w, T, config, relax)
        if model != "auto":  # the fit's expected corner error (auto's also counts the bias)
            corner_sd = float(np.sqrt(np.mean(sigma2 * fit.predict(corners)[1])))
    return _checked(
        np.linalg.inv(T) @ fit.M @ T,
        inliers,
        xy_cur,
        xy_prev,
        config,
        chosen,
        coverage=inlier_coverage(xy_cur[inliers], shape),
        corner_sd_px=corner_sd / T[0, 0] if np.isfinite(corner_sd) else float("nan"),
        perspective_evidence=evidence,
    )


def _relaxed(
    fit: _Fit,
    a: np.ndarray,
    b: np.ndarray,
    w: np.ndarray,
    T: np.ndarray,
    config: RegistrationConfig,
    relax: bool | Callable[[float, np.ndarray, str], bool],
) -> tuple[_Fit, float, float]:
    """The refined fit relaxed by the perspective prior where `relax` says so (see
    `estimate_motion`), its perspective evidence (nan when not asked for) and the variance of
    its residuals inflated for clustered points, from the inliers `a` -> `b` with weights `w`."""
    chosen = fit.model
    evidence = float("nan")
    dof = max(2 * len(a) - N_PARAMS[chosen], 1)
    inflation = _inflation(a, T)
    if config.perspective_prior > 0 and chosen != "homography":
        if relax is not True:
            evidence = perspective_evidence(fit, a, b, w)
        if callable(relax):  # the pure model's H in pixels for the caller to judge
            pure = np.linalg.inv(T) @ fit.M @ T
            relax = relax(evidence, pure / pure[2, 2], chosen)
        if relax:
            sigma2 = max(fit.rss / dof, 1e-12) * inflation
            fit = _fit_with_prior(fit, a, b, w, sigma2, config.perspective_prior) or fit
    return fit, evidence, max(fit.rss / dof, 1e-12) * inflation


def inlier_coverage(xy: np.ndarray, shape: tuple[int, int]) -> float:
    """Share of the frame (h, w) inside the convex hull of the points."""
    if len(xy) < 3:
        return 0.0
    hull = cv2.convexHull(xy.astype(np.float32))
    return float(cv2.contourArea(hull) / (shape[0] * shape[1]))


# -- the quadratic retinal model (pairs of photographs) ----------------------------------------
# Can, Stewart, Roysam and Tanenbaum (PAMI 2002): x' = a1 x^2 + a2 x y + a3 y^2 + a4 x + a5 y + a6
# and the same with b for y'; 12 parameters, the curvature of the retina seen from two poses.

N_PARAMS_QUADRATIC = 12


def _fit_quadratic_norm(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted least-squares quadratic (2x6) mapping a onto b, and its weighted RSS."""
    A = quadratic_terms(a) * np.sqrt(w)[:, None]
    rhs = b * np.sqrt(w)[:, None]
    Q, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    r = rhs - A @ Q
    return Q.T, float(np.sum(r * r))


def quadratic_to_pixels(Q_norm: np.ndarray, T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """The pixel quadratic of one fitted between normalised coordinates (T_a, T_b: pixel ->
    normalised similarities): a quadratic composed with affine maps stays quadratic, so its
    coefficients follow exactly from a least-squares fit to it on a grid."""
    g = np.stack(np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5)), -1).reshape(-1, 2)
    px = (g - T_a[:2, 2]) / T_a[0, 0]
    out = (apply_quadratic(Q_norm, g) - T_b[:2, 2]) / T_b[0, 0]
    Q, *_ = np.linalg.lstsq(quadratic_terms(px), out, rcond=None)
    return Q.T


@dataclass(frozen=True)
class RobustFit:
    """A homography and a quadratic fitted robustly to matches (pixels), and the choice."""

    H: np.ndarray  # 3x3, the best homography
    Q: np.ndarray  # 2x6, the best quadratic
    inliers: np.ndarray  # (N,) bool, of the chosen model
    model: str  # "homography" or "quadratic"
    error_px: float  # mean residual (px) of the chosen model on its inliers


def robust_fit(
    xy_cur: np.ndarray,
    xy_prev: np.ndarray,
    shape: tuple[int, int],
    H0: np.ndarray,
    threshold_px: float,
    model: str = "homography",
    weights: np.ndarray | None = None,
    homography_threshold_px: float | None = None,
) -> RobustFit:
    """Homography (Gauss-Newton from H0) and quadratic fitted by re-weighted least squares
    (Huber at a third of `threshold_px`, matches beyond it out) in normalised coordinates.

    `model`: "homography", "quadratic", or "auto": the quadratic only where it beats the
    homography under a test that charges its 4 extra parameters (the homography's extra
    residual, in units of the quadratic's noise inflated by how many points share a cell,
    beyond its chi-square bound k + ADEQUATE_Z sqrt(2k)). `homography_threshold_px` (default
    `threshold_px`) bounds the homography's residuals: on a curved retina they reach ~10 px
    at 2912 px however precise the matches, so a tight bound would keep only part of them."""
    T = frame_normaliser(shape)
    a_all, b_all = normalised(T, xy_cur), normalised(T, xy_prev)
    w0 = np.ones(len(a_all)) if weights is None else np.asarray(weights, np.float64)
    M = T @ H0 @ np.linalg.inv(T)
    M = M / M[2, 2]

    def rounds(predict, fit, thr):
        def errors(state=None):
            return np.linalg.norm(predict(a_all, state) - b_all, axis=1)

        err0 = errors()
        state, inl, _, err = reweighted_rounds(
            lambda _round, _previous, inl, w: fit(a_all[inl], b_all[inl], w[inl])[0],
            errors,
            err0 < thr,
            w0 * huber_weights(err0, thr / ROBUST_HUBER_DIVISOR),
            rounds=ROBUST_ROUNDS,
            threshold=thr,
            huber_k=thr / ROBUST_HUBER_DIVISOR,
            min_points=ROBUST_MIN_POINTS,
            prior_weights=w0,
        )
        return state, inl, err0 if err is None else err

    def h_predict(q, state=None):
        return apply_homography(M if state is None else state.M, q)

    def h_fit(a, b, w):
        f = _fit("homography", a, b, w, M)
        if f is None:
            raise np.linalg.LinAlgError("homography fit failed")
        return f, f.rss

    h_thr = (homography_threshold_px or threshold_px) * T[0, 0]
    h_state, h_inl, h_err = rounds(h_predict, h_fit, h_thr)
    M_h = h_state.M if h_state is not None else M
    Qn0, _ = _fit_quadratic_norm(a_all[h_inl], b_all[h_inl], np.ones(int(h_inl.sum())))

    def q_predict(q, state=None):
        return apply_quadratic(Qn0 if state is None else state, q)

    thr = threshold_px * T[0, 0]
    q_state, q_inl, q_err = (None, h_inl, h_err)
    if model in ("quadratic", "auto") and h_inl.sum() >= 2 * N_PARAMS_QUADRATIC:
        q_state, q_inl, q_err = rounds(q_predict, _fit_quadratic_norm, thr)
    Qn = Qn0 if q_state is None else q_state
    H = np.linalg.inv(T) @ M_h @ T
    H = H / H[2, 2]
    Q = quadratic_to_pixels(Qn, T, T)
    chosen = "homography"
    if model == "quadratic" and q_state is not None:
        chosen = "quadratic"
    elif model == "auto" and q_state is not None:
        both = h_inl & q_inl
        n = int(both.sum())
        if n > 2 * N_PARAMS_QUADRATIC:
            rss_h = float(np.sum(h_err[both] ** 2))
            rss_q = float(np.sum(q_err[both] ** 2))
            sigma2 = max(rss_q / (2 * n - N_PARAMS_QUADRATIC), 1e-12) * _inflation(a_all[both], T)
            extra = N_PARAMS_QUADRATIC - N_PARAMS["homography"]
            if (rss_h - rss_q) / sigma2 > extra + ADEQUATE_Z * np.sqrt(2 * extra):
                chosen = "quadratic"
    inl, err = (q_inl, q_err) if chosen == "quadratic" else (h_inl, h_err)
    mean = float(np.mean(err[inl]) / T[0, 0]) if inl.any() else float("nan")
    return RobustFit(H, Q, inl, chosen, mean)
