"""Coarse-to-fine refinement of a pair's registration up to the photographs' own pixels.

Matches found at the working size are placed to a pixel or two there, i.e. 5-10 px on a 2912 px
photograph. Each level doubles the resolution (geometrically, from the working scale to 1): every
match's moving point is predicted in the fixed image by the current transform, a template around
it, warped by the transform's local affine part so that it looks as it must in the fixed image,
is searched by normalised cross-correlation in a small window there, and the peak (sub-pixel,
a parabola per axis) is its new fixed position; the transform is then fitted again, robustly,
on the re-localised matches (an inlier a level cannot place keeps its place from the level
before, at that level's lower weight; a level that places fewer than half of them ends the
refinement). Cost: one `cv2.remap` per image and level for all templates and windows, one
small `cv2.matchTemplate` per match and level.

Video registrations are refined by tracking instead (`track_points`, `[registration]
track_window_px`): each inlier of the current frame is followed into the reference frame by
pyramidal Lucas-Kanade from where the fitted model predicts it, on band-passed copies of both
frames (`lk_texture`, made once per frame during extraction), and the model is refitted on the
tracked points (`tracking._tracked`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from mosaic.config import RegistrationConfig
from mosaic.geometry import apply_homography, apply_quadratic, rescaled
from mosaic.preprocess import Disc, retina_disc
from mosaic.registration import RobustFit, robust_fit

log = logging.getLogger(__name__)

TEMPLATE_HALF_PX = 12  # template of 25x25 level pixels
SEARCH_PX = 5  # searched this far around the prediction at each level
MIN_NCC = 0.6  # a weaker correlation peak leaves the match out of the fit
THRESHOLD_LEVEL_PX = 2.0  # robust fit: residuals beyond this (level pixels) are outliers
MIN_POINTS = 12
LEVEL_KEEPS = 0.5  # a level that re-localises fewer than this share of the last one's inliers stops

Mapping = Callable[[np.ndarray], np.ndarray]

TEXTURE_SIGMA_PX = (1.0, 8.0)  # band-pass for tracking: a difference of Gaussians of these sd
TRACK_MAX_SHIFT_PX = 3.0  # a point the tracker moves further than this from the prediction is out
TRACK_LEVELS = 1  # pyramid levels above the frame (the prediction is within a few px)
TRACK_ITERATIONS = 5  # steps from the prediction (a few px off); 30 cost 2.5x for no gain
TRACK_EIGEN_QUANTILE = 0.2  # the weakest-textured windows (smallest LK eigenvalue) are out


def _smooth(image: np.ndarray, sigma: float) -> np.ndarray:
    """A Gaussian blur of large `sigma` computed at 1/4 resolution and brought back: 6x
    faster, and the band-passed texture differs by ~1 % of its sd (measured). The 4x4 area
    average and the linear upsampling each add ~1.15 px of sd, taken off the small blur."""
    h, w = image.shape
    if sigma < 4.0 or min(h, w) < 64:
        return cv2.GaussianBlur(image, (0, 0), sigma)
    small = cv2.resize(image, (round(w / 4), round(h / 4)), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), np.sqrt(sigma**2 - 2 * 1.15**2) / 4)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def _erode_by_octagon(mask: np.ndarray, radius_px: int) -> np.ndarray:
    """`preprocess.erode_by_disc` with an octagon for the disc (a square, then a diamond): it
    contains the disc, its corners reach 1.082 radii, and it is ~6x faster at 16 px (an
    elliptic kernel is not separable)."""
    square = round(radius_px * (1 - np.sqrt(0.5)) / np.sqrt(0.5))  # half-side: the diagonal
    diamond = radius_px - square  # extent matches the axes' (both radius_px)
    out = mask
    if square > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * square + 1, 2 * square + 1))
        out = cv2.erode(out, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=255)
    if diamond > 0:
        cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
        out = cv2.erode(
            out, cross, iterations=diamond, borderType=cv2.BORDER_CONSTANT, borderValue=255
        )
    return out


def lk_texture(gray: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The frame's band-passed texture as uint8 (±3 sd around 128): illumination, vignetting
    and gain changes removed, vessels kept, for `track_points`. Outside `mask` (uint8, 0 = no
    retina: the view's border, burned-in overlays) and as far inside it as the band-pass
    reaches, flat 128: structure fixed to the camera must not pull the tracked points."""
    fine, coarse = TEXTURE_SIGMA_PX
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), fine)
    hp = cv2.subtract(g, _smooth(g, coarse))
    valid = None
    if mask is not None and not mask.all():
        valid = _erode_by_octagon(mask, round(2 * coarse))
    _, sd = cv2.meanStdDev(hp, mask=valid if valid is not None and valid.any() else None)
    gain = 127.5 / (3.0 * float(sd[0, 0]) + 1e-6)
    texture = cv2.addWeighted(hp, gain, hp, 0.0, 127.0, dtype=cv2.CV_8U)  # saturating
    if valid is None:
        return texture
    flat = np.full_like(texture, 128)
    cv2.copyTo(texture, valid, flat)
    return flat


