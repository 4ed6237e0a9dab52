"""The paper's evaluation criteria ("Evaluation criteria") and its registration failure rules.

Pure numpy. Points are (x, y) float arrays of shape (N, 2); `H_1_to_2` maps pixel coordinates
of image 1 into image 2.
"""

from __future__ import annotations

import numpy as np

MIN_MATCHES = 4  # a homography needs 4 correspondences
MAX_SCALE = 4.0
MIN_SCALE = 0.1
ACCEPTABLE_MEE_PX = 10.0
ACCEPTABLE_MAE_PX = 30.0


def failure_reason(H: np.ndarray | None, n_matches: int) -> str | None:
    """The paper's "failed registration" rules; None when the homography is usable.

    Failed when: fewer than 4 matches, no homography, non-finite entries, a flip (reflection:
    negative determinant of the upper-left 2x2 after normalising H[2,2] to 1), or a scaling
    component outside [0.1, 4]. The scaling is read from the singular values of that
    normalised 2x2 part (the local scale at the origin): fail if the largest is > 4 or the
    smallest < 0.1.
    """
    if n_matches < MIN_MATCHES:
        return f"too few matches ({n_matches} < {MIN_MATCHES})"
    if H is None:
        return "no homography found"
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (3, 3):
        return f"homography has shape {H.shape}, not 3x3"
    if not np.all(np.isfinite(H)):
        return "homography has non-finite entries"
    if abs(H[2, 2]) < 1e-12:
        return "degenerate homography (H[2,2] = 0)"
    A = H[:2, :2] / H[2, 2]
    if np.linalg.det(A) < 0:
        return "homography contains a reflection (flip)"
    s = np.linalg.svd(A, compute_uv=False)
    if s[0] > MAX_SCALE:
        return f"scale {s[0]:.3g} > {MAX_SCALE:g}"
    if s[-1] < MIN_SCALE:
        return f"scale {s[-1]:.3g} < {MIN_SCALE:g}"
    return None


