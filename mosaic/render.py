"""The re-render: each segment's mosaic rendered again from its frames at the refined poses.

With all poses known each segment's canvas is allocated once (`Canvas` with an extent, so
multiband blends). When exposure gains or per-place quality are needed, a first pass over the
video keeps, per segment, the frames' summed (and largest) sharpness per cell of a
low-resolution canvas and the mean values of coarse cells per frame (for the gains): no frame
is kept for those, but up to `RERENDER_KEEP_BYTES` of frames are kept for the second pass,
which corrects, weights (`mosaic.compose`) and adds them. `ReadAhead` reads the frames while
the pose graph is solved.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Container, Iterable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np

from mosaic.canvas import Canvas, footprint_box
from mosaic.compose import (
    PRECISION,
    SHARPNESS_KNEE,
    SHARPNESS_POWER,
    measure_quality,
    precision_weights,
    weights_from_small,
)
from mosaic.config import ComposeConfig
from mosaic.geometry import pixel_scale, scale_matrix, translation
from mosaic.io import Lookahead
from mosaic.photometry import (
    SATURATED,
    FrameQuality,
    GainObservations,
    VideoPhotometry,
    analysis_factor,
    channel_max,
    inside_share,
    small_size,
)

log = logging.getLogger(__name__)

# the re-render keeps frames (decoded, their masks as bits, their quality) from its first pass
# for the second, up to this many bytes (113 frames of 660x350 take 82 MB; 14 of 1920x1080
# fit); the video is read again for the others
RERENDER_KEEP_BYTES = 96 * 2**20
# frames (decoded, with their masks) read ahead while the pose graph is solved, up to this many
# bytes (`ReadAhead`: ~0.2 s of reading, 34 frames of 660x350, 4 of 1920x1080)
READ_AHEAD_BYTES = 32 * 2**20
BEST_POWER = 24.0  # best: (sharpness / best sharpness here)^this; 10 % worse weighs 0.08
GAIN_CELLS = 24  # cells along a frame's longer side for the exposure solve


FrameSource = Callable[[], Iterable[tuple[int, np.ndarray, np.ndarray]]]
_Read = tuple[int, np.ndarray, np.ndarray, FrameQuality | None]  # a frame, its mask, quality
BeforeAdd = Callable[[int, Canvas, np.ndarray, np.ndarray, np.ndarray], None]


class ReadAhead:
    """A `FrameSource` whose first reading starts when it is made, in a thread of its own: the
    re-render's frames are decoded and masked while the pose graph is solved (which needs
    neither). Up to `keep_bytes` of frames (image and mask) wait to be taken, in order; the
    first call takes them, a later call reads afresh. `close` stops the thread."""

    def __init__(self, frames: FrameSource, keep_bytes: int = READ_AHEAD_BYTES) -> None:
        self._frames = frames
        self._keep_bytes = keep_bytes
        self._held: deque[tuple[int, np.ndarray, np.ndarray]] = deque()
        self._bytes = 0
        self._done = self._stop = self._taken = False
        self._error: BaseException | None = None
        self._changed = threading.Condition()
        self._thread = threading.Thread(target=self._read, name="read-ahead", daemon=True)
        self._thread.start()

    def __call__(self) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        if self._taken:
            return iter(self._frames())
        self._taken = True
        return self._take()

    def close(self) -> None:
        with self._changed:
            self._stop = True
            self._changed.notify_all()
        self._thread.join()

    def _read(self) -> None:
        try:
            for item in self._frames():
                with self._changed:
                    while self._bytes >= self._keep_bytes and not self._stop:
                        self._changed.wait()
                    if self._stop:
                        return
                    self._held.append(item)
                    self._bytes += item[1].nbytes + item[2].nbytes
                    self._changed.notify_all()
        except BaseException as exc:  # re-raised where the frame would have been read
            self._error = exc
        finally:
            with self._changed:
                self._done = True
                self._changed.notify_all()

    def _take(self) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        while True:
            with self._changed:
                while not self._held and not self._done:
                    self._changed.wait()
                if not self._held:
                    if self._error is not None:
                        raise self._error
                    return
                item = self._held.popleft()
                self._bytes -= item[1].nbytes + item[2].nbytes
                self._changed.notify_all()
            yield item


@dataclass
class _Grid:
    """A low-resolution grid over a canvas extent: `factor` canvas pixels per cell."""

    x0: int
    y0: int
    factor: float
    shape: tuple[int, int]  # (rows, cols)

    @classmethod
    def over(cls, extent: tuple[int, int, int, int], factor: float) -> _Grid:
        x0, y0, x1, y1 = extent
        rows, cols = math.ceil((y1 - y0) / factor), math.ceil((x1 - x0) / factor)
        return cls(x0, y0, factor, (max(rows, 1), max(cols, 1)))

    def from_small(self, H: np.ndarray, frame_shape: tuple[int, int], small: tuple[int, int]):
        """H from the cells of a frame resized to `small` (w, h) into this grid's cells."""
        k = self.factor
        S = pixel_scale(1 / k)
        to_frame = np.linalg.inv(scale_matrix(frame_shape, small[::-1]))
        return S @ translation(-float(self.x0), -float(self.y0)) @ H @ to_frame


