"""Upright root-SIFT descriptors, the descriptor the paper pairs with every detector.

Paper: 128-d root-SIFT (Arandjelović & Zisserman) computed at each keypoint "without rotation
invariance" (orientation fixed to 0), because it matched fundus images better than the
rotation-invariant version.

`upright_rootsift` computes SIFT's descriptor densely instead of per keypoint (OpenCV builds a
scale-space pyramid and loops over each keypoint's window, so its cost grows with size^2); here
the cost is a few passes over the image plus a fixed amount per point, whatever the sizes:

1. The image is blurred as OpenCV's SIFT blurs its base layer for keypoints given to `compute`
   (sigma 1.6 over an assumed 0.5), and its gradients are binned into 8 orientation channels
   with linear interpolation between the two nearest bins (SIFT's orientation soft-binning).
2. SIFT pools each channel over a 4x4 grid of cells with a triangular (bilinear) kernel whose
   half-width is the cell width `3 * size / 2`. A triangle of any real half-width h at any real
   position is the second difference, with step h, of the channel's second-order summed-area
   table D(x) = sum_k f_k * max(0, x - k); D is piecewise (bi)linear between pixel centres, so
   bilinear interpolation of D is exact. With D tabulated once per image (two `cv2.integral`
   passes, float64), every keypoint costs 36 bilinear reads of D per channel (a 6x6 lattice
   whose second differences are the 16 cells), for any size: no size groups, no rounding.
3. To keep the tables small, a point pools at the coarsest level of a 2x block-average pyramid
   of the channels where its cells are still >= 2 blocks wide (size 10 -> blocks of 4 px);
   that changes descriptors by a cosine of < 0.002 and matching not measurably.
4. SIFT's Gaussian window (sigma = half the descriptor width) is applied per cell, then the
   descriptor is L2-normalised, clipped at 0.2, renormalised, and made root-SIFT.

Differences from OpenCV's `SIFT.compute` (cosine ~0.998 to its descriptors at integer points,
the same matching true positives on fundus pairs): the Gaussian window weights cells, not
pixels; orientations are quantised to 1.4 degrees; points keep their sub-pixel position (OpenCV
rounds it); values are not rounded to SIFT's byte scale. The OpenCV path stays available as
`upright_rootsift_opencv`.
"""

from __future__ import annotations

import cv2
import numpy as np

DESCRIPTOR_DIM = 128
_EPS = 1e-12
_N_CELLS = 4  # SIFT: 4x4 spatial cells ...
_N_ORI = 8  # ... of 8 orientation bins
_CELL_PER_SIZE = 1.5  # cell width = SIFT_DESCR_SCL_FCTR (3) * keypoint scale (size / 2)
_BASE_SIGMA = float(np.sqrt(1.6**2 - 0.5**2))  # OpenCV SIFT base layer: 1.6 over assumed 0.5
_CLIP = 0.2  # SIFT's clipping of normalised bins (illumination robustness)
_MIN_CELL_BLOCKS = 2.0  # pool at the coarsest pyramid level with cells >= 2 blocks wide ...
_LEVEL1_MIN_CELL_PX = 2.0  # ... but at half resolution already from 1 block (see below)
_MAX_LEVEL = 5  # blocks of up to 32 px; images are padded to whole blocks of it
_CHUNK = 256  # points per batch of lattice reads
_ORI_LEVELS = 256  # orientation quantisation for the binning lookup tables (uint8)
# Lattice j = 0..5 at offsets (j - 2.5) cells: cell c's centre is node c + 1, and its triangle is
# the second difference over nodes c, c + 1, c + 2.
_LATTICE = np.arange(_N_CELLS + 2, dtype=np.float64) - (_N_CELLS + 1) / 2
# SIFT's window: exp(-(u^2 + v^2) / (2 * sigma^2)) with sigma = half the width = 2 cells,
# evaluated at the cell centres (u, v in cells from the keypoint).
_CENTRES = np.arange(_N_CELLS, dtype=np.float64) - (_N_CELLS - 1) / 2
_WINDOW = np.exp(-(_CENTRES[:, None] ** 2 + _CENTRES[None, :] ** 2) / (0.5 * _N_CELLS**2))


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


