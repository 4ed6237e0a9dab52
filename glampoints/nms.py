"""Non-maximum suppression of keypoint score maps (paper: "standard non-differentiable NMS").

A pixel is kept when it is the maximum of the square window of side `2 * (window_px // 2) + 1`
centred on it (window 10 -> 11x11, radius 5) and its score is above `threshold`. Two kept
points are therefore more than `window_px // 2` pixels apart in Chebyshev distance.

Ties: two window maxima that lie in each other's window necessarily have equal scores; such a
candidate is dropped when a tied candidate with a smaller raster index (y * W + x) lies in its
window, so a flat plateau gives one point (its first pixel in raster order), never a cluster.
Fully vectorised: two window-maximum passes, no loop over pixels or keypoints. The window
maximum is `max_pool2d`, or for CPU float32 maps the identical but ~100x faster `cv2.dilate`
with a square kernel (its border reads as -FLT_MAX rather than -inf, which changes nothing
for kept points since they must exceed the threshold).

`nms_numpy` (the detector's path) gives the same points in the same order with numpy and
OpenCV only. Two window maxima in each other's window have equal scores, so its tie-break
compares only the candidates that share their score with another (a few dozen on a retina
score map) pairwise, and makes the window pass of the negated index only for many ties
(plateaus): ~0.4 ms instead of ~1.9 ms for a 660x350 retina score map on the 2-core
development machine.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812 (PyTorch convention)


def _radius(window_px: int) -> int:
    if window_px < 1:
        raise ValueError(f"NMS window must be >= 1 px, got {window_px}")
    return window_px // 2


def window_max(x: torch.Tensor, radius: int, use_cv2: bool = True) -> torch.Tensor:
    """Maximum over the (2 radius + 1)^2 window around each pixel of (B,1,H,W) `x`."""
    k = 2 * radius + 1
    if use_cv2 and x.device.type == "cpu" and x.dtype == torch.float32:
        kernel = np.ones((k, k), dtype=np.uint8)
        xn = x.contiguous().numpy()
        out = np.empty_like(xn)
        for b in range(xn.shape[0]):  # loop over the batch only
            out[b, 0] = cv2.dilate(xn[b, 0], kernel, borderType=cv2.BORDER_CONSTANT)
        return torch.from_numpy(out)
    return F.max_pool2d(x, k, stride=1, padding=radius)


def nms_mask(
    score: torch.Tensor, window_px: int = 10, threshold: float = 0.0, use_cv2: bool = True
) -> torch.Tensor:
    """Boolean (B,1,H,W) mask of the kept local maxima of a (B,1,H,W) score map."""
    if score.dim() != 4 or score.shape[1] != 1:
        raise ValueError(f"score map must be (B,1,H,W), got {tuple(score.shape)}")
    r = _radius(window_px)
    score = score.detach()
    if r == 0:
        return score > threshold
    local_max = window_max(score, r, use_cv2)
    cand = (score == local_max) & (score > threshold)
    # Tie break: among candidates in one window (necessarily equal scores) keep the one with
    # the smallest raster index, found as a max-pool of the negated index.
    _, _, h, w = score.shape
    dtype = torch.float32 if h * w < 2**24 else torch.float64
    index = torch.arange(h * w, dtype=dtype, device=score.device).view(1, 1, h, w)
    neg_index = torch.where(cand, -index, torch.full_like(index, -float(h * w)))
    first = window_max(neg_index, r, use_cv2)
    return cand & (neg_index == first)


def nms(
    score: torch.Tensor,
    window_px: int = 10,
    threshold: float = 0.0,
    top_k: int | None = None,
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Keypoints of each map of a (B,1,H,W) batch: list of (xy (N,2) float32, scores (N,)).

    Points are sorted by decreasing score (ties: raster order); at most `top_k` are kept.
    """
    keep = nms_mask(score, window_px, threshold)
    out: list[tuple[torch.Tensor, torch.Tensor]] = []
    for b in range(score.shape[0]):
        ys, xs = torch.nonzero(keep[b, 0], as_tuple=True)
        s = score[b, 0, ys, xs].detach().float()
        order = torch.sort(s, descending=True, stable=True).indices
        if top_k is not None:
            order = order[: max(int(top_k), 0)]
        xy = torch.stack([xs[order], ys[order]], dim=1).to(torch.float32)
        out.append((xy, s[order]))
    return out