def _warp_box(src: np.ndarray, H: np.ndarray, grid_shape: tuple[int, int], border: float = 0.0):
    """`src` warped by `H` into the part of a grid its footprint covers: (x0, y0, roi), or None
    when it falls outside."""
    h, w = src.shape[:2]
    x0, y0, x1, y1 = footprint_box(H, (h, w))
    x0, y0 = max(x0 - 1, 0), max(y0 - 1, 0)
    x1, y1 = min(x1 + 1, grid_shape[1]), min(y1 + 1, grid_shape[0])
    if x1 <= x0 or y1 <= y0:
        return None
    M = translation(-float(x0), -float(y0)) @ H
    roi = cv2.warpPerspective(
        src, M, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR, borderValue=border
    )
    return x0, y0, roi


@dataclass
class _SegmentRender:
    """What the re-render keeps per segment between and during its passes."""

    poses: dict[int, np.ndarray]
    extent: tuple[int, int, int, int]
    quality_grid: _Grid
    gain_grid: _Grid
    sharpest: np.ndarray  # the most any frame's sharpness reached, per cell of quality_grid
    sharp_sum: np.ndarray  # the frames' sharpness summed per cell of quality_grid ...
    sharp_count: np.ndarray  # ... over this many frames
    observations: GainObservations = field(default_factory=GainObservations)
    gains: dict[int, float] = field(default_factory=dict)
    canvas: Canvas | None = None


@dataclass(frozen=True)
class _Kept:
    """A frame the re-render's first pass keeps for its second: as decoded, its mask packed
    into bits (`np.packbits` of mask != 0) and its quality maps (None: not measured)."""

    image: np.ndarray
    mask_bits: np.ndarray
    quality: FrameQuality | None

    def unpacked(self) -> tuple[np.ndarray, np.ndarray, FrameQuality | None]:
        """(image, mask as uint8 0 / 255, quality)."""
        h, w = self.image.shape[:2]
        mask = np.unpackbits(self.mask_bits, count=h * w).reshape(h, w)
        return self.image, cv2.multiply(mask, 255), self.quality


@dataclass(frozen=True)
class Rendered:
    """A re-rendered segment: its canvas and the exposure gains its frames were given."""

    canvas: Canvas
    gains: dict[int, float]  # frame index -> gain (empty without exposure compensation)


def render_segments(
    config: ComposeConfig,
    frames: FrameSource,
    poses: dict[int, dict[int, np.ndarray]],
    photometry: VideoPhotometry | None = None,
    before_add: BeforeAdd | None = None,
    keep_bytes: int = RERENDER_KEEP_BYTES,
) -> dict[int, Rendered]:
    """Render each segment's mosaic from its frames at known poses (`poses[segment][index]` =
    H_frame_to_ref), reading the frames through `frames()` ((index, BGR uint8 image, mask))
    once, or, when exposure gains or per-place quality are needed, in two passes (the first
    keeps only per-cell statistics). The frames of the first pass, with their masks and
    quality maps, are kept for the second up to `keep_bytes`: a video that fits is read once,
    a longer one is read again for the frames past it. `before_add(index, canvas, image, H,
    mask)` sees each frame just before it is added (e.g. to score it against the mosaic so
    far)."""
    photometry = photometry if photometry is not None else VideoPhotometry(False, False)
    rerender = _Rerender(config, frames, poses, photometry)
    if rerender.two_passes:
        rerender.first_pass(keep_bytes)
    for index, image, mask, quality in rerender.second_pass():  # second pass: the mosaic
        rerender.add(index, image, mask, quality, before_add)
    return rerender.rendered()