def _check_inputs(
    image_gray: np.ndarray, xy: np.ndarray, size_px: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N,2) float32 points and (N,) float64 sizes, after validating the image and sizes."""
    if image_gray.ndim != 2 or image_gray.dtype != np.uint8:
        raise ValueError(
            f"image must be uint8 HxW grey, got {image_gray.dtype} of shape {image_gray.shape}"
        )
    pts = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
    sizes = np.broadcast_to(np.asarray(size_px, dtype=np.float64), (len(pts),))
    if len(sizes) and not (np.isfinite(sizes).all() and (sizes > 0).all()):
        raise ValueError("descriptor size_px must be finite and > 0")
    return pts, sizes


def _gradients(image_gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient magnitude (H, W) float32 and orientation quantised to 1/32 bin (H, W) uint8.

    Gradients as OpenCV's SIFT descriptor takes them on its base layer: central differences
    with y up (angles counter-clockwise), none on the outermost pixel ring. The quantisation
    (1.4 degrees) lets a lookup table do the orientation binning.
    """
    base = cv2.GaussianBlur(image_gray.astype(np.float32), (0, 0), _BASE_SIGMA)
    dx = cv2.Sobel(base, cv2.CV_32F, 1, 0, ksize=1)
    dy = cv2.Sobel(base, cv2.CV_32F, 0, 1, ksize=1)
    mag, ang = cv2.cartToPolar(dx, cv2.multiply(dy, -1.0))  # angle in [0, 2pi)
    mag[[0, -1], :] = 0.0
    mag[:, [0, -1]] = 0.0
    ori = cv2.convertScaleAbs(ang, alpha=_ORI_LEVELS / (2 * np.pi))  # 256 (= 2pi) saturates
    return mag, ori


def _orientation_luts() -> np.ndarray:
    """(8, 256) float32: weight of quantised orientation q in bin c, max(0, 1 - |q/32 - c|).

    SIFT's linear interpolation of each gradient between its two nearest bins, circularly.
    """
    ori = np.arange(_ORI_LEVELS) * (_N_ORI / _ORI_LEVELS)
    dist = np.abs(ori[None, :] - np.arange(_N_ORI)[:, None])
    dist = np.minimum(dist, _N_ORI - dist)
    return np.maximum(1.0 - dist, 0.0).astype(np.float32)


_ORI_LUTS = _orientation_luts()


def _pyramid_level(cell_px: np.ndarray) -> np.ndarray:
    """Per point, the pyramid level l (channels block-averaged over 2**l x 2**l) to pool at.

    Block-averaging before pooling moves mass by less than a block, which changes a
    descriptor little while a cell spans >= 2 blocks (cosine to the full-resolution
    descriptor >= 0.998 on fundus images; matching true positives unchanged), so each point
    takes the coarsest level where it does. Full resolution is kept for cells under
    `_LEVEL1_MIN_CELL_PX` only: its tables cost as much as all coarser levels together, and
    cells of 1-2 blocks stay close (cosine >= 0.99, 0.995 from 1.35 blocks: SIFT's smallest
    keypoints, size ~1.8) and match as well (same true positives).
    """
    level = np.floor(np.log2(np.maximum(cell_px / _MIN_CELL_BLOCKS, 1.0)))
    level[cell_px >= _LEVEL1_MIN_CELL_PX] = np.maximum(level[cell_px >= _LEVEL1_MIN_CELL_PX], 1)
    return np.minimum(level, _MAX_LEVEL).astype(np.int64)