def warp_points(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Apply homography H to (N,2) points; returns float32 (N,2) (inf where w = 0)."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    H = np.asarray(H, dtype=np.float64)
    q = p @ H[:2, :2].T + H[:2, 2]
    w = p @ H[2, :2] + H[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = q / w[:, None]
    return out.astype(np.float32)


def _inside(xy: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    h, w = shape[:2]
    x, y = xy[:, 0], xy[:, 1]
    return np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)


def _nearest_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each row of a, the distance to its nearest row of b (inf when b is empty)."""
    if len(a) == 0:
        return np.zeros(0, dtype=np.float64)
    if len(b) == 0:
        return np.full(len(a), np.inf)
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    return np.sqrt(np.maximum(d2.min(axis=1), 0.0))


def common_region(
    xy1: np.ndarray,
    xy2: np.ndarray,
    H_1_to_2: np.ndarray,
    shape1: tuple[int, ...],
    shape2: tuple[int, ...],
) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks of the points of image 1 / image 2 that fall inside the other image."""
    xy1 = np.asarray(xy1, dtype=np.float32).reshape(-1, 2)
    xy2 = np.asarray(xy2, dtype=np.float32).reshape(-1, 2)
    in1 = _inside(warp_points(H_1_to_2, xy1), shape2)
    in2 = _inside(warp_points(np.linalg.inv(H_1_to_2), xy2), shape1)
    return in1, in2


def repeatability(
    xy1: np.ndarray,
    xy2: np.ndarray,
    H_1_to_2: np.ndarray,
    shape1: tuple[int, ...],
    shape2: tuple[int, ...],
    eps: float = 3.0,
) -> float:
    """Paper's repeatability over the points P, P' in the region common to both images.

    (#{x in P with some x' in P' at ||H x - x'|| < eps} + #{x' in P' with some x in P within
    eps of x'}) / (|P| + |P'|); 0 when both sets are empty.
    """
    xy1 = np.asarray(xy1, dtype=np.float32).reshape(-1, 2)
    xy2 = np.asarray(xy2, dtype=np.float32).reshape(-1, 2)
    in1, in2 = common_region(xy1, xy2, H_1_to_2, shape1, shape2)
    p1 = warp_points(H_1_to_2, xy1[in1])
    p2 = xy2[in2]
    total = len(p1) + len(p2)
    if total == 0:
        return 0.0
    hits = (_nearest_distance(p1, p2) < eps).sum() + (_nearest_distance(p2, p1) < eps).sum()
    return float(hits) / total


def true_positive_mask(
    xy1_matched: np.ndarray, xy2_matched: np.ndarray, H_1_to_2: np.ndarray, eps: float = 3.0
) -> np.ndarray:
    """(N,) bool: match i is correct when ||H x1_i - x2_i|| <= eps (paper: eps = 3 px)."""
    a = warp_points(H_1_to_2, np.asarray(xy1_matched).reshape(-1, 2)).astype(np.float64)
    b = np.asarray(xy2_matched, dtype=np.float64).reshape(-1, 2)
    d = np.linalg.norm(a - b, axis=1)
    return np.isfinite(d) & (d <= eps)


def matching_score(
    xy1: np.ndarray,
    xy2: np.ndarray,
    xy1_matched: np.ndarray,
    xy2_matched: np.ndarray,
    H_1_to_2: np.ndarray,
    shape1: tuple[int, ...],
    shape2: tuple[int, ...],
    eps: float = 3.0,
) -> float:
    """M.score: correct matches over the keypoints detected in the shared region.

    Averaged over both directions: n_correct / 2 * (1 / |P| + 1 / |P'|), where P, P' are the
    keypoints `xy1`, `xy2` lying in the common region (0 when either is empty).
    """
    in1, in2 = common_region(xy1, xy2, H_1_to_2, shape1, shape2)
    n1, n2 = int(in1.sum()), int(in2.sum())
    if n1 == 0 or n2 == 0:
        return 0.0
    n_correct = int(true_positive_mask(xy1_matched, xy2_matched, H_1_to_2, eps).sum())
    return 0.5 * n_correct * (1.0 / n1 + 1.0 / n2)


def six_fixed_points(width: int, height: int) -> np.ndarray:
    """Six fixed reference points (float32 (6,2)) for the registration error of a pair.

    The centres of a 3 (across) x 2 (down) grid of equal cells: x at 1/6, 1/2, 5/6 of the
    width, y at 1/4 and 3/4 of the height; spread over the image so that both translation
    and rotation/scale errors show.
    """
    xs = np.array([1.0, 3.0, 5.0]) / 6.0 * width
    ys = np.array([1.0, 3.0]) / 4.0 * height
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float32)


def registration_class(
    H_est: np.ndarray | None, H_gt: np.ndarray, points: np.ndarray, n_matches: int
) -> tuple[str, float, float]:
    """("failed" | "inaccurate" | "acceptable", MEE, MAE) of an estimated homography.

    `points` (reference-image points, e.g. `six_fixed_points`) are mapped by H_gt and by H_est;
    MEE / MAE are the median / maximum of the distances. Failed (MEE = MAE = nan) per
    `failure_reason`; acceptable when MEE < 10 and MAE < 30 px, inaccurate otherwise.
    """
    if failure_reason(H_est, n_matches) is not None:
        return "failed", float("nan"), float("nan")
    assert H_est is not None
    gt = warp_points(H_gt, points).astype(np.float64)
    est = warp_points(H_est, points).astype(np.float64)
    err = np.linalg.norm(gt - est, axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    mee, mae = float(np.median(err)), float(np.max(err))
    if mee < ACCEPTABLE_MEE_PX and mae < ACCEPTABLE_MAE_PX:
        return "acceptable", mee, mae
    return "inaccurate", mee, mae
