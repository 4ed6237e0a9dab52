"""Points and transforms: frames related through a common reference, and the corner error
that scores an estimated transform against the truth.

Runtime stages, the evaluation and the synthetic data share these helpers, so they live here
and not beside the data that has the truth (the runtime stages import neither `mosaic.eval`
nor `mosaic.synthetic`).
"""

from __future__ import annotations

import numpy as np


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


__all__ = ["corner_error", "relative_homographies"]
