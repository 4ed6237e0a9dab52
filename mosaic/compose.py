"""Mosaic canvas: accumulates warped frames into a growing canvas and blends them.

Frames arrive one at a time with their homography into the segment's reference frame
(`H_frame_to_ref`); the canvas never keeps frames, only float32 accumulators
(`sum_weighted` HxWxC and `weight` HxW) over a buffer that grows with slack as frames leave it.
Each frame is warped only into its own bounding box, so the cost of `add` does not grow with
the canvas.

Coordinates: pixel centres sit at integer coordinates (OpenCV's convention). The canvas
(what `render`, `coverage` and `shape` describe) is the bounding box of all placed frames;
`H_ref_to_canvas` is the translation from reference-frame pixels into it.

Seams: the image is warped bilinearly, and a warped pixel counts as valid only where *every*
source pixel its bilinear sample touches is valid (the weight map, -1e4 outside the valid
region, is warped linearly with the same homography and thresholded at 0). So neither the dark
outside of the field of view nor the zero border of the warp can leak into the mosaic, while
integer placements keep every pixel, the frame's outermost ring included.
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np

from mosaic.config import ComposeConfig
from mosaic.errors import CanvasLimitError
from mosaic.preprocess import scale_matrix

log = logging.getLogger(__name__)

_MIN_SLACK_PX = 256  # buffer growth: at least this many pixels ...
_SLACK_FRACTION = 0.25  # ... or this fraction of the needed extent, whichever is larger
# Weight given to invalid pixels before warping: far below any bilinear mix of valid weights
# (smallest nonzero OpenCV bilinear tap is 1/32^2), so "warped weight > 0" means all taps valid.
_INVALID_WEIGHT = 1.0e4
_EDGE_EPS = 1e-6  # tolerance when rounding a warped bounding box to whole pixels
_MIN_W = 1e-9  # homogeneous coordinate under which a corner counts as sent to infinity
_MIN_SAMPLED_WEIGHT = 1e-6  # resampled accumulated weight above which a pixel counts as covered


def _translation(tx: float, ty: float) -> np.ndarray:
    """3x3 float64 translation matrix."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