def track_points(
    moving: np.ndarray, fixed: np.ndarray, xy: np.ndarray, xy_pred: np.ndarray, window_px: int
) -> tuple[np.ndarray, np.ndarray]:
    """Where moving points (N, 2) lie in `fixed`, by pyramidal Lucas-Kanade from their
    predicted positions on two `lk_texture`s; and which were found (converged, near the
    prediction, in a textured window). Keypoints are placed to ~1.6 px on noisy, compressed,
    magnified video; tracking halves that (measured on the realistic tuning videos)."""
    if len(xy) == 0:
        return xy_pred.astype(np.float32), np.zeros(0, bool)
    found, status, eigen = cv2.calcOpticalFlowPyrLK(
        moving,
        fixed,
        xy.astype(np.float32).reshape(-1, 1, 2),
        xy_pred.astype(np.float32).reshape(-1, 1, 2).copy(),
        winSize=(window_px, window_px),
        maxLevel=TRACK_LEVELS,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, TRACK_ITERATIONS, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW | cv2.OPTFLOW_LK_GET_MIN_EIGENVALS,
    )
    found = found.reshape(-1, 2)
    eigen = eigen.ravel()
    ok = status.ravel().astype(bool) & np.isfinite(found).all(1)
    ok &= np.linalg.norm(found - xy_pred, axis=1) < TRACK_MAX_SHIFT_PX
    if ok.any():
        ok &= eigen > np.quantile(eigen[ok], TRACK_EIGEN_QUANTILE)
    return found, ok


ALIGN_BLUR_PX = 2.0  # `coarse_texture`: the tracking texture blurred by this sd, then halved
ALIGN_HALF_PX = 10  # `align_similarity`: windows of 21x21 coarse (~42x42 frame) pixels
ALIGN_ITERATIONS = 10
ALIGN_STOP_PX = 0.01  # ... or until a step moves the windows less than this
ALIGN_MAX_ZOOM = 0.05  # a refinement that changes the zoom by more than this ...
ALIGN_MAX_SHIFT_PX = 4.0  # ... or moves the windows' centre further is not taken
ALIGN_MIN_PIXELS = 500  # fewer window pixels seen in both frames leave the estimate unrefined


@dataclass(frozen=True)
class CoarseTexture:
    """A frame's texture for `align_similarity` (`coarse_texture`) with its gradients (Sobel,
    per coarse pixel), made once per frame: every registration of the frame reads them."""

    image: np.ndarray  # (H/2, W/2) float32 around 0, NaN where flat
    gx: np.ndarray
    gy: np.ndarray


