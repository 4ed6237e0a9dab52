"""Structures fixed to the camera, masked so that no keypoint on them pulls frames together:
burned-in overlays (a fixation cross, text, a timestamp: pixels that never change,
`OverlayMask`), lens reflexes (bright spots that stay in one place of the frame while the
retina moves, `ReflexMask`) and the camera's dark surround when haze or glare lifts it
(`SurroundMask`)."""

from __future__ import annotations

import zlib
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from mosaic.config import PreprocessConfig
from mosaic.preprocess import Prepared, to_gray


class OverlayMask:
    """Finds pixels that stay the same in every frame so far (burned-in overlays) and masks them.

    A per-pixel running minimum and maximum of the grey frames (before enhancement); once
    `MIN_FRAMES` frames are seen, connected shapes of at least `MIN_AREA_PX` pixels whose range
    is at most `overlay_max_range` grey levels and that stand out from their surroundings by at
    least `MIN_CONTRAST` grey levels, grown by `overlay_margin_px`, are taken out of the
    keypoint mask (a flat patch of retina in a slowly moving view is static for a while too, but
    looks like what surrounds it; a drawn cross or text does not). If they cover more than
    `MAX_FRACTION` of the frame, the camera (not an overlay) is static and nothing is masked.
    Frames must come in order; a frame of another size starts afresh.
    """

    MIN_FRAMES = 5
    REFRESH_FRAMES = 10  # frames between two searches for static shapes
    MIN_AREA_PX = 50  # smallest connected static shape taken for an overlay
    MAX_FRACTION = 0.2
    MIN_CONTRAST = 20.0  # grey levels between a static shape and the ring of pixels around it
    RING_PX = 7  # width of that ring

    def __init__(self, config: PreprocessConfig):
        self._config = config
        self._lo: np.ndarray | None = None
        self._hi: np.ndarray | None = None
        self._n = 0
        self._static: np.ndarray | None = None  # the overlay (bool HxW) as last found
        self._static_at = -1  # frame count when it was found
        self._last: np.ndarray | None = None  # latest grey frame

    def __call__(self, image: np.ndarray, prepared: Prepared) -> Prepared:
        """Take `image` (BGR or grey) into the history; `prepared` without its static pixels."""
        if not self._config.overlay_mask:
            return prepared
        gray = to_gray(image, self._config.green_channel)
        self._last = gray
        if self._lo is None or self._hi is None or self._lo.shape != gray.shape:
            self._lo, self._hi, self._n, self._static_at = gray.copy(), gray.copy(), 0, -1
        else:
            np.minimum(self._lo, gray, out=self._lo)
            np.maximum(self._hi, gray, out=self._hi)
        self._n += 1
        # the static set only shrinks as frames come: refreshing it now and then is enough
        stale = self._static_at < 0 or self._n - self._static_at >= self.REFRESH_FRAMES
        return self._masked(prepared, refresh=stale)

    def apply(self, prepared: Prepared) -> Prepared:
        """`prepared` without the overlay found in all frames so far (e.g. the whole video)."""
        return self._masked(prepared, refresh=self._static_at != self._n)

    def _masked(self, prepared: Prepared, refresh: bool) -> Prepared:
        if (
            not self._config.overlay_mask
            or self._lo is None
            or self._lo.shape != prepared.mask.shape
            or self._n < self.MIN_FRAMES
        ):
            return prepared
        if refresh:
            self._static = self._find_static(prepared.mask)
            self._static_at = self._n
        if self._static is None:
            return prepared
        return Prepared(prepared.gray, cleared(prepared.mask, self._static))

    def _find_static(self, fov: np.ndarray) -> np.ndarray | None:
        """Overlay pixels inside the view `fov` (with their margin), or None when there is none
        or the camera itself is static."""
        assert self._lo is not None and self._hi is not None
        static = (self._hi - self._lo) <= self._config.overlay_max_range  # uint8: hi >= lo
        static &= fov > 0
        # an overlay is a solid shape; pixels that merely have not changed yet are scattered
        n, labels, stats, _ = cv2.connectedComponentsWithStats(static.view(np.uint8), 8)
        big = stats[:, cv2.CC_STAT_AREA] >= self.MIN_AREA_PX
        big[0] = False  # background label
        big &= self._contrast(labels, n, fov) >= self.MIN_CONTRAST
        static = big[labels]
        r = self._config.overlay_margin_px
        if r > 0 and static.any():
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            static = cv2.dilate(static.view(np.uint8), kernel).astype(bool)
        if not static.any() or static.mean() > self.MAX_FRACTION:
            return None
        return static

    def _contrast(self, labels: np.ndarray, n: int, fov: np.ndarray) -> np.ndarray:
        """Per label: |mean grey of the shape - mean grey of the ring around it| (latest frame)."""
        assert self._last is not None
        grey = self._last.astype(np.float64).ravel()
        k = 2 * self.RING_PX + 1
        # each ring pixel takes the largest label within RING_PX (shapes rarely touch)
        grown = cv2.dilate(labels.astype(np.float32), np.ones((k, k), np.uint8)).astype(np.int64)
        ring = ((labels == 0) & (grown > 0) & (fov > 0)).ravel()
        inside = (labels > 0).ravel()

        def mean_per_label(where: np.ndarray, lab: np.ndarray) -> np.ndarray:
            total = np.bincount(lab.ravel()[where], grey[where], minlength=n)
            count = np.bincount(lab.ravel()[where], minlength=n)
            return np.divide(total, count, out=np.full(n, np.nan), where=count > 0)

        diff = np.abs(mean_per_label(inside, labels) - mean_per_label(ring, grown))
        return np.nan_to_num(diff, nan=0.0)  # no ring (a shape filling the view): not an overlay