class _Rerender:
    """One `render_segments`: which segment owns each frame, the segments' state
    (`_SegmentRender`) and the frames the first pass keeps for the second."""

    def __init__(
        self,
        config: ComposeConfig,
        frames: FrameSource,
        poses: dict[int, dict[int, np.ndarray]],
        photometry: VideoPhotometry,
    ) -> None:
        self._config = config
        self._frames = frames
        self._poses = poses
        self._photometry = photometry
        self._owner = {index: seg for seg, p in poses.items() for index in p}
        self._need_sharpest = config.sharpness_weighting or config.blend == "best"
        self.two_passes = config.exposure or self._need_sharpest
        self._states: dict[int, _SegmentRender] = {}
        self._kept: dict[int, _Kept] = {}

    def first_pass(self, keep_bytes: int) -> None:
        """Statistics only (`_first_pass`), then the exposure gains solved per segment; the
        frames read are kept for the second pass up to `keep_bytes`."""
        config = self._config
        room = keep_bytes
        # read a frame ahead in a thread, while this one measures the frame before
        with Lookahead(self._reads(measure=False)) as first:
            for index, image, mask, _ in first:
                quality = measure_quality(config, image, mask) if self._need_sharpest else None
                st = self._state_of(self._owner[index], image.shape[:2])
                _first_pass(config, st, index, image, mask, quality, self._photometry)
                packed = np.packbits(mask != 0)  # only where the mask is nonzero matters
                if image.nbytes + packed.nbytes <= room:
                    self._kept[index] = _Kept(image, packed, quality)
                    room -= image.nbytes + packed.nbytes
        for seg, st in self._states.items():
            if config.exposure:
                st.gains = st.observations.solve()
                values = np.array(list(st.gains.values()))
                if len(values):
                    log.info(
                        "segment %d: exposure gains %.3f-%.3f (median %.3f) over %d frames",
                        seg, values.min(), values.max(), float(np.median(values)), len(values),
                    )  # fmt: skip

    def second_pass(self) -> Iterator[_Read]:
        """The frames again, in order: those kept from the first pass, the others read."""
        kept = self._kept
        if self.two_passes and kept.keys() >= self._owner.keys():
            while kept:  # in the order read; each let go once added
                index = next(iter(kept))
                yield index, *kept.pop(index).unpacked()
            return
        with Lookahead(self._reads(kept.keys())) as again:
            for index, image, mask, quality in again:
                if index in kept:
                    yield index, *kept.pop(index).unpacked()
                else:
                    yield index, image, mask, quality

    def add(
        self,
        index: int,
        image: np.ndarray,
        mask: np.ndarray,
        quality: FrameQuality | None,
        before_add: BeforeAdd | None,
    ) -> None:
        """A frame of the second pass corrected, weighted and added to its segment's canvas."""
        st = self._state_of(self._owner[index], image.shape[:2])
        if st.canvas is None:
            st.canvas = Canvas(self._config, extent=st.extent)
        H = st.poses[index]
        corrected = self._photometry.correct(image, st.gains.get(index))
        weights = None
        if self._need_sharpest:
            weights = self._weights(st, index, image, mask, quality)
        if before_add is not None:
            before_add(index, st.canvas, image, H, mask)
        st.canvas.add(corrected, H, mask, weights)

    def rendered(self) -> dict[int, Rendered]:
        """The segments' canvases, each blending thread's last frames waited for."""
        for st in self._states.values():
            if st.canvas is not None:
                st.canvas.flush()  # the blending thread's last frames, and the thread let go
        return {
            seg: Rendered(st.canvas, st.gains)
            for seg, st in self._states.items()
            if st.canvas is not None
        }

    def _weights(
        self,
        st: _SegmentRender,
        index: int,
        image: np.ndarray,
        mask: np.ndarray,
        quality: FrameQuality | None,
    ) -> np.ndarray:
        """A frame's weight factors (h, w): `best`, its sharpness against the sharpest frame's
        at each place; else one factor for the whole frame against the other frames there,
        x glare (x the precision)."""
        config = self._config
        quality = quality if quality is not None else measure_quality(config, image, mask)
        q = _sharpness(config, quality)
        small = q.shape[1::-1]
        M = st.quality_grid.from_small(st.poses[index], image.shape[:2], small)

        def here(grid: np.ndarray) -> np.ndarray:
            flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            return cv2.warpPerspective(grid, M, small, flags=flags)

        if config.blend == "best":
            relative = np.clip(q / np.maximum(here(st.sharpest), 1e-12), 0.0, 1.0)
            small_weights = relative**BEST_POWER
        else:  # one factor for the whole frame (per-pixel factors leave seams)
            # the other frames' mean sharpness at the frame's places (leave-one-out)
            others = here(st.sharp_count) - (q > 0)
            mean = (here(st.sharp_sum) - q) / np.maximum(others, 1e-6)
            share = _frame_share(q, np.where(others > 0.5, mean, 0.0))
            small_weights = quality.glare * share
            if PRECISION:
                small_weights = small_weights * precision_weights(
                    self._photometry, image.shape, small, st.gains.get(index)
                )
        return weights_from_small(small_weights, image.shape[:2])

    def _state_of(self, seg: int, shape: tuple[int, int]) -> _SegmentRender:
        """A segment's state, made at its first frame: the extent of its frames' footprints
        and the grids over it."""
        if seg not in self._states:
            boxes = np.array([footprint_box(H, shape) for H in self._poses[seg].values()])
            extent = (
                int(boxes[:, 0].min()),
                int(boxes[:, 1].min()),
                int(boxes[:, 2].max()),
                int(boxes[:, 3].max()),
            )
            q_grid = _Grid.over(extent, analysis_factor(shape))
            g_grid = _Grid.over(extent, max(shape) / GAIN_CELLS)
            zeros = np.zeros(q_grid.shape, np.float32)
            self._states[seg] = _SegmentRender(
                self._poses[seg], extent, q_grid, g_grid, zeros, zeros.copy(), zeros.copy()
            )
        return self._states[seg]

    def _reads(self, known: Container[int] = (), measure: bool = True) -> Iterator[_Read]:
        """The segments' frames read, with their quality maps where `measure` (None where not
        needed, or for the `known` frames, whose image is not used)."""
        for index, image, mask in self._frames():
            if index in self._owner:
                measured = measure and self._need_sharpest and index not in known
                yield (
                    index,
                    image,
                    mask,
                    measure_quality(self._config, image, mask) if measured else None,
                )


