"""Fundus pre-processing of the paper (green channel, CLAHE, bilateral) and the field-of-view mask.

The detector sees `Prepared.gray`; keypoints are only kept where `Prepared.mask` is set, so the
dark border around the circular/elliptical view of fundus and slit-lamp frames yields none, nor
(with `OverlayMask`) burned-in overlays such as a fixation cross, text or a timestamp, which
would otherwise pull every frame to the same place.
"""

from __future__ import annotations

import dataclasses
import logging
import zlib
from collections import deque
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from mosaic.config import GatingConfig, PreprocessConfig
from mosaic.geometry import rescaled, scale_matrix

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
    return (cx + 0.5) / s - 0.5, (cy + 0.5) / s - 0.5, r / s


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
        return Prepared(prepared.gray, np.where(self._static, np.uint8(0), prepared.mask))

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
        return Prepared(prepared.gray, np.where(reflex > 0, np.uint8(0), prepared.mask))


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


# --------------------------------------------------------------------------------------------
# A handheld lens's rim
# --------------------------------------------------------------------------------------------

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
    small: np.ndarray, lit: np.ndarray, circle: Circle, fixed_radius: bool = False
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
    d = np.arange(-RIM_REACH, RIM_REACH + 0.25, 0.5, dtype=np.float32)
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


def find_lens_rim(image: np.ndarray, view: np.ndarray, near: Circle | None = None) -> RimFit | None:
    """A handheld lens's rim in a frame (BGR or grey, with its view mask `view`), in the
    frame's pixels: the best circle that `RIM_FIND` takes, or, near `near` (the last frame's
    rim), one that `RIM_KEEP` does; None where there is none.

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
        cx, cy, r = fit.circle
        return dataclasses.replace(fit, circle=((cx + 0.5) / s - 0.5, (cy + 0.5) / s - 0.5, r / s))

    def is_near(fit: RimFit) -> bool:
        assert near is not None
        (cx, cy, r), (nx, ny, nr) = fit.circle, near
        return np.hypot(cx - nx, cy - ny) <= RIM_NEAR * nr and abs(r - nr) <= RIM_NEAR * nr

    kept = []  # near the last rim, on the weaker evidence
    if near is not None:
        cx, cy = rescaled(np.asarray(near[:2], np.float64), s)
        prior = (cx, cy, near[2] * s)
        fit = checked(prior)
        if fit.shows(RIM_FIND) and is_near(fit):
            return fit
        # on weak evidence, the radius is the last rim's (the lens's): a short arc's is loose
        fit = checked(prior, fixed_radius=True)
        kept = [fit] if fit.shows(RIM_KEEP) and is_near(fit) else []
    strength, angle = _rim_gradient(small)
    radii = np.arange(RIM_RADII[0] * size[1], RIM_RADII[1] * size[1] + 1.0)
    found = [checked(c) for c in _circle_votes(strength, angle, lit, radii)]
    taken = [f for f in found if f.shows(RIM_FIND)] or kept
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
        if predicted is None and self._n - self._searched < self.SEARCH_EVERY:
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
