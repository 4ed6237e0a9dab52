"""Mosaic canvas: accumulates warped frames into a growing canvas and blends them; and the
compositing around it: photometric correction, per-pixel frame weights, the re-render pass.

Frames arrive one at a time with their homography into the segment's reference frame
(`H_frame_to_ref`); the canvas never keeps frames, only float32 accumulators
(`sum_weighted` HxWxC and `weight` HxW) over a buffer that grows with slack as frames leave it.
Each frame is warped only into its own bounding box, so the cost of `add` does not grow with
the canvas. A canvas of known extent (the re-render, where all poses are known) can also
blend multiband (`mosaic.blending`); a growing one falls back to feathering, and so does one
whose pyramids would take more than `MULTIBAND_MAX_BYTES`. `render` goes by strips of rows:
no float image of the whole canvas is made.

Blend modes (`[compose] blend`): `average`, `feather` (weights ramp up over `feather_px` from
the frame's border and field-of-view edge), `last` (later frames on top), `best` (each place
from its sharpest frame, a soft selection: smooth seams) and `multiband` (the feather weights,
Burt-Adelson: detail blended where the weight is, shading over ~32 px).

Compositing (`LiveCompositor` while streaming, `render_segments` for the re-render): frames are
divided by the video's flat-field (`[compose] flatfield`), scaled by their exposure gain
(`exposure`: live, against the canvas under the frame; re-render, a global least-squares
solution over all frames from a first pass over the video) and weighted by their sharpness
against the other frames at the same places and by glare (`sharpness_weighting`; live, against
the recent frames). The first pass keeps, per segment, the frames' summed (and largest)
sharpness per cell of a low-resolution canvas and the mean values of coarse cells per frame
(for the gains): no frame is kept.

Coordinates: pixel centres sit at integer coordinates (OpenCV's convention). The canvas
(what `render`, `coverage` and `shape` describe) is the bounding box of all placed frames;
`H_ref_to_canvas` is the translation from reference-frame pixels into it.

Seams: the image is warped bilinearly, and a warped pixel counts as valid only where *every*
source pixel its bilinear sample touches is valid (the weight map, -1e30 outside the valid
region, is warped linearly with the same homography and thresholded at 0). So neither the dark
outside of the field of view nor the zero border of the warp can leak into the mosaic, while
integer placements keep every pixel, the frame's outermost ring included.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Container, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from mosaic.blending import LaplacianBlender, shrink_noise
from mosaic.config import ComposeConfig
from mosaic.errors import CanvasLimitError
from mosaic.io import Lookahead
from mosaic.photometry import (
    DARK,
    SATURATED,
    FrameQuality,
    GainObservations,
    VideoPhotometry,
    analysis_factor,
    channel_max,
    frame_quality,
    inside_share,
    normalised_grid,
    robust_gain,
    shading_terms,
    shrink,
    small_size,
)
from mosaic.preprocess import scale_matrix

log = logging.getLogger(__name__)

BLENDS = ("feather", "average", "last", "multiband", "best")
MULTIBAND_LEVELS = 5  # Laplacian levels: seams are smoothed over ~2^5 = 32 px
# multiband's pyramids take 21 bytes a canvas pixel (3 channels) on top of the canvas' 16 and
# the image's 3: a canvas needing more than this (~12.5 Mpx, 3500x3500; the re-render's peak
# then ~0.55 GB, docs/compose.md) feathers instead (19 bytes a pixel), with a warning
MULTIBAND_MAX_BYTES = 256 * 2**20
RENDER_ROWS = 256  # rows of a strip of `Canvas.render`
PICTURE_THREADS = 2  # strips of the picture (render, denoise) made at once
# frames whose multiband pyramids may wait for the canvas' blending thread (each a copy of the
# frame's box: ~6 MB at 660x350, ~45 MB at 1920x1080)
BLEND_AHEAD = 1
# the re-render keeps frames (decoded, their masks as bits, their quality) from its first pass
# for the second, up to this many bytes (113 frames of 660x350 take 82 MB; 14 of 1920x1080
# fit); the video is read again for the others
RERENDER_KEEP_BYTES = 96 * 2**20
# frames (decoded, with their masks) read ahead while the pose graph is solved, up to this many
# bytes (`ReadAhead`: ~0.2 s of reading, 34 frames of 660x350, 4 of 1920x1080)
READ_AHEAD_BYTES = 32 * 2**20
# feather / average / multiband: weight x min(1, relative sharpness / knee)^power
SHARPNESS_KNEE = 0.8  # frames at least this sharp (relative to the others there) count fully
SHARPNESS_POWER = 4.0  # ... blurrier ones fall off fast: half the knee weighs 1/16
PRECISION = True  # weights x (shading / gain)^2: the corrected frame's inverse noise variance
BEST_POWER = 24.0  # best: (sharpness / best sharpness here)^this; 10 % worse weighs 0.08
GAIN_CELLS = 24  # cells along a frame's longer side for the exposure solve
_MIN_FACTOR = 1e-20  # floor of a weight factor: a valid pixel keeps a positive weight
_MAX_FACTOR = 1e20  # cap of a weight factor (far under _INVALID_WEIGHT / 32^2)

_MIN_SLACK_PX = 256  # buffer growth: at least this many pixels ...
_SLACK_FRACTION = 0.25  # ... or this fraction of the needed extent, whichever is larger
# Weight given to invalid pixels before warping: far below any bilinear mix of valid weights
# (smallest nonzero OpenCV bilinear tap is 1/32^2; valid weights are at most _MAX_FACTOR), so
# "warped weight > 0" means all taps valid.
_INVALID_WEIGHT = 1.0e30
_EDGE_EPS = 1e-6  # tolerance when rounding a warped bounding box to whole pixels
_MIN_W = 1e-9  # homogeneous coordinate under which a corner counts as sent to infinity
_MIN_SAMPLED_WEIGHT = 1e-6  # resampled accumulated weight above which a pixel counts as covered


def _multiband_fits(height: int, width: int, channels: int) -> bool:
    """Whether multiband's pyramids for a canvas of (height, width) stay within
    `MULTIBAND_MAX_BYTES`; if not, say so: the canvas feathers instead."""
    need = LaplacianBlender.bytes_for(height, width, channels, MULTIBAND_LEVELS)
    if need <= MULTIBAND_MAX_BYTES:
        return True
    log.warning(
        "a %dx%d mosaic is blended by feathering instead of multiband: its pyramids would "
        "take %.0f MB, over %.0f MB",
        width, height, need / 2**20, MULTIBAND_MAX_BYTES / 2**20,
    )  # fmt: skip
    return False


def _translation(tx: float, ty: float) -> np.ndarray:
    """3x3 float64 translation matrix."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