def _first_pass(
    config: ComposeConfig,
    st: _SegmentRender,
    index: int,
    image: np.ndarray,
    mask: np.ndarray,
    quality: FrameQuality | None,
    photometry: VideoPhotometry,
) -> None:
    """What the re-render's first pass keeps of a frame: its sharpness on the segment's
    quality grid (the most, the sum and the count of frames per cell) and its exposure
    observations."""
    H = st.poses[index]
    if quality is not None:
        q = _sharpness(config, quality)
        M = st.quality_grid.from_small(H, image.shape[:2], q.shape[1::-1])
        box = _warp_box(q, M, st.sharpest.shape)
        seen = _warp_box((q > 0).astype(np.float32), M, st.sharpest.shape)
        if box is not None and seen is not None:
            x0, y0, roi = box
            cells = (slice(y0, y0 + roi.shape[0]), slice(x0, x0 + roi.shape[1]))
            np.maximum(st.sharpest[cells], roi, out=st.sharpest[cells])
            st.sharp_sum[cells] += roi
            st.sharp_count[cells] += seen[2]
    if config.exposure:
        _observe_cells(st, index, image, mask, H, photometry)


def _frame_share(sharpness: np.ndarray, mean: np.ndarray) -> np.float32:
    """A frame's sharpness factor: its median sharpness relative to the mean of the other
    frames at the same places (`mean`, 0 where none saw; over the places with detail: where
    that mean is above its lower quartile under the frame); 1 from `SHARPNESS_KNEE` up
    (averaging frames about as sharp lowers the noise), falling with `SHARPNESS_POWER`
    under it. A frame no other frame overlaps keeps 1."""
    seen = (sharpness > 0) & (mean > 0)
    if not seen.any():
        return np.float32(1.0)
    detailed = seen & (mean >= np.percentile(mean[seen], 25))
    rho = float(np.median(sharpness[detailed] / mean[detailed]))
    return np.float32(min(1.0, rho / SHARPNESS_KNEE) ** SHARPNESS_POWER)


def _sharpness(config: ComposeConfig, quality: FrameQuality) -> np.ndarray:
    """What frames are compared by at a place, on the frame's analysis grid: local sharpness
    x glare (`photometry.FrameQuality`); without sharpness weighting (`best`), the distance
    to the frame's border."""
    return quality.sharpness() if config.sharpness_weighting else quality.ramp


def _observe_cells(
    st: _SegmentRender,
    index: int,
    image: np.ndarray,
    mask: np.ndarray,
    H: np.ndarray,
    photometry: VideoPhotometry,
) -> None:
    """Mean values of the gain grid's cells the frame wholly covers (no saturated pixel)."""
    grid = st.gain_grid
    size = small_size(image.shape, grid.factor)
    small = photometry.correct_small(image, size)
    inside = inside_share((mask > 0) & (channel_max(image) < SATURATED), size)
    M = grid.from_small(H, image.shape[:2], size)
    inside_box = _warp_box(inside, M, grid.shape)
    value_box = _warp_box(small, M, grid.shape)
    if inside_box is None or value_box is None:
        return
    x0, y0, covered = inside_box
    _, _, values = value_box
    good = covered > 0.999
    if not good.any():
        return
    rows, cols = np.nonzero(good)
    cells = (rows + y0) * grid.shape[1] + (cols + x0)
    st.observations.add(index, cells, values.reshape((*good.shape, -1)).mean(axis=2)[good])
