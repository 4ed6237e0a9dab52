"""A handheld lens's rim: the retina seen through a lens held before the eye shows only inside
a disc that moves about the frame with the hand, the face around it (`LensRimMask`)."""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from mosaic.config import PreprocessConfig
from mosaic.geometry import circle_unscaled, rescaled
from mosaic.preprocess import Prepared, erode_by_disc

Circle = tuple[float, float, float]  # (cx, cy, r) px

RIM_SIDE_PX = 192  # the rim is searched on a copy of at most this longer side (analysis px)
RIM_RADII = (0.3, 0.8)  # a lens's rim, in frame heights: an optic disc is far smaller, the
# source photograph's own field of view in magnified video far larger
RIM_EDGE_POINTS = 1200  # strongest edge pixels (local maxima across the edge) that vote
RIM_CANDIDATES = 3  # circles of the vote checked against the frame
RIM_ANGLES = 120  # directions around a circle in which its edge is looked for
RIM_REACH = 4.0  # the edge is looked for this far (analysis px) either side of the circle
RIM_VIEW_MARGIN = 3  # analysis px between a profile's ends and the view mask's edge: the
# view's own (soft) border steps too
RIM_STEP = 7.0  # grey levels (RMS over the colour channels) a rim's two sides differ by
RIM_ON_CIRCLE = 0.4  # an edge this close to the fitted circle (analysis px) lies on it


@dataclass(frozen=True)
class RimTest:
    """What a circle must show to be taken for a lens's rim (`RimFit.shows`)."""

    seen: float  # at least this share of its directions in the frame and the lit view
    support: float  # on at least this share of those, the frame steps right on the circle
    residual: float  # those steps at most this far from it (median, analysis px)


# On the realistic tuning videos (every 2nd frame of 8 with a rim and 8 without): rims found
# within 3 px had support 0.72 or more in 95 % of frames, residual <= 0.30 in 99 %; frames
# without a rim reached support 0.45 in 99 % (0.68 at most, on 16 % of the circle seen).
RIM_FIND = RimTest(seen=0.3, support=0.75, residual=0.3)
# ... or a shorter arc that steps almost everywhere along it: a large lens's rim cut by the
# frame's edges and the source's dark field of view (0.27-0.29 of it seen, support 0.97-1.0
# on the first frames of 3 of 20 training-photograph rim videos, where RIM_FIND missed it)
RIM_FIND_ARC = RimTest(seen=0.2, support=0.9, residual=0.3)
# a rim near the last frame's (the hand moves it smoothly) is kept on weaker evidence: where
# the face's colour meets the retina's, stretches of the rim hardly step
RIM_KEEP = RimTest(seen=0.15, support=0.45, residual=0.35)
RIM_NEAR = 0.1  # near: centre and radius within this share of the radius of the last rim


@dataclass(frozen=True)
class RimFit:
    """A circle refitted to the frame's edge across it, and how well the frame bears it out."""

    circle: Circle  # frame px
    seen: float  # share of its directions in the frame and well inside the lit view
    support: float  # share of those where the two sides differ by RIM_STEP, right on it
    residual: float  # median distance of those steps to the circle, analysis px

    def shows(self, test: RimTest) -> bool:
        return (
            self.seen >= test.seen
            and self.support >= test.support
            and self.residual <= test.residual
        )

    @property
    def found(self) -> bool:
        """Taken for a rim without a prior (`RIM_FIND` or `RIM_FIND_ARC`)."""
        return self.shows(RIM_FIND) or self.shows(RIM_FIND_ARC)


def _rim_gradient(small: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel the colour edge's strength (the structure tensor's larger eigenvalue; grey
    levels / px) and its normal's angle (radians, modulo pi)."""
    gx = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3)
    if gx.ndim == 3:
        jxx, jyy, jxy = (gx * gx).sum(2), (gy * gy).sum(2), (gx * gy).sum(2)
    else:
        jxx, jyy, jxy = gx * gx, gy * gy, gx * gy
    half = np.sqrt(((jxx - jyy) / 2) ** 2 + jxy**2)
    return np.sqrt((jxx + jyy) / 2 + half) / 8.0, 0.5 * np.arctan2(2 * jxy, jxx - jyy)


