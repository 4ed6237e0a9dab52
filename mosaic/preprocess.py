"""Fundus pre-processing of the paper (green channel, CLAHE, bilateral) and the field-of-view mask.

The detector sees `Prepared.gray`; keypoints are only kept where `Prepared.mask` is set, so the
dark border around the circular/elliptical view of fundus and slit-lamp frames yields none, nor
(with `camera_fixed.OverlayMask`) burned-in overlays such as a fixation cross, text or a
timestamp, which would otherwise pull every frame to the same place. Also here: the working
size, interlacing, vessel polarity and the blur gate (`FrameGate`).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from mosaic.config import GatingConfig, PreprocessConfig
from mosaic.geometry import circle_unscaled, scale_matrix

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Prepared:
    """A frame ready for detection: enhanced grey image and its valid-pixel mask."""

    gray: np.ndarray  # uint8 HxW
    mask: np.ndarray  # uint8 HxW, 255 inside the field of view


@lru_cache(maxsize=8)
def _clahe(clip_limit: float, tiles: int) -> cv2.CLAHE:
    return cv2.createCLAHE(clipLimit=clip_limit, tileGridSize=(tiles, tiles))


def to_gray(image: np.ndarray, green_channel: bool) -> np.ndarray:
    """Single channel: the green channel of a BGR frame (best vessel contrast) or its luma."""
    if image.ndim == 2:
        return image
    if green_channel:
        return np.ascontiguousarray(image[:, :, 1])
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


DARK_VIEW_FRACTION = 0.25  # the border is at most this fraction of the view's bright level
DARK_VIEW_FLOOR = 3.0  # grey level: nothing is told from the black border below this


def _dark_view_threshold(small: np.ndarray) -> float:
    """A border threshold for an under-exposed view (a dark photograph, low gain: the retina
    itself a few grey levels above the black border, its vessels still visible): a quarter of
    the frame's bright level (its 99th percentile), never under DARK_VIEW_FLOOR."""
    counts = cv2.calcHist([small], [0], None, [256], [0, 256]).ravel().cumsum()
    bright = float(np.searchsorted(counts, 0.99 * counts[-1]))
    return max(DARK_VIEW_FLOOR, DARK_VIEW_FRACTION * bright)


def erode_by_disc(mask: np.ndarray, radius_px: int, edge_counts: bool = False) -> np.ndarray:
    """`mask` (uint8) shrunk by a disc of `radius_px`: what lies at least that far inside it.
    With `edge_counts`, the image's edge is outside too (for what is fixed to the camera, such
    as a descriptor cut by the frame's edge); else the mask continues beyond the edge."""
    if radius_px <= 0:
        return mask
    size = 2 * radius_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    border = 0 if edge_counts else 255
    return cv2.erode(mask, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=border)


def field_of_view_mask(gray: np.ndarray, threshold: int, erode_px: int) -> np.ndarray:
    """Pixels inside the illuminated field of view: the bright region connected to the image.

    A dark border (below `threshold` after light smoothing, or below a quarter of the frame's
    bright level in an under-exposed view) is excluded, and the mask is eroded by
    `erode_px` so detectors do not fire on the edge of the aperture itself. Dark structures inside
    the view (vessels, haemorrhages) stay inside because holes are filled.
    """
    small = cv2.GaussianBlur(gray, (0, 0), 2.0)
    threshold = min(threshold, _dark_view_threshold(small))
    _, mask = cv2.threshold(small, threshold, 255, cv2.THRESH_BINARY)  # small > threshold
    if not mask.any():
        return np.full_like(gray, 255)
    # Fill holes: anything not reachable from the border through dark pixels is inside the view.
    n, labels = cv2.connectedComponents(cv2.bitwise_not(mask), connectivity=4)
    touches_border = np.zeros(n, dtype=bool)
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    touches_border[edge] = True
    touches_border[0] = True  # label 0 is the bright region itself
    if not touches_border.all():  # most frames have no hole: no pass over the labels
        mask[~touches_border[labels]] = 255
    return erode_by_disc(mask, erode_px)


FOV_DISC_THRESHOLD = 15  # grey level separating a fundus image's black border from the retina


