"""The mosaic canvas: accumulates warped frames into a growing canvas and blends them.

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
Burt-Adelson: detail blended where the weight is, shading over ~32 px). What the frames are
weighted by is `mosaic.compose`'s; the re-render is `mosaic.render`'s.

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
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

import cv2
import numpy as np

from mosaic.blending import LaplacianBlender, shrink_noise
from mosaic.config import ComposeConfig
from mosaic.errors import CanvasLimitError
from mosaic.geometry import scale_matrix, translation

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
        return translation(-float(x0), -float(y0))

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
        return translation(-float(x0), -float(y0)) @ H_out_to_ref, rows, cols

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
        M = translation(-float(fx0), -float(fy0)) @ H
        warped, weight, valid = self._warped(image, M, (fx1 - fx0, fy1 - fy0), mask, weights)
        self._accumulate(warped, weight, valid, M, (fx0, fy0), weights is not None)
        self._content = union
        self._n_frames += 1

    def _warped(
        self,
        image: np.ndarray,
        M: np.ndarray,
        size: tuple[int, int],
        mask: np.ndarray | None,
        weights: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A frame warped by `M` into its box of (w, h) = `size`: (image, weight, valid), each
        a scratch view; valid is 255 where all of a pixel's bilinear taps are valid."""
        h, w = image.shape[:2]
        rw, rh = size
        flags, border = cv2.INTER_LINEAR, cv2.BORDER_CONSTANT
        warped = self._scratch(f"warped_{image.dtype}", rh, rw, self._channels, image.dtype.type)
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
        return warped, weight, valid

    def _accumulate(
        self,
        warped: np.ndarray,
        weight: np.ndarray,
        valid: np.ndarray,
        M: np.ndarray,
        origin: tuple[int, int],
        weighted: bool,
    ) -> None:
        """Blend a warped frame (`_warped`) into the accumulators at its box's `origin`
        (reference coords of its pixel (0, 0)) as the blend mode does; `weighted`: the frame
        came with weight factors."""
        rh, rw = valid.shape
        cn = self._channels
        fx0, fy0 = origin
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
        elif not self._feathered and not weighted:  # average
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
        """Hook of `add` (average blend): more planes under the same placement (`CanvasPlanes`)."""

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


class CanvasPlanes(Canvas):
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


def footprint_box(H: np.ndarray, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Half-open integer box (x0, y0, x1, y1) of a (h, w) frame placed by `H`."""
    h, w = shape
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float)
    mapped = corners @ np.asarray(H, np.float64).T
    xy = mapped[:, :2] / mapped[:, 2:]
    lo = np.floor(xy.min(axis=0) + _EDGE_EPS)
    hi = np.ceil(xy.max(axis=0) - _EDGE_EPS) + 1
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])