def _ridge(strength: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Where the edge strength is a maximum across the edge (along its normal, quantised to
    one of four directions): a thin line along each edge, as in Canny."""
    padded = np.pad(strength, 1)
    h, w = strength.shape
    octant = np.rint(angle / (np.pi / 4)).astype(np.int64) % 4  # 0: x, 1: diagonal, 2: y, 3
    ridge = np.zeros(strength.shape, bool)
    for k, (dx, dy) in enumerate(((1, 0), (1, 1), (0, 1), (-1, 1))):
        ahead = padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
        behind = padded[1 - dy : 1 - dy + h, 1 - dx : 1 - dx + w]
        ridge |= (octant == k) & (strength >= ahead) & (strength > behind)
    return ridge


def _circle_votes(
    strength: np.ndarray, angle: np.ndarray, usable: np.ndarray, radii: np.ndarray
) -> list[Circle]:
    """The circles (analysis px) most edge pixels agree on. Each of the strongest edge pixels
    inside `usable` votes for the centres along its normal (both ways) at the radii of
    `radii`; at the centres most voted for, the radius is the one most edge pixels whose
    normal points at the centre lie at (their count divided by the radius: a larger circle
    has more pixels)."""
    h, w = strength.shape
    ys, xs = np.nonzero(usable & _ridge(strength, angle))
    s = strength[ys, xs]
    if len(s) > RIM_EDGE_POINTS:
        keep = np.argpartition(s, -RIM_EDGE_POINTS)[-RIM_EDGE_POINTS:]
        ys, xs = ys[keep], xs[keep]
    a = angle[ys, xs]
    nx, ny = np.cos(a).astype(np.float32), np.sin(a).astype(np.float32)
    pad = int(radii[-1] // 3)  # centres a little outside the frame too
    aw, ah = w + 2 * pad, h + 2 * pad
    along = np.concatenate([radii[::2], -radii[::2]]).astype(np.float32)[:, None]
    ax = np.rint(xs + pad + along * nx).astype(np.int32)
    ay = np.rint(ys + pad + along * ny).astype(np.int32)
    ok = (ax >= 0) & (ax < aw) & (ay >= 0) & (ay < ah)
    acc = np.bincount(ay[ok] * aw + ax[ok], minlength=ah * aw).astype(np.float32)
    acc = cv2.GaussianBlur(acc.reshape(ah, aw), (0, 0), 1.5)
    found: list[Circle] = []
    for _ in range(RIM_CANDIDATES):
        y, x = np.unravel_index(int(np.argmax(acc)), acc.shape)
        if acc[y, x] <= 0:
            break
        acc[max(y - 8, 0) : y + 9, max(x - 8, 0) : x + 9] = 0
        cx, cy = float(x - pad), float(y - pad)
        dx, dy = xs - cx, ys - cy
        dist = np.hypot(dx, dy)
        facing = np.abs(dx * nx + dy * ny) >= 0.95 * dist  # normal along the radius
        counts = np.bincount(np.rint(dist[facing]).astype(np.int64), minlength=int(radii[-1]) + 2)
        counts = np.convolve(counts, np.ones(3), "same")[radii.astype(np.int64)] / radii
        found.append((cx, cy, float(radii[int(np.argmax(counts))])))
    return found


def _fit_circle(xy: np.ndarray, start: Circle | None = None) -> tuple[Circle, np.ndarray]:
    """Least-squares circle through points (N, 2), refitted without the far ones; the circle
    and each point's distance to it. With `start`, only the centre is fitted, from `start`'s
    (Gauss-Newton), the radius held at its: a short arc then still places it."""
    keep = np.ones(len(xy), bool)
    circle = start or (0.0, 0.0, 0.0)
    residual = np.zeros(len(xy))
    for _ in range(3):
        if start is None:
            A = np.column_stack([2 * xy[keep], np.ones(int(keep.sum()))])
            (cx, cy, c), *_ = np.linalg.lstsq(A, (xy[keep] ** 2).sum(1), rcond=None)
            circle = (float(cx), float(cy), float(np.sqrt(max(c + cx**2 + cy**2, 0.0))))
        else:
            centre, r = np.array(start[:2]), start[2]
            for _ in range(5):
                offset = xy[keep] - centre
                dist = np.maximum(np.linalg.norm(offset, axis=1, keepdims=True), 1e-9)
                centre = centre - np.linalg.lstsq(-offset / dist, dist[:, 0] - r, rcond=None)[0]
            circle = (float(centre[0]), float(centre[1]), r)
        cx, cy, r = circle
        residual = np.abs(np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) - r)
        keep = residual <= max(3 * float(np.median(residual[keep])), 0.75)
        if keep.sum() < 3:
            break
    return circle, residual


def _check_rim(
    small: np.ndarray,
    lit: np.ndarray,
    circle: Circle,
    fixed_radius: bool = False,
    reach: float = RIM_REACH,
) -> RimFit:
    """`circle` (analysis px) refitted to the frame's edge across it, and how well the frame
    bears it out. In each of `RIM_ANGLES` directions the colour profile across the circle
    (within `RIM_REACH`) is sampled; where it lies in the frame and the lit view `lit` on
    both sides, it is seen; where its two ends differ by `RIM_STEP`, its steepest point is an
    edge. The circle is fitted to those edges; the ones on it support it. Only the lit view
    counts: a fundus camera's dark aperture is the view mask's already. `fixed_radius`: only
    the centre is refitted."""
    h, w = lit.shape
    cx, cy, r = circle
    theta = np.linspace(0.0, 2 * np.pi, RIM_ANGLES, endpoint=False)
    d = np.arange(-reach, reach + 0.25, 0.5, dtype=np.float32)
    cos, sin = np.cos(theta)[:, None], np.sin(theta)[:, None]
    map_x = (cx + (r + d) * cos).astype(np.float32)
    map_y = (cy + (r + d) * sin).astype(np.float32)
    profile = cv2.remap(small, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if profile.ndim == 2:
        profile = profile[..., None]
    ex = np.rint(map_x[:, [0, -1]]).astype(np.int64)
    ey = np.rint(map_y[:, [0, -1]]).astype(np.int64)
    seen = ((ex >= 0) & (ex < w) & (ey >= 0) & (ey < h)).all(1)
    seen[seen] = lit[ey[seen], ex[seen]].all(1)
    n_seen = int(seen.sum())
    n, channels = len(d), profile.shape[2]
    outer, inner = profile[:, n - n // 4 :].mean(1), profile[:, : n // 4].mean(1)
    step = np.linalg.norm(outer - inner, axis=1) / np.sqrt(channels)
    slope = np.linalg.norm(np.diff(profile, axis=1), axis=2)  # (angles, n - 1)
    k = np.argmax(slope, axis=1)
    edges = seen & (k > 0) & (k < n - 2) & (step >= RIM_STEP)  # steepest inside the profile
    if edges.sum() < 8:
        return RimFit(circle, n_seen / len(theta), 0.0, np.inf)
    rows = np.flatnonzero(edges)
    k = k[rows]
    left, mid, right = slope[rows, k - 1], slope[rows, k], slope[rows, k + 1]
    curve = np.minimum(left - 2 * mid + right, -1e-6)  # a maximum: <= 0
    at = (d[k] + d[k + 1]) / 2 + np.clip(0.25 * (left - right) / curve, -0.25, 0.25)  # parabola
    xy = np.stack([cx + (r + at) * cos[rows, 0], cy + (r + at) * sin[rows, 0]], 1)
    fitted, residual = _fit_circle(xy.astype(np.float64), circle if fixed_radius else None)
    on = residual <= RIM_ON_CIRCLE
    support = float(on.sum()) / max(n_seen, 1)
    return RimFit(fitted, n_seen / len(theta), support, float(np.median(residual)))


def _nearer_edge(small: np.ndarray, lit: np.ndarray, circle: Circle) -> Circle:
    """A voted circle (analysis px) refitted to the edge within twice `RIM_REACH` of it: where
    little of a rim is seen the vote may miss it by more than the reach (6 analysis px on
    the first frames of a training-photograph video)."""
    fit = _check_rim(small, lit, circle, reach=2 * RIM_REACH)
    return fit.circle if np.isfinite(fit.residual) else circle


def find_lens_rim(image: np.ndarray, view: np.ndarray, near: Circle | None = None) -> RimFit | None:
    """A handheld lens's rim in a frame (BGR or grey, with its view mask `view`), in the
    frame's pixels: the best circle that `RIM_FIND` (or `RIM_FIND_ARC`) takes, or, near `near`
    (the last frame's rim), one that `RIM_KEEP` does; None where there is none.

    On a copy of at most `RIM_SIDE_PX`, the strongest colour edges vote for circles of
    `RIM_RADII` (`_circle_votes`); `near` and the circles most voted for are refitted to the
    frame's edge across them and checked (`_check_rim`). A rim near `near` that `RIM_FIND`
    takes spares the vote (the rim moves smoothly)."""
    h, w = image.shape[:2]
    s = min(1.0, RIM_SIDE_PX / max(h, w))
    size = (max(round(w * s), 1), max(round(h * s), 1))
    if min(size) < 16:
        return None
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    small = cv2.GaussianBlur(small, (0, 0), 1.0)
    view_small = cv2.resize(view, size, interpolation=cv2.INTER_NEAREST)
    lit = erode_by_disc(view_small, RIM_VIEW_MARGIN, edge_counts=True) > 0

    def checked(circle: Circle, fixed_radius: bool = False) -> RimFit:
        fit = _check_rim(small, lit, circle, fixed_radius)
        if fit.support >= RIM_KEEP.support:  # once more, about the circle it fits
            fit = _check_rim(small, lit, fit.circle, fixed_radius)
        return dataclasses.replace(fit, circle=circle_unscaled(fit.circle, s))

    def is_near(fit: RimFit) -> bool:
        assert near is not None
        (cx, cy, r), (nx, ny, nr) = fit.circle, near
        return np.hypot(cx - nx, cy - ny) <= RIM_NEAR * nr and abs(r - nr) <= RIM_NEAR * nr

    kept = []  # near the last rim, on the weaker evidence
    if near is not None:
        cx, cy = rescaled(np.asarray(near[:2], np.float64), s)
        prior = (cx, cy, near[2] * s)
        fit = checked(prior)
        if fit.found and is_near(fit):
            return fit
        # on weak evidence, the radius is the last rim's (the lens's): a short arc's is loose
        fit = checked(prior, fixed_radius=True)
        kept = [fit] if fit.shows(RIM_KEEP) and is_near(fit) else []
    strength, angle = _rim_gradient(small)
    radii = np.arange(RIM_RADII[0] * size[1], RIM_RADII[1] * size[1] + 1.0)
    votes = _circle_votes(strength, angle, lit, radii)
    found = [checked(_nearer_edge(small, lit, c)) for c in votes]
    taken = [f for f in found if f.found] or kept
    return max(taken, key=lambda f: f.support * f.seen, default=None)


def outside_rim_removed(mask: np.ndarray, circle: Circle, margin_px: float) -> np.ndarray:
    """`mask` (uint8) set to 0 outside the disc of `circle` (cx, cy, r px) shrunk by
    `margin_px`."""
    cx, cy, r = circle
    disc = np.zeros_like(mask)
    scale = 16  # sub-pixel centre and radius (cv2.circle's shift of 4 bits)
    centre = (round(cx * scale), round(cy * scale))
    cv2.circle(disc, centre, max(round((r - margin_px) * scale), 0), 255, -1, cv2.LINE_8, 4)
    return cv2.bitwise_and(mask, disc)


class LensRimMask:
    """Finds a handheld lens's rim in each frame and masks what lies outside it.

    Through a handheld fundus lens (slit lamp, a 20 D lens before a phone) the retina shows
    only inside the lens's rim, a disc that moves about the frame with the hand; around it the
    face, out of focus. Keypoints on the rim and the face match where the hand was, not the
    retina (measured: every frame of a realistic set registered to them). Each frame's rim is
    found (`find_lens_rim`, near where its recent motion puts it: the hand moves it smoothly),
    and the keypoint mask (with it the tracking texture and the blend) is cut to the disc
    shrunk by `MARGIN_PX`. A rim lost for up to `HOLD_FRAMES` frames (blur, a dark view) is
    taken where its motion puts it, shrunk further by how far that may be off. Frames in
    order; a frame of another size starts afresh.
    """

    MARGIN_PX = 3.0  # inside the rim: its soft edge (the features keep their own margin)
    HOLD_FRAMES = 8
    SEARCH_EVERY = 3  # with no rim in sight, every this many frames are searched (~6 ms each)
    SEARCH_FIRST = 8  # ... but every one of the first frames: they anchor the mosaic
    # a held rim's uncertainty grows by this much a frame (px), plus this share of its motion
    HOLD_PX, HOLD_MOTION = 2.0, 0.5

    def __init__(self, config: PreprocessConfig):
        self._config = config
        self._history: deque[tuple[int, Circle]] = deque(maxlen=2)  # (frame, rim) last found
        self._n = 0  # frames taken
        self._searched = -self.SEARCH_EVERY  # the last frame searched in full
        self._shape: tuple[int, ...] | None = None
        self.found: Circle | None = None  # the rim masked in the last frame (working px)
        self.margin_px = self.MARGIN_PX  # its margin

    def _predicted(self) -> tuple[Circle, float] | None:
        """Where the last two rims found put the rim now (moving on as it moved between them),
        and how fast it moves (px a frame); None when none was found in the last
        `HOLD_FRAMES` frames."""
        if not self._history or self._n - self._history[-1][0] > self.HOLD_FRAMES:
            return None
        n1, (x1, y1, r) = self._history[-1]
        if len(self._history) < 2 or n1 - self._history[0][0] > self.HOLD_FRAMES:
            return (x1, y1, r), 0.0
        n0, (x0, y0, _) = self._history[0]
        vx, vy = (x1 - x0) / (n1 - n0), (y1 - y0) / (n1 - n0)
        dt = self._n - n1
        return (x1 + vx * dt, y1 + vy * dt, r), float(np.hypot(vx, vy))

    def __call__(self, image: np.ndarray, prepared: Prepared) -> Prepared:
        """`prepared` without what lies outside the frame's rim (also left in `found`)."""
        self.found = None
        if not self._config.lens_rim_mask:
            return prepared
        if image.shape[:2] != self._shape:
            self._shape, self._n, self._searched = image.shape[:2], 0, -self.SEARCH_EVERY
            self._history.clear()
        self._n += 1
        predicted = self._predicted()
        later = self._n > self.SEARCH_FIRST
        if predicted is None and later and self._n - self._searched < self.SEARCH_EVERY:
            return prepared  # no rim lately: a search now and then is enough
        self._searched = self._n
        fit = find_lens_rim(image, prepared.mask, predicted[0] if predicted else None)
        if fit is not None:
            self._history.append((self._n, fit.circle))
            self.found, self.margin_px = fit.circle, self.MARGIN_PX
        elif predicted is not None:
            lost = self._n - self._history[-1][0]
            self.found = predicted[0]
            self.margin_px = self.MARGIN_PX + lost * (
                self.HOLD_PX + self.HOLD_MOTION * predicted[1]
            )
        if self.found is None:
            return prepared
        mask = outside_rim_removed(prepared.mask, self.found, self.margin_px)
        return Prepared(prepared.gray, mask)
