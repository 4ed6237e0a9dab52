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
    return classify_errors(point_errors(H_est, points, warp_points(H_gt, points)))


# --------------------------------------------------------------------------------------------
# Evaluation metrics beyond the training loss: NNDR AUC, coverage, registration errors, FIRE
# --------------------------------------------------------------------------------------------

COVERAGE_RADIUS_PX = 25.0  # disk around each true positive (paper, after Aldana-Iuit et al.)
FIRE_THRESHOLDS_PX = np.arange(1, 26)  # t = 1..25 px, the FIRE success-curve thresholds
FIRE_MAX_THRESHOLD_PX = 25.0


def point_errors(H_a_to_b: np.ndarray, xy_a: np.ndarray, xy_b: np.ndarray) -> np.ndarray:
    """(N,) float64 distances ||H xy_a - xy_b||: ground-truth points mapped by an estimate.

    Non-finite mappings (a point sent to infinity) give inf, so they never pass a threshold.
    """
    mapped = warp_points(H_a_to_b, xy_a).astype(np.float64)
    d = np.linalg.norm(mapped - np.asarray(xy_b, dtype=np.float64).reshape(-1, 2), axis=1)
    return np.where(np.isfinite(d), d, np.inf)


def classify_errors(errors: np.ndarray) -> tuple[str, float, float]:
    """("acceptable" | "inaccurate", MEE, MAE) of a non-failed registration's point errors.

    The paper's rule: acceptable when the median error < 10 px and the maximum < 30 px.
    """
    errors = np.asarray(errors, dtype=np.float64).ravel()
    if errors.size == 0:
        return "inaccurate", float("nan"), float("nan")
    mee, mae = float(np.median(errors)), float(np.max(errors))
    if mee < ACCEPTABLE_MEE_PX and mae < ACCEPTABLE_MAE_PX:
        return "acceptable", mee, mae
    return "inaccurate", mee, mae


def rmse(errors: np.ndarray) -> float:
    """Root mean squared error of point distances (nan for none)."""
    errors = np.asarray(errors, dtype=np.float64).ravel()
    return float(np.sqrt(np.mean(errors**2))) if errors.size else float("nan")