def _elongation(labels: np.ndarray, n: int) -> np.ndarray:
    """Per label of a labelled image: the ratio of its long axis to its short one (second
    moments; inf for a line one pixel wide)."""
    ys, xs = np.nonzero(labels)
    lab = labels[ys, xs]
    count = np.maximum(np.bincount(lab, minlength=n), 1)

    def mean(v: np.ndarray) -> np.ndarray:
        return np.bincount(lab, v, minlength=n) / count

    mx, my = mean(xs.astype(np.float64)), mean(ys.astype(np.float64))
    cxx = mean(xs.astype(np.float64) ** 2) - mx**2 + 1 / 12  # + a pixel's own extent
    cyy = mean(ys.astype(np.float64) ** 2) - my**2 + 1 / 12
    cxy = mean(xs.astype(np.float64) * ys) - mx * my
    half_gap = np.sqrt(((cxx - cyy) / 2) ** 2 + cxy**2)
    long, short = (cxx + cyy) / 2 + half_gap, (cxx + cyy) / 2 - half_gap
    return np.sqrt(long / np.maximum(short, 1e-12))


def _grown(shapes: np.ndarray, r: int) -> np.ndarray:
    """The bool image `shapes` dilated by a disc of radius `r`, as uint8 (dilating only the box
    around them: a fraction of a full frame's cost)."""
    x, y, w, h = cv2.boundingRect(shapes.view(np.uint8))
    x0, y0 = max(x - r, 0), max(y - r, 0)
    x1, y1 = min(x + w + r, shapes.shape[1]), min(y + h + r, shapes.shape[0])
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    out = np.zeros(shapes.shape, np.uint8)
    out[y0:y1, x0:x1] = cv2.dilate(shapes[y0:y1, x0:x1].view(np.uint8), disc)
    return out