class _Lattice:
    """Where and with which weights one pyramid level reads its tables for a set of points.

    Per point, a 6x6 lattice at offsets (j - 2.5) cells: cell c's centre is node c + 1, and
    its triangle is the second difference over nodes c, c + 1, c + 2. D (the second-order
    summed-area table, `table[y + 1, x + 1] = sum f[l, k] * max(0, y - l) * max(0, x - k)`)
    is bilinear between pixel centres, zero above/left of the image and linear below/right
    of it, so each node is read bilinearly from the segment [y0, y0 + 1] with y0 clamped to
    [-1, rows - 1] (and likewise x) and extrapolated outside it, which is exact.
    """

    def __init__(self, pts: np.ndarray, cell_px: np.ndarray, level: int, shape: tuple[int, int]):
        rows, cols = shape
        s = float(2**level)
        # Block i of a level covers full-resolution pixels [i*s, (i+1)*s): centre i*s + (s-1)/2.
        centre = (pts.astype(np.float64) - (s - 1) / 2) / s
        step = cell_px / s
        gx = centre[:, 0:1] + _LATTICE[None, :] * step[:, None]  # (N, 6)
        gy = centre[:, 1:2] + _LATTICE[None, :] * step[:, None]
        x0 = np.clip(np.floor(gx), -1, cols - 1)
        y0 = np.clip(np.floor(gy), -1, rows - 1)
        fx = (gx - x0)[:, None, :]  # (N, 1, 6)
        fy = (gy - y0)[:, :, None]  # (N, 6, 1)
        self.stride = cols + 2
        # Flat index of table[y0 + 1, x0 + 1] per node, (N, 6, 6), and the bilinear weights of
        # the 2x2 table entries from there.
        rows_at = (y0 + 1).astype(np.int64) * self.stride
        i00 = rows_at[:, :, None] + (x0 + 1).astype(np.int64)[:, None, :]
        self.corners = (i00, i00 + 1, i00 + self.stride, i00 + (self.stride + 1))
        self.weights = ((1.0 - fy) * (1.0 - fx), (1.0 - fy) * fx, fy * (1.0 - fx), fy * fx)

    def read(self, tables: np.ndarray) -> np.ndarray:
        """D of each channel at the lattice nodes, (N, 6, 6, C) float64, from channel-last
        (R * S, C) tables: each bilinear tap gathers one node's C channels, contiguous."""
        out = np.take(tables, self.corners[0], axis=0)
        out *= self.weights[0][..., None]
        tmp = np.empty_like(out)
        for idx, weight in zip(self.corners[1:], self.weights[1:], strict=True):
            np.take(tables, idx, axis=0, out=tmp)
            tmp *= weight[..., None]
            out += tmp
        return out