def fov_distance(source: np.ndarray, threshold: float = FOV_DISC_THRESHOLD) -> np.ndarray:
    """Distance (px) of every pixel to the black border of a fundus image's field of view.

    The border is found by thresholding at `threshold`; holes (dark lesions, vessels) are
    filled. The map is padded by one pixel (index [y + 1, x + 1]) so the image border also
    counts as outside.
    """
    gray = source if source.ndim == 2 else cv2.cvtColor(source, cv2.COLOR_BGR2GRAY)
    mask = (cv2.GaussianBlur(gray, (0, 0), 2.0) > threshold).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(1 - mask, connectivity=4)
    h, w = mask.shape
    x0, y0 = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    x1, y1 = x0 + stats[:, cv2.CC_STAT_WIDTH], y0 + stats[:, cv2.CC_STAT_HEIGHT]
    is_hole = (x0 > 0) & (y0 > 0) & (x1 < w) & (y1 < h)
    is_hole[0] = False  # label 0: the bright region itself
    mask[is_hole[labels]] = 1
    return cv2.distanceTransform(np.pad(mask, 1), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def estimate_fov_disc(source: np.ndarray) -> tuple[float, float, float]:
    """Largest disc (cx, cy, r) inside the illuminated field of view of a fundus image.

    The maximum of the distance to the view's border gives the largest inscribed disc — also
    correct for fundus images whose circular view is clipped at the top and bottom.
    """
    dist = fov_distance(source)
    iy, ix = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return float(ix - 1), float(iy - 1), float(dist[iy, ix])


DISC_ANALYSIS_SIDE_PX = 512  # the disc is estimated on a copy of at most this longer side
DISC_CORNER_SIDE = 1 / 16  # the corner squares whose level is the black border's, in image sides
DISC_ABOVE_BORDER = 4.0  # grey levels above the border's that count as retina
DISC_MIN_ARC = 0.5  # share of the circle's directions the view's dark border must show
DISC_MAX_RESIDUAL = 0.03  # median distance of the border to the fitted circle, in radii


def retina_disc(image: np.ndarray) -> tuple[float, float, float] | None:
    """The field-of-view disc (cx, cy, r) in pixels when the image shows a whole retina (a
    fundus photograph: a bright disc, possibly clipped at the top and bottom, ringed by a dark
    border), None when the view runs to the image's edges (magnified, slit-lamp, AO frames).

    A circle is fitted (least squares, then again without outlying points) to the border of
    the field of view inside the image (`fov_distance`, on a copy of at most
    `DISC_ANALYSIS_SIDE_PX`); it is the retina when that border is seen in at least
    `DISC_MIN_ARC` of the directions around the centre and lies on the circle.
    """
    h, w = image.shape[:2]
    s = min(1.0, DISC_ANALYSIS_SIDE_PX / max(h, w))
    small = image
    if s < 1.0:
        small = cv2.resize(image, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    mask = (fov_distance(small, _border_threshold(small))[1:-1, 1:-1] > 0).astype(np.uint8)
    edge = mask - cv2.erode(mask, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    ys, xs = np.nonzero(edge)
    if len(xs) < 20:
        return None
    xy = np.stack([xs, ys], 1).astype(np.float64)
    keep = np.ones(len(xy), bool)
    for _ in range(2):  # x^2 + y^2 = 2 cx x + 2 cy y + c, then without the far points
        A = np.column_stack([2 * xy[keep], np.ones(int(keep.sum()))])
        (cx, cy, c), *_ = np.linalg.lstsq(A, (xy[keep] ** 2).sum(1), rcond=None)
        r = float(np.sqrt(max(c + cx**2 + cy**2, 0.0)))
        residual = np.abs(np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) - r)
        keep = residual <= max(3 * np.median(residual[keep]), 1.5)
    angle = np.arctan2(xy[keep, 1] - cy, xy[keep, 0] - cx)
    bins = np.unique(np.floor((angle + np.pi) / (2 * np.pi) * 36).astype(int) % 36)
    if (
        r < 8
        or len(bins) < DISC_MIN_ARC * 36
        or np.median(residual[keep]) > DISC_MAX_RESIDUAL * r
        or not mask[int(np.clip(cy, 0, mask.shape[0] - 1)), int(np.clip(cx, 0, mask.shape[1] - 1))]
    ):
        return None
    return circle_unscaled((cx, cy, r), s)


def _border_threshold(image: np.ndarray) -> float:
    """The grey level between a fundus photograph's black border and its retina: halfway
    between the level of the image's corners (outside the field of view of a whole retina) and
    the retina's darkest (its 5th percentile), at most FOV_DISC_THRESHOLD; a dark photograph's
    retina, only a few grey levels above its border towards the rim, then still counts."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    gray = cv2.GaussianBlur(gray, (0, 0), 2.0)
    k = max(int(min(gray.shape) * DISC_CORNER_SIDE), 1)
    corners = np.concatenate(
        [c.ravel() for c in (gray[:k, :k], gray[:k, -k:], gray[-k:, :k], gray[-k:, -k:])]
    )
    border = float(np.percentile(corners, 95))
    retina = gray[gray > border + DISC_ABOVE_BORDER]
    if retina.size == 0:
        return FOV_DISC_THRESHOLD
    middle = (border + float(np.percentile(retina, 5))) / 2
    return min(FOV_DISC_THRESHOLD, max(DARK_VIEW_FLOOR, middle))


def working_scale(image: np.ndarray, max_side_px: int, fov_diameter_px: int = 0) -> float:
    """Scale (<= 1) of the image registration runs on: the retina's diameter brought to
    `fov_diameter_px` (the scale the detector was trained at) when the image shows a whole
    retina (`retina_disc`), else the longer side brought to `max_side_px`; 0 turns either off."""
    disc = retina_disc(image) if fov_diameter_px > 0 else None
    return _scale_for(image.shape, disc, max_side_px, fov_diameter_px)


Disc = tuple[float, float, float]  # (cx, cy, r) px: a retina's field of view (`retina_disc`)


def pair_working_scales(
    a: np.ndarray,
    b: np.ndarray,
    max_side_px: int,
    fov_diameter_px: int = 0,
    discs: tuple[Disc | None, Disc | None] | None = None,
) -> tuple[float, float]:
    """`working_scale` of two photographs of one eye, except that when they are the same size
    and only one shows a whole retina, both take its scale: the same camera shows the retina at
    the same size, and a disc missed in one photograph (glare on its rim, a bright border) must
    not have the two registered at different scales. `discs`: their `retina_disc`s, when the
    caller has them already."""
    if discs is None:
        discs = (retina_disc(a), retina_disc(b)) if fov_diameter_px > 0 else (None, None)
    if a.shape[:2] == b.shape[:2] and (discs[0] is None) != (discs[1] is None):
        discs = (discs[0] or discs[1],) * 2
    return (
        _scale_for(a.shape, discs[0], max_side_px, fov_diameter_px),
        _scale_for(b.shape, discs[1], max_side_px, fov_diameter_px),
    )


def _scale_for(
    shape: tuple[int, ...],
    disc: Disc | None,
    max_side_px: int,
    fov_diameter_px: int,
) -> float:
    if fov_diameter_px > 0 and disc is not None:
        return min(1.0, fov_diameter_px / (2 * disc[2]))
    h, w = shape[:2]
    if max_side_px <= 0 or max(h, w) <= max_side_px:
        return 1.0
    return max_side_px / max(h, w)


def to_working_size(
    image: np.ndarray, max_side_px: int, fov_diameter_px: int = 0
) -> tuple[np.ndarray, np.ndarray | None]:
    """The frame resized to its working size (`working_scale`: with the default
    `fov_diameter_px` = 0, its longer side at most `max_side_px`), and H_frame_to_work (None
    when it is unchanged).

    Registration runs at a working resolution near the one the detector was trained and the
    pixel-valued settings were chosen at (descriptor size, NMS window, RANSAC threshold, ...),
    so that a camera with 2x the pixels sees the same structures at the same scale, and is not
    4x slower. A fundus photograph is sized by its retina, not by its file: a 2912 px photograph
    whose retina spans 2700 px and a 640 px one whose retina spans 500 px then look alike.
    """
    return resize_by(image, working_scale(image, max_side_px, fov_diameter_px))


def resize_by(image: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray | None]:
    """The image resized by `scale` (< 1; INTER_AREA) and H_image_to_resized, or the image
    itself and None when `scale` >= 1."""
    if scale >= 1.0:
        return image, None
    h, w = image.shape[:2]
    size = (max(round(w * scale), 1), max(round(h * scale), 1))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return small, scale_matrix(image.shape, small.shape)


POLARITY_SIDE_PX = 600  # the polarity is measured on a copy of at most this longer side
POLARITY_TOPHAT_PX = 15  # top-hat element there: wider than a vessel, narrower than the optic disc
POLARITY_MIN_QUOTIENT = 1.3  # two photographs' polarities this far apart are different modalities
POLARITY_DEAD_BAND = 0.05  # a polarity within this of 1 tells neither kind


def vessel_polarity(image: np.ndarray) -> float:
    """How much darker than bright the image's thin structures are: the 95th percentile of
    the black top-hat of the green channel over that of the white top-hat, inside the view.
    Above 1 the vessels are dark (colour and red-free photographs: 1.06-1.8 on the training
    pairs), below 1 bright (fluorescein angiograms: 0.42-0.96)."""
    gray = to_gray(image, True)
    s = min(1.0, POLARITY_SIDE_PX / max(gray.shape))
    if s < 1.0:
        gray = cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    size = POLARITY_TOPHAT_PX
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    inside = erode_by_disc(field_of_view_mask(gray, FOV_DISC_THRESHOLD, 0), size, True) > 0
    if inside.sum() < size * size:
        return 1.0
    dark = cv2.morphologyEx(gray, cv2.MORPH_BLACKHAT, kernel)[inside]
    bright = cv2.morphologyEx(gray, cv2.MORPH_TOPHAT, kernel)[inside]
    return float(np.percentile(dark, 95) + 1.0) / float(np.percentile(bright, 95) + 1.0)


FIELD_MIN_ROWS = 16  # frames with fewer rows are not tested
FIELD_MAX_PX = 384  # the fields are compared on at most this many (field) rows and columns
PHASE_TAPER = 0.15  # cycles / px: sd of the Gaussian weighting the phase correlation's spectrum


def field_offset(image: np.ndarray) -> tuple[float, float]:
    """Where (dx, dy px) a frame's odd rows lie relative to its even rows, beyond the row
    between them.

    An interlaced camera reads the odd rows (its second field) half a frame interval after the
    even ones, so a moving view is combed: the fields are offset by half the motion between
    frames. A progressive frame gives ~(0, 0). Phase correlation of the two fields over the
    frame's middle half: borders and burned-in overlays are fixed to the camera and would pull
    it to 0.
    """
    h, w = image.shape[:2]
    if h < FIELD_MIN_ROWS or w < FIELD_MIN_ROWS:
        return 0.0, 0.0
    n = h // 2
    # the middle half of the field rows, at most FIELD_MAX_PX a side about the centre (large
    # frames: the same offset, a fraction of the work), cut from the frame before anything
    fh, fw = min(n // 2, FIELD_MAX_PX), min(w // 2, FIELD_MAX_PX)
    r0 = n // 4 + (n // 2 - fh) // 2
    c0 = w // 4 + (w // 2 - fw) // 2
    crop = image[2 * r0 : 2 * (r0 + fh) + 1, c0 : c0 + fw]
    gray = to_gray(crop, False).astype(np.float32)  # luma: the offset is geometry
    first, second = gray[0::2], gray[1::2]
    # the first field halfway between its rows: the second field's rows (frame rows 2k + 1),
    # so that a progressive frame correlates at 0 (a half-row shift is ambiguous to measure)
    first = (first[:-1] + first[1:]) / 2
    second = second[: len(first)]
    dx, dy = _phase_shift(first, second)
    return dx, 2.0 * dy  # a field row is two frame rows


def _phase_shift(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The shift (dx, dy px) of `b` against `a` by phase correlation: the peak of the
    normalised cross-power spectrum's inverse, refined by a parabola through it and its
    neighbours along each axis (OpenCV's centroid is biased by up to a pixel on smooth images)."""
    window = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_32F)
    fa = np.fft.rfft2((a - a.mean()) * window)
    fb = np.fft.rfft2((b - b.mean()) * window)
    cross = fb * np.conj(fa)
    # whitened, then tapered: frequencies the image lacks carry only noise and quantisation
    fy = np.fft.fftfreq(a.shape[0])[:, None]
    fx = np.fft.rfftfreq(a.shape[1])[None, :]
    taper = np.exp(-(fx**2 + fy**2) / (2 * PHASE_TAPER**2))
    surface = np.fft.irfft2(cross / np.maximum(np.abs(cross), 1e-9) * taper, s=a.shape)
    py, px = np.unravel_index(int(np.argmax(surface)), surface.shape)
    h, w = surface.shape

    def vertex(left: float, centre: float, right: float) -> float:
        curvature = left - 2 * centre + right
        return 0.0 if curvature >= 0 else 0.5 * (left - right) / curvature

    dx = px + vertex(surface[py, px - 1], surface[py, px], surface[py, (px + 1) % w])
    dy = py + vertex(surface[py - 1, px], surface[py, px], surface[(py + 1) % h, px])
    return float((dx + w / 2) % w - w / 2), float((dy + h / 2) % h - h / 2)


def first_field(image: np.ndarray) -> np.ndarray:
    """The frame's first field alone, at full size: each odd row the mean of the even rows
    around it (the last copies its neighbour). Moving the second field onto the first by its
    measured offset instead kept 3-4 px of pose error on clean interlaced test videos (the
    fields also differ by rotation and zoom), the first field alone the progressive video's
    0.6-0.9 px."""
    out = image.copy()
    even = image[0::2].astype(np.float32)
    n_odd = image[1::2].shape[0]
    below = np.concatenate([even[1:], even[-1:]])[:n_odd]
    out[1::2] = np.rint((even[:n_odd] + below) / 2).astype(image.dtype)  # within the range
    return out


class Deinterlacer:
    """Interlacing, frame by frame: each frame's field offset is measured (`field_offset`), and
    with `on` (`[preprocess] deinterlace`: the camera is interlaced) the frame is replaced by
    its first field (`first_field`): the combing goes, and every frame takes its first field's
    pose. Off, the offsets only say whether the video looks interlaced (`looks_interlaced`:
    their median above `INTERLACED_PX`). Measured medians: 0.2-0.75 px on 16 progressive
    realistic videos, 0.05-0.18 px on the sample and the two SLO clips, 1.9 px on the
    adaptive-optics clip (constant: a scanner's line offset or its cones' pattern), 0.6-5.1 px
    on 24 interlaced realistic videos (half the motion between frames). Whether deinterlacing
    pays depends on the view's sharpness more than on the offset (docs/evaluation.md), so it
    is not automatic."""

    INTERLACED_PX = 2.0

    def __init__(self, on: bool = False) -> None:
        self.on = on
        self.offsets_px: list[float] = []

    def __call__(self, image: np.ndarray) -> tuple[np.ndarray, bool]:
        """The frame (its first field alone when on) and whether it was deinterlaced."""
        self.offsets_px.append(float(np.hypot(*field_offset(image))))
        return (first_field(image), True) if self.on else (image, False)

    @property
    def median_offset_px(self) -> float | None:
        return float(np.median(self.offsets_px)) if self.offsets_px else None

    @property
    def looks_interlaced(self) -> bool:
        median = self.median_offset_px
        return median is not None and median > self.INTERLACED_PX


def invert_in_view(image: np.ndarray) -> np.ndarray:
    """The image with its grey levels inverted inside its field of view (bright vessels made
    dark); the black border around the view stays black."""
    view = field_of_view_mask(to_gray(image, True), FOV_DISC_THRESHOLD, 0) > 0
    out = image.copy()
    out[view] = 255 - image[view]
    return out


def pair_polarities(a: np.ndarray, b: np.ndarray) -> tuple[bool, bool]:
    """Which of two photographs of an eye to invert (`invert_in_view`) so that both show dark
    vessels: the one with bright vessels when the other's are dark, each clearly (outside
    `POLARITY_DEAD_BAND` of 1), and their polarities (`vessel_polarity`) differ by at least
    `POLARITY_MIN_QUOTIENT` (a colour photograph and an angiogram); neither otherwise, as for
    two photographs of one kind. The detector was trained on dark vessels, and the descriptors
    of a structure and of its negative do not match."""
    pa, pb = vessel_polarity(a), vessel_polarity(b)
    low, high = min(pa, pb), max(pa, pb)
    if low > 1 - POLARITY_DEAD_BAND or high < 1 + POLARITY_DEAD_BAND:
        return False, False
    if high < POLARITY_MIN_QUOTIENT * low:
        return False, False
    return pa < pb, pb < pa


def inverted_as(
    fixed: np.ndarray, moving: np.ndarray, invert: tuple[bool, bool]
) -> tuple[np.ndarray, np.ndarray]:
    """The pair with the photographs `invert` names (fixed, moving) inverted in their view."""
    a, b = (invert_in_view(im) if i else im for im, i in zip((fixed, moving), invert, strict=True))
    return a, b


def prepare(image: np.ndarray, config: PreprocessConfig) -> Prepared:
    """Apply the configured pre-processing to one BGR (or grey) uint8 frame."""
    gray = to_gray(image, config.green_channel)
    if config.fov_mask:
        mask = field_of_view_mask(gray, config.fov_threshold, config.fov_erode_px)
    else:
        mask = np.full(gray.shape, 255, np.uint8)
    if config.clahe:
        gray = _clahe(config.clahe_clip_limit, config.clahe_tile_grid).apply(gray)
    if config.bilateral:
        gray = cv2.bilateralFilter(
            gray,
            config.bilateral_diameter_px,
            config.bilateral_sigma_color,
            config.bilateral_sigma_space,
        )
    return Prepared(gray=gray, mask=mask)


def sharpness(prepared: Prepared) -> float:
    """Variance of the Laplacian inside the field of view (at half resolution): blur lowers it."""
    small = cv2.pyrDown(prepared.gray)
    mask = cv2.resize(prepared.mask, (small.shape[1], small.shape[0]), cv2.INTER_NEAREST) > 0
    if not mask.any():
        return 0.0
    return float(cv2.Laplacian(small, cv2.CV_32F)[mask].var())


@dataclass(frozen=True)
class Gate:
    """The gate's verdict on a frame: why to skip it, or why it is too blurred to blend."""

    skip: str | None = None
    blurred: str | None = None  # registered all the same (`[gating] blurred = "track"`)


class FrameGate:
    """Skips frames not worth registering (too little field of view) and finds those too
    blurred to blend (relative to recent frames): skipped too, or only kept out of the blend.

    Blur is judged against the median sharpness of recent accepted frames, not an absolute
    threshold, so the same setting works across cameras, resolutions and contrast.
    """

    HISTORY = 15
    MIN_HISTORY = 5

    def __init__(self, config: GatingConfig):
        self._config = config
        self._recent: deque[float] = deque(maxlen=self.HISTORY)

    def __call__(self, prepared: Prepared) -> Gate:
        """Whether to skip the frame, or to register it without blending it."""
        if not self._config.enabled:
            return Gate()
        fov = float(np.count_nonzero(prepared.mask)) / prepared.mask.size
        if fov < self._config.min_fov_fraction:
            limit = self._config.min_fov_fraction
            return Gate(skip=f"too little field of view ({fov:.0%} < {limit:.0%})")
        value = sharpness(prepared)
        if len(self._recent) >= self.MIN_HISTORY:
            median = float(np.median(self._recent))
            if value < self._config.min_sharpness_ratio * median:
                reason = (
                    f"too blurred (sharpness {value:.0f} < {self._config.min_sharpness_ratio}"
                    f" x recent median {median:.0f})"
                )
                if self._config.blurred == "skip":
                    return Gate(skip=reason)
                return Gate(blurred=reason)
        self._recent.append(value)
        return Gate()