class SurroundMask:
    """Remembers the camera's dark surround (outside its aperture) and keeps it out of frames
    whose haze or glare lifts it.

    Haze (scattered light) or glare can lift the surround above `fov_threshold`: the frame's
    view mask then covers it, and the only structure left on a faint frame is the aperture's
    edge, fixed to the camera, which registrations lock onto (zero motion, 20-50 inliers).
    The surround is the pixels outside the view mask in at least `SHARE` of the frames so far
    (from `MIN_FRAMES` frames on) and in the last frame counted, so a dark border that moves
    with the retina is let go as soon as a frame shows it inside. A frame in which more than
    `LIFTED` of the surround, at least `MIN_AREA` of the frame, shows as inside is lifted: the
    surround is taken out of its mask and the frame is not counted. Other frames are left as
    they are. After `MAX_LIFTED` lifted frames in a row the view has changed for good and the
    history starts again. Frames must come in order; a frame of another size starts afresh."""

    MIN_FRAMES = 5
    SHARE = 0.9
    LIFTED = 0.5
    MIN_AREA = 0.02
    MAX_LIFTED = 50

    def __init__(self, config: PreprocessConfig):
        self._enabled = config.surround_mask and config.fov_mask
        self._dark: np.ndarray | None = None  # (H, W) uint32: frames each pixel was outside
        self._n = 0  # frames counted
        self._lifted_run = 0
        self._surround: np.ndarray | None = None  # bool (H, W), None when there is none
        self._area = 0  # its pixels
        self.lifted: np.ndarray | None = None  # the surround taken out of the last frame

    def __call__(self, prepared: Prepared) -> Prepared:
        """Count the frame, or, when its surround is lifted, take the surround out of it."""
        self.lifted = None
        if not self._enabled:
            return prepared
        outside = prepared.mask == 0
        if self._dark is None or self._dark.shape != outside.shape:
            self._dark = np.zeros(outside.shape, np.uint32)
            self._n, self._lifted_run, self._surround = 0, 0, None
        if self._is_lifted(outside):
            self._lifted_run += 1
            if self._lifted_run <= self.MAX_LIFTED:
                self.lifted = self._surround
                return Prepared(prepared.gray, cleared(prepared.mask, self.lifted))
            self._dark[:] = 0  # not a lifted surround: a new view
            self._n = 0
        self._lifted_run = 0
        self._dark += outside
        self._n += 1
        self._surround = None
        if self._n >= self.MIN_FRAMES:
            surround = (self._dark >= self.SHARE * self._n) & outside
            self._area = np.count_nonzero(surround)
            if self._area >= self.MIN_AREA * surround.size:
                self._surround = surround
        return prepared  # its own mask holds the surround already

    def _is_lifted(self, outside: np.ndarray) -> bool:
        surround = self._surround
        if surround is None:
            return False
        return np.count_nonzero(surround & ~outside) > self.LIFTED * self._area


def cleared(mask: np.ndarray, where: np.ndarray) -> np.ndarray:
    """A uint8 view mask set to 0 where `where` (bool) holds: what is fixed to the camera out."""
    return np.where(where, np.uint8(0), mask)