def _cell_histograms(image_gray: np.ndarray, pts: np.ndarray, cell_px: np.ndarray) -> np.ndarray:
    """(N, 4, 4, 8) float64 SIFT cell histograms (triangular pooling, not yet windowed).

    Per orientation channel and pyramid level: the channel's second-order summed-area table
    (two `cv2.integral` passes, float64), read at every point's lattice; the second
    differences of the lattice are the triangle-pooled cells, exactly, for any cell width.
    """
    h, w = image_gray.shape
    mag, ori = _gradients(image_gray)
    levels = _pyramid_level(cell_px)
    groups = [(lv, np.flatnonzero(levels == lv)) for lv in np.unique(levels).tolist()]
    # Zero-pad to whole blocks of the coarsest level: block averages stay aligned at every
    # level, and each point's descriptor does not depend on the other points of the call.
    block = 2**_MAX_LEVEL
    hp, wp = -(-h // block) * block, -(-w // block) * block
    full = np.zeros((hp, wp), np.float32)
    tables = {lv: np.empty((_N_ORI, (hp >> lv) + 2, (wp >> lv) + 2)) for lv, _ in groups}
    for c in range(_N_ORI):  # 8 whole-image passes (and a few per level), no per-pixel loop
        cv2.multiply(cv2.LUT(ori, _ORI_LUTS[c]), mag, dst=full[:h, :w])
        level_map, level_now = full, 0
        for lv, _ in groups:
            while level_now < lv:  # 2x2 block average
                level_map = cv2.resize(
                    level_map, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA
                )
                level_now += 1
            cv2.integral(cv2.integral(level_map, sdepth=cv2.CV_64F), tables[lv][c], cv2.CV_64F)
    hist = np.empty((len(pts), _N_CELLS, _N_CELLS, _N_ORI))
    for lv, sel in groups:
        # Reads round off at ~1e-16 of a table's range; cells below a generous multiple of it
        # are noise (a flat region would otherwise get a normalised noise descriptor): 0.
        tol = 64.0 * np.finfo(np.float64).eps * float(tables[lv][:, -1, -1].max())
        shape = (hp >> lv, wp >> lv)
        # channel-last (R * S, 8): a lattice node's 8 channels share a cache line
        by_node = np.ascontiguousarray(tables[lv].reshape(_N_ORI, -1).T)
        for start in range(0, len(sel), _CHUNK):  # chunks keep the temporaries in cache
            part = sel[start : start + _CHUNK]
            node = _Lattice(pts[part], cell_px[part], lv, shape).read(by_node)  # (n,6,6,8)
            rows = node[:, :-2] - 2.0 * node[:, 1:-1] + node[:, 2:]
            cells = rows[:, :, :-2] - 2.0 * rows[:, :, 1:-1] + rows[:, :, 2:]  # (n, 4, 4, 8)
            # In units of the level's tables: a per-point factor the normalisation removes.
            cells[cells < tol] = 0.0
            hist[part] = cells
    return hist


def _normalise(hist: np.ndarray) -> np.ndarray:
    """SIFT's L2 normalise, clip at 0.2, renormalise; then root-SIFT. (N,128) float32."""
    norm = np.linalg.norm(hist, axis=1, keepdims=True)
    return rootsift(np.minimum(hist, _CLIP * norm))


def upright_rootsift(
    image_gray: np.ndarray, xy: np.ndarray, size_px: float | np.ndarray = 10.0
) -> np.ndarray:
    """(N,128) float32 upright root-SIFT descriptors of uint8 HxW `image_gray` at points `xy`.

    One row per input point, in input order; a point outside the image (or not finite) gets a
    zero row, as does a point whose whole support is flat. `size_px` is the keypoint diameter
    as OpenCV's SIFT reads it (cell width 1.5 * size_px, descriptor width 4 cells): one value,
    or one per point. Layout and semantics are SIFT's (see the module docstring).
    """
    pts, sizes = _check_inputs(image_gray, xy, size_px)
    n = len(pts)
    out = np.zeros((n, DESCRIPTOR_DIM), dtype=np.float32)
    if n == 0:
        return out
    h, w = image_gray.shape
    inside = (
        np.isfinite(pts).all(axis=1)
        & (pts[:, 0] >= 0)
        & (pts[:, 0] <= w - 1)
        & (pts[:, 1] >= 0)
        & (pts[:, 1] <= h - 1)
    )
    if not inside.any():
        return out
    hist = _cell_histograms(image_gray, pts[inside], _CELL_PER_SIZE * sizes[inside])
    hist *= _WINDOW[None, :, :, None]
    out[inside] = _normalise(hist.reshape(len(hist), DESCRIPTOR_DIM))
    return out


_SIFT: cv2.SIFT | None = None


def _sift() -> cv2.SIFT:
    global _SIFT  # a SIFT object is cheap but re-creating it per call is pointless
    if _SIFT is None:
        _SIFT = cv2.SIFT_create()
    return _SIFT


def upright_rootsift_opencv(
    image_gray: np.ndarray, xy: np.ndarray, size_px: float | np.ndarray = 10.0
) -> np.ndarray:
    """Reference: `upright_rootsift` through OpenCV's SIFT `compute` (slower, for comparison).

    One row per input point, in input order (OpenCV's output is re-indexed through the
    keypoints' class_id, so a dropped or re-ordered keypoint cannot shift rows; a point OpenCV
    returns no descriptor for gets a zero row).
    """
    pts, sizes = _check_inputs(image_gray, xy, size_px)
    n = len(pts)
    out = np.zeros((n, DESCRIPTOR_DIM), dtype=np.float32)
    if n == 0:
        return out
    # cv2.KeyPoint.convert cannot set angle=0 (it leaves -1, i.e. a 1 degree rotation), so the
    # keypoints are built here; class_id carries the input row.
    kps = [
        cv2.KeyPoint(float(x), float(y), size, 0.0, 0.0, 0, i)
        for i, ((x, y), size) in enumerate(zip(pts.tolist(), sizes.tolist(), strict=True))
    ]
    kps_out, desc = _sift().compute(image_gray, kps)
    if desc is None or len(kps_out) == 0:
        return out
    rows = np.fromiter((k.class_id for k in kps_out), dtype=np.int64, count=len(kps_out))
    out[rows] = rootsift(desc)
    return out