def coarse_texture(texture: np.ndarray) -> CoarseTexture:
    """A `lk_texture` blurred (`ALIGN_BLUR_PX`) and halved, as float32 around 0, NaN where it
    is flat (no retina: the view's border, a lens's rim): where a window's own Lucas-Kanade
    stops in the noise a few pixels from the truth, the many windows of one similarity on this
    smoother texture still converge (`align_similarity`)."""
    smooth = cv2.GaussianBlur(cv2.subtract(texture, 128.0, dtype=cv2.CV_32F), (0, 0), ALIGN_BLUR_PX)
    h, w = texture.shape
    size = ((w + 1) // 2, (h + 1) // 2)
    half = cv2.resize(smooth, size, interpolation=cv2.INTER_AREA)
    flat = cv2.erode((texture == 128).view(np.uint8), np.ones((3, 3), np.uint8))
    if flat.any():  # a block of exact 128s is `lk_texture`'s no-retina value, not texture
        half[cv2.resize(flat, size, interpolation=cv2.INTER_AREA) > 0] = np.nan
    gx = cv2.Sobel(half, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(half, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return CoarseTexture(half, gx, gy)


def align_similarity(
    moving: CoarseTexture, fixed: CoarseTexture, xy: np.ndarray, H_moving_to_fixed: np.ndarray
) -> np.ndarray | None:
    """The similarity H_moving_to_fixed nearest the given one that best aligns windows around
    the moving points (N, 2) with the fixed frame, on two `coarse_texture`s: one Gauss-Newton
    solve (inverse compositional) for the four parameters over all windows together. Per
    window, Lucas-Kanade on noisy magnified frames keeps about half of its start's error in
    zoom (measured); jointly, the noise of each window averages out. None where too few
    pixels are seen in both frames or the solve leaves the start by more than
    ALIGN_MAX_ZOOM in zoom or ALIGN_MAX_SHIFT_PX at the windows' centre."""
    if len(xy) == 0:
        return None
    xy = xy.astype(np.float64)
    q = (xy - 0.5) / 2.0  # coarse pixel coordinates
    c = q.mean(0)
    sc = 1.0 / max(float(np.abs(q - c).max()), 1.0)
    o = np.arange(-ALIGN_HALF_PX, ALIGN_HALF_PX + 1, dtype=np.float32)
    ox, oy = np.meshgrid(o, o)
    # one row of window pixels per point: remap's maps are limited to 32767 columns
    X = (q[:, 0, None, None].astype(np.float32) + ox).reshape(len(q), -1)
    Y = (q[:, 1, None, None].astype(np.float32) + oy).reshape(len(q), -1)
    template = _sample(moving.image, X, Y)
    gx, gy = _sample(moving.gx, X, Y), _sample(moving.gy, X, Y)
    cx, cy, s32 = np.float32(c[0]), np.float32(c[1]), np.float32(sc)  # keep float32
    zx, zy = ((X - cx) * s32).ravel(), ((Y - cy) * s32).ravel()
    seen = np.isfinite(template) & np.isfinite(gx) & np.isfinite(gy)
    template[~seen] = gx[~seen] = gy[~seen] = 0.0  # no texture in the moving frame: adds nothing
    # steepest descent images (rows) of the template for the warp (1 + a + ib) z + t, in
    # units of sc
    steepest = np.stack([gx * zx + gy * zy, gy * zx - gx * zy, gx, gy]) / s32
    try:  # inverse compositional: the Hessian is the template's, the same at every step
        hessian_inv = np.linalg.inv((steepest @ steepest.T).astype(np.float64))
    except np.linalg.LinAlgError:
        return None
    m0, t0 = _complex_similarity(H_moving_to_fixed, xy, c, sc)
    m, t = m0, t0
    for _ in range(ALIGN_ITERATIONS):
        a, b = np.float32(m.real / sc), np.float32(m.imag / sc)
        wx = zx * a - zy * b + np.float32(t.real / sc + c[0])
        wy = zx * b + zy * a + np.float32(t.imag / sc + c[1])
        error = _sample(fixed.image, wx.reshape(X.shape), wy.reshape(X.shape)) - template
        lost = np.isnan(error)  # warped outside the fixed frame's texture: adds nothing
        if np.count_nonzero(seen & ~lost) < ALIGN_MIN_PIXELS:
            return None
        error[lost] = 0.0
        d = hessian_inv @ (steepest @ error).astype(np.float64)
        step = 1.0 + d[0] + 1j * d[1]  # m, t <- (m, t) composed with the inverse step
        m, t = m / step, t - m * (d[2] + 1j * d[3]) / step
        if np.abs(d).max() < ALIGN_STOP_PX / 2 * sc:
            break
    if abs(abs(m) / abs(m0) - 1.0) > ALIGN_MAX_ZOOM or abs(t - t0) / sc > ALIGN_MAX_SHIFT_PX / 2:
        return None
    N = _normaliser(c, sc)
    S = np.array([[m.real, -m.imag, t.real], [m.imag, m.real, t.imag], [0.0, 0.0, 1.0]])
    return np.linalg.inv(N) @ S @ N


def _normaliser(c: np.ndarray, sc: float) -> np.ndarray:
    """Frame pixels to `align_similarity`'s coordinates: coarse pixels (frame / 2), centred
    on c, scaled by sc."""
    return np.array(
        [[sc / 2, 0.0, -sc * (0.25 + c[0])], [0.0, sc / 2, -sc * (0.25 + c[1])], [0.0, 0.0, 1.0]]
    )


def _complex_similarity(
    H: np.ndarray, xy: np.ndarray, c: np.ndarray, sc: float
) -> tuple[complex, complex]:
    """(m, t) of the similarity z -> m z + t (normalised coordinates) nearest H on the points
    xy (least squares): H may carry perspective."""
    N = _normaliser(c, sc)
    a = apply_homography(N, xy) @ np.array([1.0, 1j])
    b = apply_homography(N @ H, xy) @ np.array([1.0, 1j])
    ma, mb = a.mean(), b.mean()
    m = complex((np.conj(a - ma) * (b - mb)).sum() / max(float((np.abs(a - ma) ** 2).sum()), 1e-12))
    return m, complex(mb - m * ma)


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (1-D float32) of a float32 image at (x, y) (2-D), NaN outside it."""
    out = cv2.remap(
        image,
        x.astype(np.float32, copy=False),
        y.astype(np.float32, copy=False),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    return out.ravel()


FLOW_LEVELS = 3  # pyramid levels for `flow_points`: the motion prior may be ~100 px off
FLOW_BACK_PX = 1.0  # a point tracked there and back must return this close to its start


def flow_points(
    moving: np.ndarray, fixed: np.ndarray, xy: np.ndarray, xy_pred: np.ndarray, window_px: int
) -> tuple[np.ndarray, np.ndarray]:
    """Where points (N, 2) of `moving` lie in `fixed` (two `lk_texture`s), by pyramidal
    Lucas-Kanade over FLOW_LEVELS levels from a prediction that may be far off (a motion
    prior, where matching failed), kept where tracking back returns within FLOW_BACK_PX: the
    forward-backward check stands in for the descriptors that found no consensus."""
    if len(xy) == 0:
        return xy_pred.astype(np.float32), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.01)
    start = xy.astype(np.float32).reshape(-1, 1, 2)
    found, status, _ = cv2.calcOpticalFlowPyrLK(
        moving, fixed, start, xy_pred.astype(np.float32).reshape(-1, 1, 2).copy(),
        winSize=(window_px, window_px), maxLevel=FLOW_LEVELS, criteria=criteria,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )  # fmt: skip
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(
        fixed, moving, found, start.copy(), winSize=(window_px, window_px),
        maxLevel=FLOW_LEVELS, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )  # fmt: skip
    found = found.reshape(-1, 2)
    ok = status.ravel().astype(bool) & status_back.ravel().astype(bool)
    ok &= np.isfinite(found).all(1) & np.isfinite(back.reshape(-1, 2)).all(1)
    ok &= np.linalg.norm(back.reshape(-1, 2) - xy, axis=1) < FLOW_BACK_PX
    return found, ok


AGREEMENT_SCALE = 0.5  # `texture_agreement` is computed at this scale (the band-pass is coarse)


def texture_agreement(
    fixed: np.ndarray, moving: np.ndarray, H_moving_to_fixed: np.ndarray
) -> float:
    """Normalised cross-correlation of two `lk_texture`s where both see retina, `fixed`
    sampled at `H_moving_to_fixed` of `moving`'s pixels: near 0 for a wrong placement or
    noise, towards 1 for a right one on a sharp view."""
    s = AGREEMENT_SCALE
    S = np.diag([s, s, 1.0])
    small = [cv2.resize(t, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) for t in (fixed, moving)]
    h, w = small[1].shape
    warped = cv2.warpPerspective(
        small[0], S @ H_moving_to_fixed @ np.linalg.inv(S), (w, h),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=128,
    )  # fmt: skip
    a, b = warped.astype(np.float32) - 128.0, small[1].astype(np.float32) - 128.0
    both = (a != 0) & (b != 0)  # flat 128: outside the view (`lk_texture`)
    if both.sum() < 100:
        return 0.0
    a, b = a[both], b[both]
    return float((a * b).sum() / (np.sqrt((a * a).sum() * (b * b).sum()) + 1e-6))


@dataclass(frozen=True)
class Refined:
    """The transform after refinement, and its matches at full resolution."""

    fit: RobustFit
    xy_moving: np.ndarray  # (N, 2) full-resolution pixels
    xy_fixed: np.ndarray  # (N, 2) places in the fixed image, from the finest level that found them
    weight: np.ndarray  # (N,) in the last fit: the correlation peak, lower if carried; 0: unused
    levels: int


def level_scales(start_scale: float, levels: int) -> list[float]:
    """`levels` scales from just above `start_scale` up to 1, evenly in log scale."""
    if levels <= 0 or start_scale >= 1.0:
        return [1.0] if levels > 0 else []
    return [float(s) for s in np.geomspace(start_scale, 1.0, levels + 1)[1:]]


def _local_affine(predict: Mapping, xy: np.ndarray, eps: float = 1.0) -> np.ndarray:
    """(N, 2, 2) Jacobian of `predict` at each point, by central differences."""
    dx, dy = np.array([eps, 0.0]), np.array([0.0, eps])
    jx = (predict(xy + dx) - predict(xy - dx)) / (2 * eps)
    jy = (predict(xy + dy) - predict(xy - dy)) / (2 * eps)
    return np.stack([jx, jy], axis=2)


def _grey(image: np.ndarray) -> np.ndarray:
    g = image[:, :, 1] if image.ndim == 3 else image
    return g.astype(np.float32)


def relocalise(
    fixed: np.ndarray,
    moving: np.ndarray,
    xy_moving: np.ndarray,
    predict: Mapping,  # moving full-resolution pixels (N, 2) -> fixed ones (N, 2)
    scale: float,
) -> tuple[np.ndarray, np.ndarray]:
    """New fixed positions (N, 2, full resolution) of moving points, and their NCC peaks, by
    template matching at `scale` of the full-resolution grey images `fixed` and `moving`."""
    k, r = TEMPLATE_HALF_PX, SEARCH_PX
    if scale < 1.0:
        size_f = (round(fixed.shape[1] * scale), round(fixed.shape[0] * scale))
        size_m = (round(moving.shape[1] * scale), round(moving.shape[0] * scale))
        fixed = cv2.resize(fixed, size_f, interpolation=cv2.INTER_AREA)
        moving = cv2.resize(moving, size_m, interpolation=cv2.INTER_AREA)
    n = len(xy_moving)
    pred = predict(xy_moving)
    # A fixed-image step u around the prediction comes from moving step J^-1 u (full-res units
    # are the same at every level, up to the scale that cancels).
    J = _local_affine(predict, xy_moving)
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    good = np.abs(det) > 1e-6
    J_inv = np.zeros_like(J)
    J_inv[good] = np.linalg.inv(J[good])
    t = np.arange(-k, k + 1, dtype=np.float64)
    u = np.stack(np.meshgrid(t, t), -1).reshape(-1, 2)  # (m, 2) template offsets, level px
    pm = rescaled(xy_moving, scale)
    src = pm[:, None, :] + np.einsum("nij,mj->nmi", J_inv, u)
    side = 2 * k + 1
    templates = _tiles(moving, src.reshape(n, side, side, 2))
    ts = np.arange(-k - r, k + r + 1, dtype=np.float64)
    wv = np.stack(np.meshgrid(ts, ts), -1)
    pf = rescaled(pred, scale)
    windows = _tiles(fixed, pf[:, None, None, :] + wv[None])
    out = np.full((n, 2), np.nan)
    peaks = np.zeros(n)
    for i in np.flatnonzero(good & np.isfinite(pf).all(1)):
        if templates[i].std() < 1.0:
            continue
        res = cv2.matchTemplate(windows[i], templates[i], cv2.TM_CCOEFF_NORMED)
        iy, ix = np.unravel_index(int(np.argmax(res)), res.shape)
        peaks[i] = res[iy, ix]
        if not (0 < ix < res.shape[1] - 1 and 0 < iy < res.shape[0] - 1):
            continue  # the peak is on the window's edge: not found
        dx = _parabola(res[iy, ix - 1], res[iy, ix], res[iy, ix + 1])
        dy = _parabola(res[iy - 1, ix], res[iy, ix], res[iy + 1, ix])
        out[i] = pred[i] + (np.array([ix + dx, iy + dy]) - r) / scale
    return out, peaks


def _tiles(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """`image` sampled (bilinear) at (N, h, w, 2) positions: N tiles of h x w. One `cv2.remap`
    per group of tiles stacked in a column (it takes fewer than SHRT_MAX rows)."""
    n, h, w = xy.shape[:3]
    out = np.empty((n, h, w), np.float32)
    per = max((32767 - 1) // h, 1)
    for i in range(0, n, per):
        m = xy[i : i + per].reshape(-1, w, 2).astype(np.float32)
        out[i : i + per] = cv2.remap(image, m[..., 0], m[..., 1], cv2.INTER_LINEAR).reshape(
            -1, h, w
        )
    return out


def _parabola(a: float, b: float, c: float) -> float:
    d = a - 2 * b + c
    return 0.0 if d >= 0 else float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))


def refine_pair(
    fixed: np.ndarray,
    moving: np.ndarray,
    xy_moving: np.ndarray,
    H0: np.ndarray,
    start_scale: float,
    levels: int,
    model: str = "homography",
    homography_threshold_px: float | None = None,
) -> Refined | None:
    """Refine H0 (moving -> fixed, full-resolution pixels) from the coarse inliers' moving
    points `xy_moving` through `levels` levels from `start_scale` (the working scale) up to the
    full resolution; `model` as in `registration.robust_fit` (the quadratic predicts the next
    level once chosen; `homography_threshold_px` bounds the homography's residuals, full
    resolution). Stops at the first level that loses most of the matches (`LEVEL_KEEPS`); None
    when the first one does."""
    g_fixed, g_moving = _grey(fixed), _grey(moving)
    shape = moving.shape[:2]
    fit: RobustFit | None = None
    H = H0

    def predict(q: np.ndarray) -> np.ndarray:
        if fit is not None and fit.model == "quadratic":
            return apply_quadratic(fit.Q, q)
        return apply_homography(H, q)

    done: Refined | None = None
    placed = np.full((len(xy_moving), 2), np.nan)  # each match's best place so far, full res
    weight = np.zeros(len(xy_moving))
    previous = start_scale
    for level, scale in enumerate(level_scales(start_scale, levels), 1):
        xy_f, ncc = relocalise(g_fixed, g_moving, xy_moving, predict, scale)
        ok = np.isfinite(xy_f).all(1) & (ncc >= MIN_NCC)
        kept = 0 if done is None else int(done.fit.inliers.sum())
        if ok.sum() < max(MIN_POINTS, LEVEL_KEEPS * kept):
            # The photographs hold no more detail here (defocus, noise, upsampled): the
            # previous level's answer stands rather than one fitted to a few matches.
            break
        # A previous inlier this level cannot place keeps its place from the level before,
        # at that level's coarser precision (weight ~ scale^2), so no region goes unmatched.
        carried = ~ok & (done.fit.inliers if done is not None else False)
        weight[carried] *= (previous / scale) ** 2
        placed[ok], weight[ok] = xy_f[ok], ncc[ok]
        use = ok | carried
        fit = robust_fit(
            xy_moving[use],
            placed[use],
            shape,
            H,
            THRESHOLD_LEVEL_PX / scale,
            model,
            weights=weight[use],
            homography_threshold_px=homography_threshold_px,
        )
        H = fit.H
        inliers = np.zeros(len(xy_moving), bool)
        inliers[np.flatnonzero(use)[fit.inliers]] = True
        fit = RobustFit(fit.H, fit.Q, inliers, fit.model, fit.error_px)
        done = Refined(fit, xy_moving, placed.copy(), np.where(use, weight, 0.0), level)
        previous = scale
    return done


def fit_pair(
    fixed: np.ndarray,
    moving: np.ndarray,
    xy_moving: np.ndarray,
    xy_fixed: np.ndarray,
    H_moving_to_fixed: np.ndarray,
    start_scale: float,
    config: RegistrationConfig,
    model: str = "homography",
    discs: tuple[Disc | None, Disc | None] | None = None,
) -> tuple[RobustFit, int]:
    """A pair's final transform from its coarse inliers (`xy_moving` -> `xy_fixed`, full
    resolution, found at `start_scale`) and coarse homography: refined through `config.
    refine_levels` levels (`refine_pair`), or, with none or when refinement keeps fewer than
    `config.min_inliers` matches, fitted robustly to the coarse matches; and the levels done.

    `model`: "homography", "quadratic" or "auto" (the quadratic where it pays, as in
    `registration.robust_fit`). The quadratic is fitted in every case: the answer's `H` is
    the homography closest to it over the overlap (`overlap_homography`), the best single
    homography for a curved retina, and "homography" answers that one alone. `discs`: the
    fixed and moving `retina_disc`s, when the caller has them already."""
    inner = "quadratic" if model == "quadratic" else "auto"
    coarse_px = config.reproj_threshold_px / start_scale  # the coarse threshold, full resolution
    fit, levels = None, 0
    matched = xy_moving, xy_fixed  # the matches the final fit saw
    if config.refine_levels > 0:
        refined = refine_pair(
            fixed,
            moving,
            xy_moving,
            H_moving_to_fixed,
            start_scale,
            config.refine_levels,
            inner,
            coarse_px,
        )
        if refined is not None and refined.fit.inliers.sum() >= config.min_inliers:
            fit, levels = refined.fit, refined.levels
            matched = refined.xy_moving, refined.xy_fixed
        else:
            log.info("refinement kept too few matches: the coarse registration stands")
    if fit is None:
        fit = robust_fit(xy_moving, xy_fixed, moving.shape[:2], H_moving_to_fixed, coarse_px, inner)
    if fit.model != "quadratic":
        return fit, levels
    disc_fixed, disc_moving = discs or (retina_disc(fixed), retina_disc(moving))
    H = overlap_homography(fit.Q, fit.H, moving.shape[:2], fixed.shape[:2], disc_moving, disc_fixed)
    if model != "homography":
        return RobustFit(H, fit.Q, fit.inliers, "quadratic", fit.error_px), levels
    a, b = (xy[fit.inliers] for xy in matched)  # the homography's own residual on them
    error = float(np.mean(np.linalg.norm(apply_homography(H, a) - b, axis=1)))
    return RobustFit(H, fit.Q, fit.inliers, "homography", error), levels


OVERLAP_SHRINK = 0.9  # the retina's outer tenth (dim, little matched) is left out of the overlap
OVERLAP_GRID = 64  # samples across the moving image


def overlap_homography(
    Q: np.ndarray,
    H: np.ndarray,
    moving_shape: tuple[int, int],
    fixed_shape: tuple[int, int],
    moving_disc: Disc | None,
    fixed_disc: Disc | None,
) -> np.ndarray:
    """The homography closest (least squares) to the quadratic `Q` (moving -> fixed) over the
    overlap: where both photographs see the retina (each one's disc without its outer tenth,
    or its whole frame when it has none). On a curved retina no homography fits everywhere;
    this one spreads its error evenly over the retina both photographs show, rather than over
    where the matches cluster (a robust fit to them also drops the periphery, where the
    curvature's residuals are largest). `H` (the robust fit) when the overlap is too small."""

    def inside(xy: np.ndarray, shape: tuple[int, int], disc) -> np.ndarray:
        if disc is None:
            return (xy >= 0).all(1) & (xy[:, 0] <= shape[1] - 1) & (xy[:, 1] <= shape[0] - 1)
        return np.hypot(xy[:, 0] - disc[0], xy[:, 1] - disc[1]) < OVERLAP_SHRINK * disc[2]

    h, w = moving_shape
    step = max(h, w) / OVERLAP_GRID
    gx, gy = np.meshgrid(np.arange(0, w, step), np.arange(0, h, step))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    target = apply_quadratic(Q, grid)
    use = inside(grid, moving_shape, moving_disc) & inside(target, fixed_shape, fixed_disc)
    if use.sum() < OVERLAP_GRID:
        return H
    H_fit, _ = cv2.findHomography(grid[use], target[use], 0)
    return H if H_fit is None else H_fit / H_fit[2, 2]


def fixed_to_moving_map(
    H: np.ndarray, Q: np.ndarray | None, fixed_shape: tuple[int, int], step: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) float32 of the fixed image's shape: where each fixed pixel comes from in
    the moving image, for `cv2.remap`. The homography inverts exactly; the quadratic by Newton
    steps from the inverse homography on a grid every `step` px, interpolated in between."""
    h, w = fixed_shape
    if Q is None:
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        src = apply_homography(np.linalg.inv(H), np.column_stack([gx.ravel(), gy.ravel()]))
        return (
            src[:, 0].reshape(h, w).astype(np.float32),
            src[:, 1].reshape(h, w).astype(np.float32),
        )
    gx, gy = np.meshgrid(np.arange(0, w + step, step, float), np.arange(0, h + step, step, float))
    target = np.column_stack([gx.ravel(), gy.ravel()])
    xy = apply_homography(np.linalg.inv(H), target)

    def quad(q: np.ndarray) -> np.ndarray:
        return apply_quadratic(Q, q)

    for _ in range(8):
        J = _local_affine(quad, xy)
        r = target - quad(xy)
        xy = xy + np.linalg.solve(J, r[:, :, None])[:, :, 0]
    coarse_x = xy[:, 0].reshape(gx.shape).astype(np.float32)
    coarse_y = xy[:, 1].reshape(gx.shape).astype(np.float32)
    ux, uy = np.meshgrid(
        np.arange(w, dtype=np.float32) / step, np.arange(h, dtype=np.float32) / step
    )
    return (
        cv2.remap(coarse_x, ux, uy, cv2.INTER_LINEAR),
        cv2.remap(coarse_y, ux, uy, cv2.INTER_LINEAR),
    )


def warp_check(
    fixed: np.ndarray, moving: np.ndarray, H: np.ndarray, Q: np.ndarray | None, tile_px: int = 0
) -> np.ndarray:
    """The moving image warped into the fixed image's frame (`cv2.remap`), beside a
    checkerboard of the fixed and the warped image (tiles of `tile_px`, default 1/8 of the
    fixed image's longer side), both BGR uint8 of the fixed image's shape, side by side."""
    map_x, map_y = fixed_to_moving_map(H, Q, fixed.shape[:2])
    warped = cv2.remap(moving, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    fixed3 = fixed if fixed.ndim == 3 else cv2.cvtColor(fixed, cv2.COLOR_GRAY2BGR)
    warped3 = warped if warped.ndim == 3 else cv2.cvtColor(warped, cv2.COLOR_GRAY2BGR)
    tile = tile_px or max(max(fixed.shape[:2]) // 8, 1)
    yy, xx = np.mgrid[0 : fixed.shape[0], 0 : fixed.shape[1]]
    board = ((yy // tile + xx // tile) % 2).astype(bool)
    check = np.where(board[..., None], warped3, fixed3)
    return np.hstack([warped3, check])