class ReflexMask:
    """Finds lens reflexes (bright spots fixed to the camera) in the recent frames and masks them.

    A reflex of the fundus lens stays near one place of the frame (it wanders a few px, its
    brightness flickers) while the retina moves under it; points on its steep edge match
    where the camera was, and tracking windows that hold it are pulled the same way (measured:
    three reflexes double a realistic clip's error). Per pixel, the minimum over the last
    `WINDOW` frames of how far it is above its surroundings (grey frames before enhancement):
    where that stays at least `reflex_brightness` in compact shapes (at most `MAX_FRACTION` of
    the view each, round or oval, where they were `STEADY_FRAMES` before), something bright
    has stayed there while the view moved; those shapes, grown by `overlay_margin_px` +
    `REACH_PX`, leave the keypoint mask. Retinal bright spots (the optic disc, exudates) move
    with the retina and drop out of the minimum; while the camera is still, everything stays,
    which then costs nothing (the frames do not move). Frames in order; a frame of another size
    starts afresh.
    """

    WINDOW = 12  # frames a reflex must stay bright in
    # A thick bright vessel that the view moves along stays bright at its pixels for a while too,
    # but the place where it does moves: a reflex's shape must overlap, by half its area, the
    # one found this many frames before
    STEADY_FRAMES = 3
    # Beyond the shape found (where the reflex stayed) it still shows this far: its wander and
    # its glow (a realistic clip with three reflexes: 6 px left 1.04 px of error, 14 px 0.52,
    # 24 px 0.62; 0.43 without reflexes)
    REACH_PX = 14
    MIN_AREA_PX = 12  # smallest shape taken for a reflex
    MAX_FRACTION = 0.03  # largest one, as a share of the view: larger is retina, not a spot
    SURROUNDINGS_PX = 84  # side of the neighbourhood a reflex is brighter than
    # A bright vessel that the view moves along stays at the same pixels too, but as a line:
    # reflexes are round or oval (long axis at most this x the short one)
    MAX_ELONGATION = 4.0

    def __init__(self, config: PreprocessConfig):
        self._config = config
        self._recent: deque[np.ndarray] = deque(maxlen=self.WINDOW)
        self._lasting: deque[np.ndarray] = deque(maxlen=self.STEADY_FRAMES + 1)
        self.found: Spots | None = None  # the reflexes masked in the last frame
        self._kept: Spots | None = None  # the last reflexes found

    @classmethod
    def _surroundings(cls, gray: np.ndarray, inside: np.ndarray) -> np.ndarray:
        """The grey level around each pixel: a median over ~`SURROUNDINGS_PX` (at a quarter of
        the size), which a spot smaller than half of it does not raise, and which follows
        vignetting and illumination. Outside the view (`inside` False) stands the view's
        median: the dark border must not make the retina next to it look bright."""
        h, w = gray.shape
        filled = np.where(inside, gray, np.uint8(np.median(gray[inside])))
        size = (max(w // 4, 1), max(h // 4, 1))
        small = cv2.resize(filled, size, interpolation=cv2.INTER_AREA)
        k = cls.SURROUNDINGS_PX // 4 | 1
        return cv2.resize(cv2.medianBlur(small, k), (w, h), interpolation=cv2.INTER_LINEAR)

    def __call__(self, image: np.ndarray, prepared: Prepared) -> Prepared:
        """Take `image` (BGR or grey) into the history; `prepared` without the reflexes (also
        left in `found`)."""
        self.found = None
        if not self._config.reflex_mask:
            return prepared
        gray = to_gray(image, self._config.green_channel)
        if self._recent and self._recent[0].shape != gray.shape:
            self._recent.clear()
            self._lasting.clear()
        inside = prepared.mask > 0
        if not inside.any():
            return prepared
        self._recent.append(cv2.subtract(gray, self._surroundings(gray, inside)))
        if len(self._recent) < self.WINDOW:
            return prepared
        lasting = np.minimum.reduce(self._recent) >= self._config.reflex_brightness
        lasting &= inside
        self._lasting.append(lasting)
        if len(self._lasting) <= self.STEADY_FRAMES or not lasting.any():
            return prepared
        _, labels, stats, _ = cv2.connectedComponentsWithStats(lasting.view(np.uint8), 8)
        area = stats[:, cv2.CC_STAT_AREA]
        spot = (area >= self.MIN_AREA_PX) & (area <= self.MAX_FRACTION * inside.sum())
        spot &= _elongation(labels, len(area)) <= self.MAX_ELONGATION
        before = np.bincount(labels[self._lasting[0]], minlength=len(area))
        spot &= before >= area / 2
        spot[0] = False  # background label
        if not spot.any():
            return prepared
        reflex = _grown(spot[labels], self._config.overlay_margin_px + self.REACH_PX)
        found = Spots.of(reflex)
        # the same as the last frame's (common: a reflex holds still): one object for both, so
        # a long video keeps one copy per change, not per frame
        self.found = self._kept = self._kept if found == self._kept else found
        return Prepared(prepared.gray, cleared(prepared.mask, reflex > 0))


@dataclass(frozen=True)
class Spots:
    """Pixels of one frame to leave out (its lens reflexes), kept small for the re-render: the
    corner of their bounding box and the box's bits, compressed (mostly zeros: a few hundred
    bytes a frame)."""

    x: int
    y: int
    size: tuple[int, int]  # (height, width) of the box
    bits: bytes  # zlib of np.packbits of the box, row-major

    @classmethod
    def of(cls, mask: np.ndarray) -> Spots:
        """The nonzero pixels of `mask` (one nonzero at least)."""
        x, y, w, h = cv2.boundingRect(mask)
        packed = np.packbits(mask[y : y + h, x : x + w] > 0).tobytes()
        return cls(x, y, (h, w), zlib.compress(packed, 1))

    def removed_from(self, mask: np.ndarray) -> np.ndarray:
        """`mask` with these pixels set to 0."""
        (h, w), x, y = self.size, self.x, self.y
        packed = np.frombuffer(zlib.decompress(self.bits), np.uint8)
        box = np.unpackbits(packed, count=h * w).reshape(h, w).astype(bool)
        out = mask.copy()
        out[y : y + h, x : x + w][box] = 0
        return out
