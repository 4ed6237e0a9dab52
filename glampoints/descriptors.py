"""Upright root-SIFT descriptors, the descriptor the paper pairs with every detector.

Paper: 128-d root-SIFT (Arandjelović & Zisserman) computed at each keypoint "without rotation
invariance" (orientation fixed to 0), because it matched fundus images better than the
rotation-invariant version.
"""

from __future__ import annotations

import cv2
import numpy as np

DESCRIPTOR_DIM = 128
_EPS = 1e-12


def rootsift(desc: np.ndarray) -> np.ndarray:
    """Root-SIFT of (N,128) SIFT descriptors: L1-normalise each row, then element-wise sqrt.

    Rows then have unit L2 norm, so Euclidean matching equals the Hellinger kernel on SIFT.
    All-zero rows stay zero. Returns float32.
    """
    d = np.abs(np.asarray(desc, dtype=np.float32))
    if d.ndim != 2:
        raise ValueError(f"descriptors must be (N, D), got shape {d.shape}")
    l1 = d.sum(axis=1, keepdims=True)
    return np.sqrt(d / np.maximum(l1, _EPS)).astype(np.float32, copy=False)


_SIFT: cv2.SIFT | None = None


def _sift() -> cv2.SIFT:
    global _SIFT  # a SIFT object is cheap but re-creating it per call is pointless
    if _SIFT is None:
        _SIFT = cv2.SIFT_create()
    return _SIFT


def upright_rootsift(
    image_gray: np.ndarray, xy: np.ndarray, size_px: float | np.ndarray = 10.0
) -> np.ndarray:
    """(N,128) float32 upright root-SIFT descriptors of uint8 HxW `image_gray` at points `xy`.

    One row per input point, in input order (OpenCV's output is re-indexed through the
    keypoints' class_id, so a dropped or re-ordered keypoint cannot shift rows; a point OpenCV
    returns no descriptor for gets a zero row). `size_px` is the keypoint diameter given to
    SIFT, which sets the descriptor's support region: one value, or one per point.
    """
    pts = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
    n = len(pts)
    out = np.zeros((n, DESCRIPTOR_DIM), dtype=np.float32)
    if n == 0:
        return out
    if image_gray.ndim != 2 or image_gray.dtype != np.uint8:
        raise ValueError(
            f"image must be uint8 HxW grey, got {image_gray.dtype} of shape {image_gray.shape}"
        )
    sizes = np.broadcast_to(np.asarray(size_px, dtype=np.float32), (n,)).tolist()
    # cv2.KeyPoint.convert cannot set angle=0 (it leaves -1, i.e. a 1 degree rotation), so the
    # keypoints are built here; class_id carries the input row.
    kps = [
        cv2.KeyPoint(float(x), float(y), size, 0.0, 0.0, 0, i)
        for i, ((x, y), size) in enumerate(zip(pts.tolist(), sizes, strict=True))
    ]
    kps_out, desc = _sift().compute(image_gray, kps)
    if desc is None or len(kps_out) == 0:
        return out
    rows = np.fromiter((k.class_id for k in kps_out), dtype=np.int64, count=len(kps_out))
    out[rows] = rootsift(desc)
    return out