def nearest_neighbour_ratios(distances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each row of an (Na, Nb) descriptor distance matrix: nearest column and NNDR.

    The ratio is d(1st NN) / d(2nd NN) (Lowe's test); 0 when there is a single column (no
    second neighbour), 1 when both distances are 0 (indistinguishable).
    """
    d = np.asarray(distances, dtype=np.float64)
    n_a, n_b = d.shape
    if n_a == 0 or n_b == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.float64)
    nearest = d.argmin(axis=1)
    first = d[np.arange(n_a), nearest]
    if n_b == 1:
        return nearest, np.zeros(n_a)
    second = np.partition(d, 1, axis=1)[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(second > 0, first / second, 1.0)
    return nearest, ratio


def nndr_auc(ratios: np.ndarray, correct: np.ndarray) -> float:
    """Area under the ROC curve traced by the NNDR threshold t (a match is kept if ratio <= t).

    Positives are nearest-neighbour matches that are correct under the ground truth, negatives
    the others; sweeping t from 0 to 1 moves from (FPR, TPR) = (0, 0) to (1, 1). The area equals
    the probability that a correct match has a lower ratio than a wrong one (ties count half).
    nan when there is no correct or no wrong match (the curve is undefined).
    """
    ratios = np.asarray(ratios, dtype=np.float64).ravel()
    correct = np.asarray(correct, dtype=bool).ravel()
    pos, neg = ratios[correct], np.sort(ratios[~correct])
    if pos.size == 0 or neg.size == 0:
        return float("nan")
    below = np.searchsorted(neg, pos, side="left")  # wrong matches with a lower ratio
    not_above = np.searchsorted(neg, pos, side="right")
    higher = neg.size - not_above
    ties = not_above - below
    return float((higher + 0.5 * ties).sum() / (pos.size * neg.size))


def coverage_fraction(
    xy: np.ndarray,
    shape: tuple[int, ...],
    radius_px: float = COVERAGE_RADIUS_PX,
    mask: np.ndarray | None = None,
) -> float:
    """Fraction of the image covered by the union of disks of `radius_px` around the points.

    The paper's coverage fraction of true-positive keypoints. Pixel (col, row) is covered when
    its centre (col, row) lies within the radius of a point; disks are clipped at the image
    border. With a `mask` (nonzero = counted), the fraction is of the masked area only.
    """
    h, w = shape[:2]
    valid = np.ones((h, w), bool) if mask is None else np.asarray(mask) > 0
    area = int(valid.sum())
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    if area == 0 or len(xy) == 0:
        return 0.0
    r = int(np.ceil(radius_px))
    oy, ox = np.mgrid[-r : r + 2, -r : r + 2]  # offsets from floor(x, y) reaching every pixel
    ox, oy = ox.ravel(), oy.ravel()
    covered = np.zeros((h, w), bool)
    for start in range(0, len(xy), 256):  # chunks bound memory to 256 x (2r + 3)^2 offsets
        p = xy[start : start + 256]
        px = np.floor(p[:, :1]).astype(np.int64) + ox
        py = np.floor(p[:, 1:]).astype(np.int64) + oy
        hit = (px - p[:, :1]) ** 2 + (py - p[:, 1:]) ** 2 <= radius_px**2
        hit &= (px >= 0) & (px < w) & (py >= 0) & (py < h)
        covered[py[hit], px[hit]] = True
    return float((covered & valid).sum()) / area


def success_curve(errors: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Fraction of pairs whose error is strictly below each threshold (inf = failed: never)."""
    errors = np.asarray(errors, dtype=np.float64).ravel()
    thresholds = np.asarray(thresholds, dtype=np.float64).ravel()
    if errors.size == 0:
        return np.full(thresholds.shape, np.nan)
    return (errors[None, :] < thresholds[:, None]).mean(axis=1)


def fire_auc(errors: np.ndarray, thresholds: np.ndarray = FIRE_THRESHOLDS_PX) -> float:
    """FIRE protocol AUC: mean over t = 1..25 px of the fraction of pairs with error < t."""
    return float(np.mean(success_curve(errors, thresholds)))


def fire_auc_integral(errors: np.ndarray, max_px: float = FIRE_MAX_THRESHOLD_PX) -> float:
    """The 0..25 variant: exact area under the success curve over t in [0, max_px] / max_px.

    The area under F(t) = mean(e_i < t) is mean(max(0, max_px - e_i)), so this equals the mean
    of clip(1 - e_i / max_px, 0, 1); failed pairs (inf) add 0.
    """
    errors = np.asarray(errors, dtype=np.float64).ravel()
    if errors.size == 0:
        return float("nan")
    return float(np.mean(np.clip(1.0 - errors / max_px, 0.0, 1.0)))


def mean_auc(errors_by_category: dict[str, np.ndarray]) -> float:
    """mAUC: the mean of the per-category FIRE AUCs (e.g. S, P, A); nan without categories."""
    aucs = [fire_auc(e) for e in errors_by_category.values() if np.asarray(e).size]
    return float(np.mean(aucs)) if aucs else float("nan")


def class_error_stats(
    classes: np.ndarray, mee: np.ndarray, rmse_px: np.ndarray
) -> dict[str, dict[str, float]]:
    """Mean and std of MEE and RMSE per class: acceptable, inaccurate and all non-failed.

    The paper's supplementary tables (MEE / RMSE per registration class); nan for an empty class.
    """
    classes = np.asarray(classes)
    mee = np.asarray(mee, dtype=np.float64)
    rmse_px = np.asarray(rmse_px, dtype=np.float64)
    groups = {
        "acceptable": classes == "acceptable",
        "inaccurate": classes == "inaccurate",
        "non_failed": classes != "failed",
    }
    out = {}
    for name, sel in groups.items():
        n = int(sel.sum())
        stats = {"n": float(n)}
        for key, values in (("mee", mee[sel]), ("rmse", rmse_px[sel])):
            stats[f"{key}_mean"] = float(values.mean()) if n else float("nan")
            stats[f"{key}_std"] = float(values.std()) if n else float("nan")
        out[name] = stats
    return out
