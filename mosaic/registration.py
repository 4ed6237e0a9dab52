"""Robust homography between two frames and the paper's rules that declare it failed."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from glampoints.metrics import failure_reason
from mosaic.config import RegistrationConfig

METHODS = {
    "ransac": cv2.RANSAC,
    "usac_default": cv2.USAC_DEFAULT,
    "usac_magsac": cv2.USAC_MAGSAC,
    "usac_accurate": cv2.USAC_ACCURATE,
    "usac_fast": cv2.USAC_FAST,
}


@dataclass(frozen=True)
class Registration:
    """Outcome of registering the current frame to the previous one."""

    H_cur_to_prev: np.ndarray | None  # 3x3 float64, None when failed
    n_matches: int
    n_inliers: int
    inliers: np.ndarray  # (n_matches,) bool
    reproj_error_px: float  # mean transfer error of the inliers; nan when failed
    reason: str | None  # why it failed; None when registered

    @property
    def ok(self) -> bool:
        return self.reason is None


def estimate_homography(
    xy_cur: np.ndarray, xy_prev: np.ndarray, config: RegistrationConfig
) -> Registration:
    """Homography mapping matched points of the current frame onto the previous one."""
    n = len(xy_cur)
    no_inliers = np.zeros(n, bool)
    reason = failure_reason(None, n) if n < 4 else None
    if reason is not None:
        return Registration(None, n, 0, no_inliers, float("nan"), reason)
    H, mask = cv2.findHomography(
        xy_cur.astype(np.float32),
        xy_prev.astype(np.float32),
        METHODS[config.method],
        config.reproj_threshold_px,
        maxIters=config.max_iters,
        confidence=config.confidence,
    )
    inliers = mask.ravel().astype(bool) if mask is not None else no_inliers
    n_inliers = int(inliers.sum())
    reason = failure_reason(H, n)
    if reason is None and n_inliers < config.min_inliers:
        reason = f"too few inliers ({n_inliers} < {config.min_inliers})"
    if reason is not None:
        return Registration(None, n, n_inliers, inliers, float("nan"), reason)
    H = H / H[2, 2]
    ones = np.ones((n_inliers, 1))
    mapped = np.hstack([xy_cur[inliers], ones]) @ H.T
    err = np.linalg.norm(mapped[:, :2] / mapped[:, 2:] - xy_prev[inliers], axis=1)
    return Registration(H, n, n_inliers, inliers, float(err.mean()), None)