class Canvas:
    """Growing mosaic canvas with feather, average or last-wins blending."""

    def __init__(self, config: ComposeConfig, channels: int = 3) -> None:
        if config.blend not in ("feather", "average", "last"):
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
        self._feathered = config.blend == "feather" and config.feather_px > 0
        self._scratch_bufs: dict[str, np.ndarray] = {}

    # ----------------------------------------------------------------------------- queries

    @property
    def n_frames(self) -> int:
        """Number of frames added so far."""
        return self._n_frames

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
        """Blended mosaic, uint8 (H, W, C); pixels no frame covered are 0."""
        sum_c, weight_c = self._content_views()
        out = np.zeros(sum_c.shape, np.float32)
        covered = weight_c > 0
        np.divide(sum_c, weight_c[..., None], out=out, where=covered[..., None])
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
        channel: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The blended canvas seen from a frame placed by `H_frame_to_ref`: (values float32,
        valid bool), both of the frame's (h, w) = `frame_shape[:2]`, or of a copy resized by
        `scale` (rounded like `cv2.resize` sizes, pixel centres as `preprocess.scale_matrix`).

        `channel` picks one colour channel (1: green of BGR; ignored on a 1-channel canvas).
        Valid where some frame contributed: the accumulated sum and weight are both sampled
        bilinearly and divided, so a value is a weighted mean of covered pixels only and
        nothing of the empty canvas leaks in.
        """
        fh, fw = int(frame_shape[0]), int(frame_shape[1])
        h, w = max(round(fh * scale), 1), max(round(fw * scale), 1)
        values = np.zeros((h, w), np.float32)
        valid = np.zeros((h, w), bool)
        if self._content is None or fh == 0 or fw == 0:
            return values, valid
        H_out_to_frame = np.linalg.inv(scale_matrix((fh, fw), (h, w)))
        H_out_to_ref = np.asarray(H_frame_to_ref, np.float64) @ H_out_to_frame
        # Only the content under the frame's footprint is sampled (the buffer may be large).
        corners = np.array([[-1, -1, 1], [w, -1, 1], [-1, h, 1], [w, h, 1]], float)
        mapped = corners @ H_out_to_ref.T
        if not np.all(np.isfinite(mapped)) or np.any(mapped[:, 2] <= _MIN_W):
            return values, valid
        xy = mapped[:, :2] / mapped[:, 2:]
        cx0, cy0, cx1, cy1 = self._content
        x0 = max(int(np.floor(xy[:, 0].min())) - 1, cx0)
        y0 = max(int(np.floor(xy[:, 1].min())) - 1, cy0)
        x1 = min(int(np.ceil(xy[:, 0].max())) + 2, cx1)
        y1 = min(int(np.ceil(xy[:, 1].max())) + 2, cy1)
        if x1 <= x0 or y1 <= y0:
            return values, valid
        rows = slice(y0 - self._buf_y0, y1 - self._buf_y0)
        cols = slice(x0 - self._buf_x0, x1 - self._buf_x0)
        sum_roi, weight_roi = self._sum[rows, cols], self._weight[rows, cols]
        M = _translation(-float(x0), -float(y0)) @ H_out_to_ref  # output -> ROI pixels
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        warped_sum = cv2.warpPerspective(sum_roi, M, (w, h), flags=flags)
        weight = cv2.warpPerspective(weight_roi, M, (w, h), flags=flags)
        if warped_sum.ndim == 3:
            warped_sum = warped_sum[..., min(channel, warped_sum.shape[2] - 1)]
        valid = weight > _MIN_SAMPLED_WEIGHT
        np.divide(warped_sum, weight, out=values, where=valid)
        return values, valid

    # ----------------------------------------------------------------------------- adding

    def add(
        self, image: np.ndarray, H_frame_to_ref: np.ndarray, mask: np.ndarray | None = None
    ) -> None:
        """Warp `image` into the canvas and blend it in.

        `mask` (uint8 HxW, nonzero = valid field of view) limits which pixels contribute;
        None means the whole frame. Raises `CanvasLimitError` without touching the canvas
        if the frame would push either side of the canvas beyond `max_canvas_px`.
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
        warped = self._scratch("warped", rh, rw, cn, np.uint8)
        cv2.warpPerspective(image, M, (rw, rh), dst=warped, flags=flags, borderMode=border)
        weight = self._scratch("weight", rh, rw, 1, np.float32)
        cv2.warpPerspective(
            self._frame_weights((h, w), mask),
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
        elif not self._feathered:  # average
            cv2.accumulate(warped, sum_roi, valid)
            cv2.accumulate(self._scratch("ones", rh, rw, 1, np.float32), weight_roi, valid)
        else:  # feather
            weight_c = weight
            if cn > 1:
                weight_c = self._scratch("weight_c", rh, rw, cn, np.float32)
                cv2.merge([weight] * cn, dst=weight_c)
            warped_f = self._scratch("warped_f", rh, rw, cn, np.float32)
            np.copyto(warped_f, warped)
            cv2.accumulateProduct(warped_f, weight_c, sum_roi, valid)
            cv2.accumulate(weight, weight_roi, valid)
        self._content = union
        self._n_frames += 1

    # ----------------------------------------------------------------------------- internals

    def _check_image(self, image: np.ndarray) -> np.ndarray:
        """Validate dtype and channel count; returns HxW (1 channel) or HxWxC."""
        if image.dtype != np.uint8:
            raise ValueError(f"frame must be uint8, got {image.dtype}")
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
        valid = np.full(shape, 1, np.uint8) if mask is None else (mask != 0).astype(np.uint8)
        if self._feathered:
            feather = np.float32(self._config.feather_px)
            padded = cv2.copyMakeBorder(valid, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
            dist = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_5)[1:-1, 1:-1]
            weights = np.minimum(dist, feather) / feather
        else:
            weights = np.ones(shape, np.float32)
        weights[valid == 0] = -_INVALID_WEIGHT
        self._cache_key = (shape, None if mask is None else mask.copy())
        self._cache_weights = np.ascontiguousarray(weights, dtype=np.float32)
        return self._cache_weights

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