class Canvas:
    """Growing mosaic canvas with feather, average, last-wins, best or multiband blending.

    `extent` (x0, y0, x1, y1 in reference pixels, half-open), when the poses of all frames
    are known, allocates the canvas once; `multiband` needs it (else it feathers).
    """

    def __init__(
        self,
        config: ComposeConfig,
        channels: int = 3,
        extent: tuple[int, int, int, int] | None = None,
    ) -> None:
        if config.blend not in BLENDS:
            raise ValueError(f"unknown blend mode {config.blend!r}")
        if channels not in (1, 3):
            raise ValueError(f"channels must be 1 or 3, got {channels}")
        self._config = config
        self._channels = channels
        self._n_frames = 0
        # Allocated buffer: reference coords of its pixel (0, 0); arrays hold the size.
        self._buf_x0 = 0
        self._buf_y0 = 0
        self._sum = np.zeros((0, 0, channels), np.float32)
        self._weight = np.zeros((0, 0), np.float32)
        # Content box in reference coords, half-open [x0, x1) x [y0, y1); None before any frame.
        self._content: tuple[int, int, int, int] | None = None
        # Per-frame weight map cache (frames of one video share shape and often the mask).
        self._cache_key: tuple[tuple[int, int], np.ndarray | None] | None = None
        self._cache_weights: np.ndarray | None = None
        self._weight_bufs: tuple[np.ndarray, ...] | None = None  # `_frame_weights`' buffers
        ramped = config.blend in ("feather", "best", "multiband")
        self._feathered = ramped and config.feather_px > 0
        self._scratch_bufs: dict[str, np.ndarray] = {}
        self._blender: LaplacianBlender | None = None
        self._blend_origin = (0, 0)  # reference coords of the blender's pixel (0, 0)
        # multiband's pyramids are built in a thread of their own (`_blend_later`)
        self._blending: ThreadPoolExecutor | None = None
        self._pending: deque[Future[None]] = deque()
        if extent is not None:
            x0, y0, x1, y1 = extent
            self._buf_x0, self._buf_y0 = x0, y0
            self._sum = np.zeros((y1 - y0, x1 - x0, channels), np.float32)
            self._weight = np.zeros((y1 - y0, x1 - x0), np.float32)
            if config.blend == "multiband" and _multiband_fits(y1 - y0, x1 - x0, channels):
                self._blender = LaplacianBlender(y1 - y0, x1 - x0, channels, MULTIBAND_LEVELS)
                self._blend_origin = (x0, y0)

    # ----------------------------------------------------------------------------- queries

    @property
    def n_frames(self) -> int:
        """Number of frames added so far."""
        return self._n_frames

    @property
    def blend(self) -> str:
        """The blend applied: `[compose] blend`, but `feather` for `multiband` without its
        pyramids (a growing canvas, or one over `MULTIBAND_MAX_BYTES`)."""
        if self._config.blend == "multiband" and self._blender is None:
            return "feather"
        return self._config.blend

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the canvas (bounding box of all frames); (0, 0) before any."""
        if self._content is None:
            return (0, 0)
        x0, y0, x1, y1 = self._content
        return (y1 - y0, x1 - x0)

    @property
    def H_ref_to_canvas(self) -> np.ndarray:
        """Translation from reference-frame pixel coords into the canvas' pixel coords."""
        if self._content is None:
            return np.eye(3)
        x0, y0, _, _ = self._content
        return _translation(-float(x0), -float(y0))

    def fits(self, H_frame_to_ref: np.ndarray, frame_shape: tuple[int, int]) -> bool:
        """Whether adding a frame of `frame_shape` (h, w) keeps the canvas within the cap."""
        return self._placement(H_frame_to_ref, frame_shape)[1] is None

    def render(self) -> np.ndarray:
        """Blended mosaic, uint8 (H, W, C); pixels no frame covered are 0. Rendered in strips
        of `RENDER_ROWS` rows: no float image of the whole canvas is made."""
        self.flush()
        sum_c, weight_c = self._content_views()
        out = np.zeros(sum_c.shape, np.uint8)

        def strip(r0: int) -> None:
            r1 = min(r0 + RENDER_ROWS, out.shape[0])
            out[r0:r1] = self._render_rows(sum_c[r0:r1], weight_c[r0:r1], r0)

        # the strips are independent: two at a time (OpenCV and numpy release the GIL)
        with ThreadPoolExecutor(PICTURE_THREADS, thread_name_prefix="render") as pool:
            list(pool.map(strip, range(0, out.shape[0], RENDER_ROWS)))
        return out

    def flush(self) -> None:
        """Wait until the frames added so far are in the multiband pyramids (they are built in
        a thread of their own; raises what it raised there), and let that thread go."""
        while self._pending:
            self._pending.popleft().result()
        if self._blending is not None:
            self._blending.shutdown(wait=True)
            self._blending = None

    def picture(self) -> np.ndarray:
        """The mosaic as written and reported: `render`, with `denoise` the noise the blend
        left shrunk (`blending.shrink_noise`: the finest band where it is near the noise)."""
        image = self.render()
        if not self._config.denoise:
            return image
        return shrink_noise(image, self.coverage() > 0, RENDER_ROWS, PICTURE_THREADS)

    def _render_rows(self, sum_c: np.ndarray, weight_c: np.ndarray, r0: int) -> np.ndarray:
        """uint8 rows of `render` from the content's rows r0 .. r0 + len(`sum_c`)."""
        out = np.zeros(sum_c.shape, np.float32)
        covered = weight_c > 0
        np.divide(sum_c, weight_c[..., None], out=out, where=covered[..., None])
        if self._blender is not None and self._content is not None:
            # the multiband result over the blender's extent (all of the content, unless a
            # frame was placed outside the extent it was made for)
            x0, cy0, x1, _ = self._content
            y0, y1 = cy0 + r0, cy0 + r0 + len(out)  # the strip, in reference coordinates
            ox, oy = self._blend_origin
            ix0, iy0 = max(x0, ox), max(y0, oy)
            ix1, iy1 = min(x1, ox + self._blender.width), min(y1, oy + self._blender.height)
            if ix1 > ix0 and iy1 > iy0:
                blended = self._blender.render_rows(iy0 - oy, iy1 - oy)[:, ix0 - ox : ix1 - ox]
                inner = (slice(iy0 - y0, iy1 - y0), slice(ix0 - x0, ix1 - x0))
                np.copyto(out[inner], blended, where=covered[inner][..., None])
        np.rint(out, out=out)
        np.clip(out, 0, 255, out=out)
        return out.astype(np.uint8)

    def coverage(self) -> np.ndarray:
        """uint8 mask (H, W) of the canvas: 255 where at least one frame contributed, else 0."""
        _, weight_c = self._content_views()
        return (weight_c > 0).astype(np.uint8) * 255

    def content_in_frame(
        self,
        H_frame_to_ref: np.ndarray,
        frame_shape: tuple[int, ...],
        scale: float = 1.0,
        channel: int | None = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The blended canvas seen from a frame placed by `H_frame_to_ref`: (values float32,
        valid bool), both of the frame's (h, w) = `frame_shape[:2]`, or of a copy resized by
        `scale` (rounded like `cv2.resize` sizes, pixel centres as `preprocess.scale_matrix`).

        `channel` picks one colour channel (1: green of BGR; ignored on a 1-channel canvas);
        None gives all of them, values (h, w, C).
        Valid where some frame contributed: the accumulated sum and weight are both sampled
        bilinearly and divided, so a value is a weighted mean of covered pixels only and
        nothing of the empty canvas leaks in.
        """
        fh, fw = int(frame_shape[0]), int(frame_shape[1])
        h, w = max(round(fh * scale), 1), max(round(fw * scale), 1)
        values = np.zeros((h, w) if channel is not None else (h, w, self._channels), np.float32)
        valid = np.zeros((h, w), bool)
        if self._content is None or fh == 0 or fw == 0:
            return values, valid
        roi = self._roi_under(H_frame_to_ref, (fh, fw), (h, w))
        if roi is None:
            return values, valid
        warped_sum = self._sampled(self._sum, roi, (w, h))
        weight = self._sampled(self._weight, roi, (w, h))
        if channel is not None and warped_sum.ndim == 3:
            warped_sum = warped_sum[..., min(channel, warped_sum.shape[2] - 1)]
        elif channel is None:
            warped_sum = warped_sum.reshape(h, w, self._channels)
        valid = weight > _MIN_SAMPLED_WEIGHT
        np.divide(
            warped_sum,
            weight if channel is not None else weight[..., None],
            out=values,
            where=valid if channel is not None else valid[..., None],
        )
        return values, valid

    @staticmethod
    def _sampled(
        array: np.ndarray, roi: tuple[np.ndarray, slice, slice], size: tuple[int, int]
    ) -> np.ndarray:
        """A canvas array seen from the frame: its `roi` (`_roi_under`) warped bilinearly
        into the frame's (w, h) = `size`."""
        M, rows, cols = roi
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        return cv2.warpPerspective(array[rows, cols], M, size, flags=flags)

    def _roi_under(
        self, H_frame_to_ref: np.ndarray, frame: tuple[int, int], out: tuple[int, int]
    ) -> tuple[np.ndarray, slice, slice] | None:
        """What `content_in_frame` samples for a (h, w) = `frame` frame seen at (h, w) = `out`:
        M (output pixels -> ROI pixels) and the buffer's rows and columns of the content under
        the frame's footprint (the buffer may be large); None where nothing is under it."""
        assert self._content is not None
        h, w = out
        H_out_to_frame = np.linalg.inv(scale_matrix(frame, out))
        H_out_to_ref = np.asarray(H_frame_to_ref, np.float64) @ H_out_to_frame
        corners = np.array([[-1, -1, 1], [w, -1, 1], [-1, h, 1], [w, h, 1]], float)
        mapped = corners @ H_out_to_ref.T
        if not np.all(np.isfinite(mapped)) or np.any(mapped[:, 2] <= _MIN_W):
            return None
        xy = mapped[:, :2] / mapped[:, 2:]
        cx0, cy0, cx1, cy1 = self._content
        x0 = max(int(np.floor(xy[:, 0].min())) - 1, cx0)
        y0 = max(int(np.floor(xy[:, 1].min())) - 1, cy0)
        x1 = min(int(np.ceil(xy[:, 0].max())) + 2, cx1)
        y1 = min(int(np.ceil(xy[:, 1].max())) + 2, cy1)
        if x1 <= x0 or y1 <= y0:
            return None
        rows = slice(y0 - self._buf_y0, y1 - self._buf_y0)
        cols = slice(x0 - self._buf_x0, x1 - self._buf_x0)
        return _translation(-float(x0), -float(y0)) @ H_out_to_ref, rows, cols

    # ----------------------------------------------------------------------------- adding

    def add(
        self,
        image: np.ndarray,
        H_frame_to_ref: np.ndarray,
        mask: np.ndarray | None = None,
        weights: np.ndarray | None = None,
    ) -> None:
        """Warp `image` (uint8, or float32 after photometric correction) into the canvas and
        blend it in.

        `mask` (uint8 HxW, nonzero = valid field of view) limits which pixels contribute;
        None means the whole frame. `weights` (float32 HxW, > 0) multiplies the blend mode's
        own weights (the feather ramp, or 1) per pixel; `last` ignores it. Raises
        `CanvasLimitError` without touching the canvas if the frame would push either side of
        the canvas beyond `max_canvas_px`.
        """
        image = self._check_image(image)
        h, w = image.shape[:2]
        if mask is not None and mask.shape != (h, w):
            raise ValueError(f"mask shape {mask.shape} does not match frame shape {(h, w)}")
        H = np.asarray(H_frame_to_ref, dtype=np.float64)
        box, problem = self._placement(H, (h, w))
        if problem is not None:
            raise CanvasLimitError(problem)
        assert box is not None
        fx0, fy0, fx1, fy1 = box
        union = (fx0, fy0, fx1, fy1)
        if self._content is not None:
            cx0, cy0, cx1, cy1 = self._content
            union = (min(cx0, fx0), min(cy0, fy0), max(cx1, fx1), max(cy1, fy1))
        self._ensure_buffer(union)

        # Warp only into the frame's bounding box (ROI) of the buffer. Every intermediate
        # lives in a reused scratch buffer and OpenCV's masked accumulate / copyTo write
        # straight into the accumulator views: no per-frame allocation (page faults on
        # fresh multi-MB arrays otherwise cost as much as the warps themselves).
        rw, rh = fx1 - fx0, fy1 - fy0
        cn = self._channels
        M = _translation(-float(fx0), -float(fy0)) @ H
        flags, border = cv2.INTER_LINEAR, cv2.BORDER_CONSTANT
        warped = self._scratch(f"warped_{image.dtype}", rh, rw, cn, image.dtype.type)
        cv2.warpPerspective(image, M, (rw, rh), dst=warped, flags=flags, borderMode=border)
        weight = self._scratch("weight", rh, rw, 1, np.float32)
        frame_weights = self._frame_weights((h, w), mask)
        if weights is not None and self._config.blend != "last":
            if weights.shape != (h, w):
                raise ValueError(f"weights shape {weights.shape} does not match frame {(h, w)}")
            factor = np.asarray(weights, np.float32)
            factor = cv2.max(cv2.min(factor, _MAX_FACTOR), _MIN_FACTOR)
            # the product inside, the invalid weight kept outside (OpenCV: one pass each)
            scaled = cv2.multiply(frame_weights, factor)
            outside = cv2.compare(frame_weights, 0.0, cv2.CMP_LE)
            frame_weights = cv2.copyTo(frame_weights, outside, dst=scaled)
        cv2.warpPerspective(
            frame_weights,
            M,
            (rw, rh),
            dst=weight,
            flags=flags,
            borderMode=border,
            borderValue=-_INVALID_WEIGHT,
        )
        valid = self._scratch("valid", rh, rw, 1, np.uint8)
        cv2.compare(weight, 0.0, cv2.CMP_GT, dst=valid)  # 255 where all bilinear taps valid

        bx, by = fx0 - self._buf_x0, fy0 - self._buf_y0
        sum_roi = self._sum[by : by + rh, bx : bx + rw]
        weight_roi = self._weight[by : by + rh, bx : bx + rw]
        if cn == 1:
            sum_roi = sum_roi[..., 0]
        if self._config.blend == "last":
            warped_f = self._scratch("warped_f", rh, rw, cn, np.float32)
            np.copyto(warped_f, warped)
            cv2.copyTo(warped_f, valid, dst=sum_roi)
            cv2.copyTo(self._scratch("ones", rh, rw, 1, np.float32), valid, dst=weight_roi)
        elif not self._feathered and weights is None:  # average
            cv2.accumulate(warped, sum_roi, valid)
            cv2.accumulate(self._scratch("ones", rh, rw, 1, np.float32), weight_roi, valid)
            self._accumulate_more(M, valid, (slice(by, by + rh), slice(bx, bx + rw)))
        else:  # per-pixel weights: feather ramp and / or the given factor
            weight_c = weight
            if cn > 1:
                weight_c = self._scratch("weight_c", rh, rw, cn, np.float32)
                cv2.merge([weight] * cn, dst=weight_c)
            warped_f = warped
            if warped.dtype != np.float32:
                warped_f = self._scratch("warped_f", rh, rw, cn, np.float32)
                np.copyto(warped_f, warped)
            cv2.accumulateProduct(warped_f, weight_c, sum_roi, valid)
            cv2.accumulate(weight, weight_roi, valid)
            if self._blender is not None:
                ox, oy = self._blend_origin
                boxed = self._blender.boxed(warped_f, weight, fx0 - ox, fy0 - oy)
                if boxed is not None:
                    self._blend_later(boxed)
        self._content = union
        self._n_frames += 1

    # ----------------------------------------------------------------------------- internals

    def _blend_later(self, boxed: tuple[np.ndarray, np.ndarray, int, int]) -> None:
        """Hand a boxed frame (`LaplacianBlender.boxed`, a copy) to the blending thread: its
        pyramid is most of a frame's compositing and needs nothing else, so it runs beside the
        next frame's reading, weighting and warping (OpenCV releases the GIL). One thread, in
        order: the accumulators add up as they would here."""
        assert self._blender is not None
        if self._blending is None:
            self._blending = ThreadPoolExecutor(1, thread_name_prefix="multiband")
        while len(self._pending) >= BLEND_AHEAD:
            self._pending.popleft().result()
        self._pending.append(self._blending.submit(self._blender.add_boxed, boxed))

    def _accumulate_more(self, M: np.ndarray, valid: np.ndarray, roi: tuple[slice, slice]) -> None:
        """Hook of `add` (average blend): more planes under the same placement (`_Planes`)."""

    def _check_image(self, image: np.ndarray) -> np.ndarray:
        """Validate dtype and channel count; returns HxW (1 channel) or HxWxC."""
        if image.dtype not in (np.uint8, np.float32):
            raise ValueError(f"frame must be uint8 or float32, got {image.dtype}")
        c = 1 if image.ndim == 2 else image.shape[2] if image.ndim == 3 else -1
        if c != self._channels:
            raise ValueError(
                f"frame has shape {image.shape}, canvas expects {self._channels} channel(s)"
            )
        if image.ndim == 3 and c == 1:
            image = image[..., 0]
        if image.shape[0] == 0 or image.shape[1] == 0:
            raise ValueError(f"frame is empty: shape {image.shape}")
        return image

    def _placement(
        self, H: np.ndarray, frame_shape: tuple[int, int]
    ) -> tuple[tuple[int, int, int, int] | None, str | None]:
        """Frame bounding box in reference coords (half-open ints), or why it cannot be placed."""
        H = np.asarray(H, dtype=np.float64)
        if H.shape != (3, 3):
            raise ValueError(f"homography must be 3x3, got shape {H.shape}")
        h, w = int(frame_shape[0]), int(frame_shape[1])
        cap = self._config.max_canvas_px
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float)
        mapped = corners @ H.T
        # The homogeneous coordinate is affine over the frame: positive at the four corners
        # means the whole frame stays on the finite side (no wrap through infinity).
        if not np.all(np.isfinite(mapped)) or np.any(mapped[:, 2] <= _MIN_W):
            return None, (
                "cannot place the frame on the mosaic canvas: its homography sends part of it "
                f"to infinity (degenerate registration), beyond the cap of {cap} px per side "
                "([compose] max_canvas_px)"
            )
        xy = mapped[:, :2] / mapped[:, 2:]
        lo = np.floor(xy.min(axis=0) + _EDGE_EPS)
        hi = np.ceil(xy.max(axis=0) - _EDGE_EPS) + 1
        ux0, uy0, ux1, uy1 = float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])
        if self._content is not None:
            cx0, cy0, cx1, cy1 = self._content
            ux0, uy0, ux1, uy1 = min(ux0, cx0), min(uy0, cy0), max(ux1, cx1), max(uy1, cy1)
        width, height = ux1 - ux0, uy1 - uy0
        if width > cap or height > cap:
            return None, (
                f"adding the frame would grow the mosaic canvas to {width:.0f}x{height:.0f} px "
                f"(width x height), beyond the cap of {cap} px per side "
                "([compose] max_canvas_px)"
            )
        return (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])), None

    def _content_views(self) -> tuple[np.ndarray, np.ndarray]:
        """Views of the accumulators cropped to the content box (empty before any frame)."""
        if self._content is None:
            return (
                np.zeros((0, 0, self._channels), np.float32),
                np.zeros((0, 0), np.float32),
            )
        x0, y0, x1, y1 = self._content
        rows = slice(y0 - self._buf_y0, y1 - self._buf_y0)
        cols = slice(x0 - self._buf_x0, x1 - self._buf_x0)
        return self._sum[rows, cols], self._weight[rows, cols]

    def _frame_weights(self, shape: tuple[int, int], mask: np.ndarray | None) -> np.ndarray:
        """Per-frame float32 weight map: > 0 inside the valid region, -_INVALID_WEIGHT outside.

        Feather: distance to the nearest invalid pixel or to just outside the frame border,
        clipped at feather_px and normalised to (0, 1]; average / last: 1. The large negative
        value outside makes the bilinearly warped map positive only where every tap is valid,
        so one warp yields both the weight and the validity.
        """
        key = self._cache_key
        if key is not None and key[0] == shape:
            same = (mask is None and key[1] is None) or (
                mask is not None and key[1] is not None and np.array_equal(mask, key[1])
            )
            if same:
                assert self._cache_weights is not None
                return self._cache_weights
        # Every map lives in a buffer kept for the frame size (the mask, and so the map, usually
        # changes at the field-of-view edge from frame to frame): fresh frame-sized arrays
        # cost page faults worth as much as the distance transform.
        h, w = shape
        if self._weight_bufs is None or self._weight_bufs[0].shape != (h + 2, w + 2):
            self._weight_bufs = (
                np.zeros((h + 2, w + 2), np.uint8),  # valid, zero-padded by one pixel
                np.empty((h + 2, w + 2), np.float32),  # its distance transform
                np.empty((h, w), np.float32),  # the weights
                np.empty((h, w), np.uint8),  # invalid
                np.full((h, w), -_INVALID_WEIGHT, np.float32),
            )
        padded, dist, weights, invalid, outside = self._weight_bufs
        valid = padded[1:-1, 1:-1]  # nonzero where valid; the border stays 0
        if mask is None:
            valid.fill(1)
        elif mask.dtype == np.uint8:
            cv2.compare(mask, 0, cv2.CMP_NE, dst=valid)
        else:
            np.copyto(valid, mask != 0)
        if self._feathered:
            feather = np.float32(self._config.feather_px)
            cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_5, dst=dist)
            cv2.min(dist[1:-1, 1:-1], float(feather), dst=weights)
            np.divide(weights, feather, out=weights)
        else:
            weights.fill(1.0)
        if mask is not None:
            cv2.compare(valid, 0, cv2.CMP_EQ, dst=invalid)
            cv2.copyTo(outside, invalid, dst=weights)
        self._cache_key = (shape, None if mask is None else mask.copy())
        self._cache_weights = weights
        return weights

    def _scratch(self, name: str, h: int, w: int, cn: int, dtype: type) -> np.ndarray:
        """An (h, w[, cn]) view of a reused scratch array, grown on demand (never shrunk).

        The "ones" buffer is filled with 1 once; the others hold garbage until written.
        """
        buf = self._scratch_bufs.get(name)
        if buf is None or buf.shape[0] < h or buf.shape[1] < w:
            bh = h if buf is None else max(buf.shape[0], h)
            bw = w if buf is None else max(buf.shape[1], w)
            shape = (bh, bw) if cn == 1 else (bh, bw, cn)
            buf = np.ones(shape, dtype) if name == "ones" else np.empty(shape, dtype)
            self._scratch_bufs[name] = buf
        return buf[:h, :w]

    def _ensure_buffer(self, need: tuple[int, int, int, int]) -> None:
        """Grow the accumulation buffer (with slack, within the cap) to contain `need`."""
        bh, bw = self._weight.shape
        bx0, by0 = self._buf_x0, self._buf_y0
        bx1, by1 = bx0 + bw, by0 + bh
        nx0, ny0, nx1, ny1 = need
        empty = bw == 0 or bh == 0
        if not empty and nx0 >= bx0 and ny0 >= by0 and nx1 <= bx1 and ny1 <= by1:
            return
        cap = self._config.max_canvas_px
        new_x0, new_x1 = self._grow_axis(nx0, nx1, None if empty else (bx0, bx1), cap)
        new_y0, new_y1 = self._grow_axis(ny0, ny1, None if empty else (by0, by1), cap)
        new_sum = np.zeros((new_y1 - new_y0, new_x1 - new_x0, self._channels), np.float32)
        new_weight = np.zeros((new_y1 - new_y0, new_x1 - new_x0), np.float32)
        if self._content is not None:  # only the content is nonzero: copy just that
            cx0, cy0, cx1, cy1 = self._content
            src = (slice(cy0 - by0, cy1 - by0), slice(cx0 - bx0, cx1 - bx0))
            dst = (slice(cy0 - new_y0, cy1 - new_y0), slice(cx0 - new_x0, cx1 - new_x0))
            new_sum[dst] = self._sum[src]
            new_weight[dst] = self._weight[src]
        log.debug(
            "canvas buffer %dx%d -> %dx%d (origin %d,%d -> %d,%d)",
            bw,
            bh,
            new_x1 - new_x0,
            new_y1 - new_y0,
            bx0,
            by0,
            new_x0,
            new_y0,
        )
        self._sum, self._weight = new_sum, new_weight
        self._buf_x0, self._buf_y0 = new_x0, new_y0

    @staticmethod
    def _grow_axis(lo: int, hi: int, current: tuple[int, int] | None, cap: int) -> tuple[int, int]:
        """New buffer extent on one axis: contains [lo, hi), slack where it grows, <= cap long."""
        pad = max(_MIN_SLACK_PX, math.ceil(_SLACK_FRACTION * (hi - lo)))
        if current is None:
            slack_lo = slack_hi = pad
        else:
            slack_lo = pad if lo < current[0] else lo - current[0]  # keep existing slack
            slack_hi = pad if hi > current[1] else current[1] - hi
        room = max(cap - (hi - lo), 0)
        if slack_lo + slack_hi > room:
            total = slack_lo + slack_hi
            slack_lo = slack_lo * room // total
            slack_hi = min(slack_hi, room - slack_lo)
        return lo - slack_lo, hi + slack_hi