def nms_numpy(
    score: np.ndarray,
    window_px: int = 10,
    threshold: float = 0.0,
    top_k: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Single HxW map: (xy (N,2) float32, scores (N,) float32), strongest first.

    Same result as `nms` on the map (ties in raster order), computed with numpy and cv2.
    """
    if score.ndim != 2:
        raise ValueError(f"score map must be HxW, got shape {score.shape}")
    r = _radius(window_px)
    s = np.asarray(score, dtype=np.float32)
    if s.strides[1] != s.itemsize:  # cv2 needs contiguous rows; a row stride is fine
        s = np.ascontiguousarray(s)
    h, w = s.shape
    if r == 0:
        cand = s > threshold
    else:
        kernel = np.ones((2 * r + 1, 2 * r + 1), dtype=np.uint8)
        local_max = cv2.dilate(s, kernel, borderType=cv2.BORDER_CONSTANT)
        cand = (s == local_max) & (s > threshold)
    ys, xs = np.divmod(np.flatnonzero(cand), w)  # raster order (10x faster than np.nonzero)
    vals = s[ys, xs]
    tied = _tied(vals) if r > 0 and len(vals) > 1 else None
    if tied is not None and len(tied) <= MAX_PAIRWISE_TIES:
        # Candidates in each other's window have equal scores, so only candidates that share
        # their score with another can be dropped: pairwise among those (a few dozen a frame).
        ty, tx, tv = ys[tied], xs[tied], vals[tied]
        near = np.abs(ty[:, None] - ty[None, :]) <= r
        near &= np.abs(tx[:, None] - tx[None, :]) <= r
        near &= tv[:, None] == tv[None, :]
        near &= tied[None, :] < tied[:, None]  # the other one comes first in raster order
        keep = np.ones(len(vals), bool)
        keep[tied[near.any(axis=1)]] = False
        ys, xs, vals = ys[keep], xs[keep], vals[keep]
    elif tied is not None:
        # Many ties (plateaus): keep, among candidates in one window, the smallest raster index.
        dtype = np.float32 if h * w < 2**24 else np.float64
        neg_index = np.full((h, w), -float(h * w), dtype=dtype)
        neg_index[ys, xs] = -(ys * w + xs).astype(dtype)  # exact: h * w < 2**24 for float32
        first = cv2.dilate(neg_index, kernel, borderType=cv2.BORDER_CONSTANT)
        keep = neg_index[ys, xs] == first[ys, xs]
        ys, xs, vals = ys[keep], xs[keep], vals[keep]
    order = np.argsort(-vals, kind="stable")
    if top_k is not None:
        order = order[: max(int(top_k), 0)]
    xy = np.stack([xs[order], ys[order]], axis=1).astype(np.float32)
    return xy.reshape(-1, 2), vals[order].astype(np.float32)


MAX_PAIRWISE_TIES = 512  # tied candidates compared pairwise; more: the tie-break's window pass


def _tied(vals: np.ndarray) -> np.ndarray | None:
    """Ascending indices of the values that equal another one, None when all are distinct."""
    v = np.sort(vals)
    same = v[1:] == v[:-1]
    if not same.any():
        return None
    shared = np.unique(v[1:][same])
    return np.flatnonzero(np.isin(vals, shared))


def refine_subpixel(score: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Sub-pixel keypoint positions: the vertex of a parabola through each peak and its two
    neighbours, separately in x and y (offsets clipped to half a pixel).

    Integer NMS positions carry up to 0.5 px of quantisation error per point, which chained
    frame-to-frame homographies accumulate; the refined positions remove most of it.
    """
    if len(xy) == 0:
        return xy.astype(np.float32)
    h, w = score.shape
    x = np.clip(np.rint(xy[:, 0]).astype(np.intp), 1, w - 2)
    y = np.clip(np.rint(xy[:, 1]).astype(np.intp), 1, h - 2)

    def at(yy: np.ndarray, xx: np.ndarray) -> np.ndarray:  # gather first: no full-map copy
        return np.nan_to_num(score[yy, xx].astype(np.float64), nan=0.0, neginf=0.0, posinf=0.0)

    c = at(y, x)

    def vertex(minus: np.ndarray, plus: np.ndarray) -> np.ndarray:
        curvature = minus - 2.0 * c + plus
        with np.errstate(divide="ignore", invalid="ignore"):
            offset = np.where(curvature < 0, 0.5 * (minus - plus) / curvature, 0.0)
        return np.clip(offset, -0.5, 0.5)

    dx = vertex(at(y, x - 1), at(y, x + 1))
    dy = vertex(at(y - 1, x), at(y + 1, x))
    border = (xy[:, 0] < 1) | (xy[:, 0] > w - 2) | (xy[:, 1] < 1) | (xy[:, 1] > h - 2)
    out = np.stack([x + dx, y + dy], axis=1)
    out[border] = xy[border]
    return out.astype(np.float32)