# --------------------------------------------------------------------------------- compositing


def _weights_from_small(small: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A per-cell weight map of the analysis grid, resized to the frame's (h, w)."""
    h, w = shape
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


class _Planes(Canvas):
    """Several 3-channel average-blend canvases that always share placements and masks, as
    one: the first plane is this canvas, the others only add their sums, so each frame's
    weights are computed and warped once for all. Every plane holds what a `Canvas` of its
    own would hold, bit for bit."""

    def __init__(self, config: ComposeConfig, planes: int) -> None:
        super().__init__(dataclasses.replace(config, blend="average"), 3)
        self._more_sums = [self._sum.copy() for _ in range(planes - 1)]
        self._more_images: list[np.ndarray] = []

    def add_planes(
        self, images: list[np.ndarray], H_frame_to_ref: np.ndarray, mask: np.ndarray
    ) -> None:
        """`Canvas.add` of one (h, w, 3) float32 image per plane, all at the same place."""
        self._more_images = images[1:]
        try:
            self.add(images[0], H_frame_to_ref, mask)
        finally:
            self._more_images = []

    def planes_in_frame(
        self, H_frame_to_ref: np.ndarray, frame_shape: tuple[int, ...]
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """`content_in_frame(..., channel=None)` of every plane at scale 1: ((h, w, 3) values
        per plane, valid)."""
        h, w = int(frame_shape[0]), int(frame_shape[1])
        sums = [self._sum, *self._more_sums]
        values = [np.zeros((h, w, 3), np.float32) for _ in sums]
        valid = np.zeros((h, w), bool)
        if self._content is None or h == 0 or w == 0:
            return values, valid
        roi = self._roi_under(H_frame_to_ref, (h, w), (h, w))
        if roi is None:
            return values, valid
        weight = self._sampled(self._weight, roi, (w, h))
        valid = weight > _MIN_SAMPLED_WEIGHT
        for total, out in zip(sums, values, strict=True):
            warped = self._sampled(total, roi, (w, h))
            np.divide(warped, weight[..., None], out=out, where=valid[..., None])
        return values, valid

    def _accumulate_more(self, M: np.ndarray, valid: np.ndarray, roi: tuple[slice, slice]) -> None:
        rh, rw = valid.shape
        for image, total in zip(self._more_images, self._more_sums, strict=True):
            warped = self._scratch("warped_more", rh, rw, 3, np.float32)
            cv2.warpPerspective(
                image, M, (rw, rh), dst=warped, flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
            )  # fmt: skip
            cv2.accumulate(warped, total[roi], valid)

    def _ensure_buffer(self, need: tuple[int, int, int, int]) -> None:
        before = (self._buf_x0, self._buf_y0, self._weight.shape)
        old_x0, old_y0 = self._buf_x0, self._buf_y0
        super()._ensure_buffer(need)
        if (self._buf_x0, self._buf_y0, self._weight.shape) == before:
            return
        grown = []
        for total in self._more_sums:
            new = np.zeros_like(self._sum)
            if self._content is not None:  # only the content is nonzero: copy just that
                cx0, cy0, cx1, cy1 = self._content
                src = (slice(cy0 - old_y0, cy1 - old_y0), slice(cx0 - old_x0, cx1 - old_x0))
                dst = (
                    slice(cy0 - self._buf_y0, cy1 - self._buf_y0),
                    slice(cx0 - self._buf_x0, cx1 - self._buf_x0),
                )
                new[dst] = total[src]
            grown.append(new)
        self._more_sums = grown


class _ShadingMosaic:
    """A low-resolution mosaic (the frames' analysis grids) of the frames' log intensity, each
    frame's gain taken out, and of the shading terms at which they saw each place: what each
    new frame is compared with for the flat-field estimate (`photometry.FlatFieldEstimator`)."""

    def __init__(self, config: ComposeConfig) -> None:
        self._planes = _Planes(config, 2)  # log I, 4 terms, 1 unused
        self._terms: tuple[tuple[int, ...], np.ndarray] | None = None

    def observe(
        self,
        photometry: VideoPhotometry,
        image: np.ndarray,
        H_frame_to_ref: np.ndarray,
        mask: np.ndarray,
    ) -> None:
        factor = analysis_factor(image.shape)
        size = small_size(image.shape, factor)
        small = shrink(image, size)
        lum = _mean(small.astype(np.float32))
        valid = inside_share(mask, size) > 0.999
        valid &= (lum > 2 * DARK) & (channel_max(small) < SATURATED)
        if self._terms is None or self._terms[0] != image.shape:
            self._terms = (image.shape, shading_terms(*normalised_grid(image.shape, size)))
        terms = self._terms[1]
        k = factor  # reference pixels per cell of the low-resolution mosaic
        K = np.array([[1 / k, 0, 0.5 / k - 0.5], [0, 1 / k, 0.5 / k - 0.5], [0, 0, 1.0]])
        M = (
            K
            @ np.asarray(H_frame_to_ref, np.float64)
            @ np.linalg.inv(scale_matrix(image.shape, size[::-1]))
        )
        log_lum = np.log(np.maximum(lum, DARK))
        offset = 0.0
        if self._planes.n_frames:
            planes, seen = self._planes.planes_in_frame(M, lum.shape)
            ok = valid & seen
            if ok.any():
                mosaic = np.concatenate(planes, axis=2)[ok]
                ratio = log_lum[ok] - mosaic[:, 0]
                n = terms.shape[-1]
                offset = photometry.observe_mosaic(
                    image.shape, ratio, terms[ok] - mosaic[:, 1 : 1 + n]
                )
        zeros = np.zeros((*lum.shape, 5 - terms.shape[-1]), np.float32)
        stack = np.concatenate([(log_lum - offset)[..., None], terms, zeros], axis=2)
        small_mask = valid.astype(np.uint8) * 255
        planes = [np.ascontiguousarray(stack[..., 3 * i : 3 * i + 3]) for i in range(2)]
        self._planes.add_planes(planes, M, small_mask)


class LiveCompositor:
    """Puts streamed frames on a growing (live) canvas and feeds the flat-field estimate.

    Each frame is compared with what the frames before it show under it: on a low-resolution
    mosaic of log intensities, for the video's flat-field estimate (`_ShadingMosaic`), and on
    the canvas, for its running exposure gain. With `correct` the frame is then flat-fielded,
    gain-compensated and weighted by its own quality before it is added (`best` and
    `multiband` feather here; the re-render, `render_segments`, does them); without, it is
    added as decoded (a preview the re-render replaces). Its sharpness factor is relative to
    the recent frames' (the re-render compares frames at the same places).
    """

    HISTORY = 15  # recent frames whose median sharpness is the reference
    # Every SHADING_EVERY-th frame feeds the flat-field estimate: consecutive frames see much
    # the same places at the same shading, and the observation costs ~5 ms a frame
    SHADING_EVERY = 2

    def __init__(
        self, config: ComposeConfig, photometry: VideoPhotometry, correct: bool = True
    ) -> None:
        self._config = config
        self.photometry = photometry
        self._correct = correct and (
            config.flatfield or config.exposure or config.sharpness_weighting
        )
        self._shading = _ShadingMosaic(config) if config.flatfield else None
        self._recent: deque[float] = deque(maxlen=self.HISTORY)
        self.frame_shape: tuple[int, int] | None = None  # (h, w) of the frames as decoded
        self._added = 0

    def add(
        self, canvas: Canvas, image: np.ndarray, H_frame_to_ref: np.ndarray, mask: np.ndarray
    ) -> float | None:
        """Observe, correct, weight and add a frame to `canvas` (raises `CanvasLimitError` like
        `Canvas.add`, before anything is observed); returns the gain applied (None: none)."""
        cfg = self._config
        if not canvas.fits(H_frame_to_ref, image.shape[:2]):
            canvas.add(image, H_frame_to_ref, mask)  # raises, naming the cap
        self.frame_shape = (int(image.shape[0]), int(image.shape[1]))
        if self._shading is not None and self._added % self.SHADING_EVERY == 0:
            self._shading.observe(self.photometry, image, H_frame_to_ref, mask)
        self._added += 1
        if not self._correct:
            canvas.add(image, H_frame_to_ref, mask)
            return None
        gain = None
        if cfg.exposure and canvas.n_frames:
            factor = analysis_factor(image.shape)
            mosaic, valid = canvas.content_in_frame(
                H_frame_to_ref, image.shape, 1.0 / factor, channel=None
            )
            size = mosaic.shape[1::-1]
            valid &= inside_share(mask, size) > 0.999
            gain = robust_gain(self.photometry.correct_small(image, size), mosaic, valid)
        corrected = self.photometry.correct(image, gain)
        weights = None
        if cfg.sharpness_weighting:
            quality = _quality(cfg, image, mask)
            sharp = quality.sharpness()
            median = float(np.median(sharp[quality.ramp > 0])) if quality.ramp.any() else 0.0
            reference = float(np.median(self._recent)) if self._recent else median
            self._recent.append(median)
            rho = median / reference if reference > 0 else 1.0
            small = quality.glare * np.float32(min(1.0, rho / SHARPNESS_KNEE) ** SHARPNESS_POWER)
            if PRECISION:
                small = small * _precision(self.photometry, image.shape, small.shape[::-1], gain)
            weights = _weights_from_small(small, image.shape[:2])
        canvas.add(corrected, H_frame_to_ref, mask, weights)
        return gain


def _mean(image: np.ndarray) -> np.ndarray:
    """Mean over the channels (a grey image as it is)."""
    return image if image.ndim == 2 else image.mean(axis=2)


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


def footprint_box(H: np.ndarray, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Half-open integer box (x0, y0, x1, y1) of a (h, w) frame placed by `H`."""
    h, w = shape
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float)
    mapped = corners @ np.asarray(H, np.float64).T
    xy = mapped[:, :2] / mapped[:, 2:]
    lo = np.floor(xy.min(axis=0) + _EDGE_EPS)
    hi = np.ceil(xy.max(axis=0) - _EDGE_EPS) + 1
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


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
        S = np.array([[1 / k, 0, 0.5 / k - 0.5], [0, 1 / k, 0.5 / k - 0.5], [0, 0, 1.0]])
        to_frame = np.linalg.inv(scale_matrix(frame_shape, small[::-1]))
        return S @ _translation(-float(self.x0), -float(self.y0)) @ H @ to_frame


def _warp_box(src: np.ndarray, H: np.ndarray, grid_shape: tuple[int, int], border: float = 0.0):
    """`src` warped by `H` into the part of a grid its footprint covers: (x0, y0, roi), or None
    when it falls outside."""
    h, w = src.shape[:2]
    x0, y0, x1, y1 = footprint_box(H, (h, w))
    x0, y0 = max(x0 - 1, 0), max(y0 - 1, 0)
    x1, y1 = min(x1 + 1, grid_shape[1]), min(y1 + 1, grid_shape[0])
    if x1 <= x0 or y1 <= y0:
        return None
    M = _translation(-float(x0), -float(y0)) @ H
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
    owner = {index: seg for seg, p in poses.items() for index in p}
    photometry = photometry if photometry is not None else VideoPhotometry(False, False)
    need_sharpest = config.sharpness_weighting or config.blend == "best"
    states: dict[int, _SegmentRender] = {}
    kept: dict[int, _Kept] = {}

    def state_of(seg: int, shape: tuple[int, int]) -> _SegmentRender:
        if seg not in states:
            boxes = np.array([footprint_box(H, shape) for H in poses[seg].values()])
            extent = (
                int(boxes[:, 0].min()),
                int(boxes[:, 1].min()),
                int(boxes[:, 2].max()),
                int(boxes[:, 3].max()),
            )
            q_grid = _Grid.over(extent, analysis_factor(shape))
            g_grid = _Grid.over(extent, max(shape) / GAIN_CELLS)
            zeros = np.zeros(q_grid.shape, np.float32)
            states[seg] = _SegmentRender(
                poses[seg], extent, q_grid, g_grid, zeros, zeros.copy(), zeros.copy()
            )
        return states[seg]

    def reads(known: Container[int] = (), measure: bool = True) -> Iterator[_Read]:
        """The segments' frames read, with their quality maps where `measure` (None where not
        needed, or for the `known` frames, whose image is not used)."""
        for index, image, mask in frames():
            if index in owner:
                measured = measure and need_sharpest and index not in known
                yield index, image, mask, _quality(config, image, mask) if measured else None

    two_passes = config.exposure or need_sharpest
    if two_passes:  # first pass: statistics only
        room = keep_bytes
        # read a frame ahead in a thread, while this one measures the frame before
        with Lookahead(reads(measure=False)) as first:
            for index, image, mask, _ in first:
                quality = _quality(config, image, mask) if need_sharpest else None
                st = state_of(owner[index], image.shape[:2])
                _first_pass(config, st, index, image, mask, quality, photometry)
                packed = np.packbits(mask != 0)  # only where the mask is nonzero matters
                if image.nbytes + packed.nbytes <= room:
                    kept[index] = _Kept(image, packed, quality)
                    room -= image.nbytes + packed.nbytes
        for seg, st in states.items():
            if config.exposure:
                st.gains = st.observations.solve()
                values = np.array(list(st.gains.values()))
                if len(values):
                    log.info(
                        "segment %d: exposure gains %.3f-%.3f (median %.3f) over %d frames",
                        seg, values.min(), values.max(), float(np.median(values)), len(values),
                    )  # fmt: skip

    def second_pass() -> Iterator[_Read]:
        """The frames again, in order: those kept from the first pass, the others read."""
        if two_passes and kept.keys() >= owner.keys():
            while kept:  # in the order read; each let go once added
                index = next(iter(kept))
                yield index, *kept.pop(index).unpacked()
            return
        with Lookahead(reads(kept.keys())) as again:
            for index, image, mask, quality in again:
                if index in kept:
                    yield index, *kept.pop(index).unpacked()
                else:
                    yield index, image, mask, quality

    for index, image, mask, quality in second_pass():  # second pass: the mosaic
        seg = owner[index]
        st = state_of(seg, image.shape[:2])
        if st.canvas is None:
            st.canvas = Canvas(config, extent=st.extent)
        H = st.poses[index]
        corrected = photometry.correct(image, st.gains.get(index))
        weights = None
        if need_sharpest:
            quality = quality if quality is not None else _quality(config, image, mask)
            q = _sharpness(config, quality)
            small = q.shape[1::-1]
            M = st.quality_grid.from_small(H, image.shape[:2], small)

            def here(grid: np.ndarray, M: np.ndarray = M, small: tuple[int, int] = small):
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
                    small_weights = small_weights * _precision(
                        photometry, image.shape, small, st.gains.get(index)
                    )
            weights = _weights_from_small(small_weights, image.shape[:2])
        if before_add is not None:
            before_add(index, st.canvas, image, H, mask)
        st.canvas.add(corrected, H, mask, weights)
    for st in states.values():
        if st.canvas is not None:
            st.canvas.flush()  # the blending thread's last frames, and the thread let go
    return {
        seg: Rendered(st.canvas, st.gains) for seg, st in states.items() if st.canvas is not None
    }


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


def _precision(
    photometry: VideoPhotometry,
    shape: tuple[int, ...],
    size: tuple[int, int],
    gain: float | None,
) -> np.ndarray:
    """How much the correction amplified a frame's noise, inverted: (shading / gain)^2 on its
    analysis grid of (w, h) = `size` (a vignetted corner, a dark frame brightened weigh less)."""
    shading = np.asarray(photometry.shading(shape, size), np.float32)
    return (shading / (1.0 if gain is None else gain)) ** 2 * np.ones(size[::-1], np.float32)


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


def _quality(config: ComposeConfig, image: np.ndarray, mask: np.ndarray) -> FrameQuality:
    factor = analysis_factor(image.shape)
    return frame_quality(image, mask, factor, config.feather_px, config.sharpness_weighting)


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
