"""Viewer sinks for the pipeline: a no-op by default, or the live rerun viewer (issue 5).

This is the only module of the project importing rerun, and it does so lazily inside
`RerunViewer`, so `--rerun off` (the `NullViewer`) imports nothing heavy.

Recording layout (timeline `frame`, sequence = frame index in the video):

    video/frame                  input frame, JPEG, downscaled to `frame_max_side`
    video/frame/keypoints        keypoints; class inlier / outlier (matched, rejected) / unmatched
    video/frame/matches          segment from each matched keypoint to the position of its match
                                 in the reference (previous or key) frame, both drawn in the
                                 current frame's pixels; inlier / outlier
    mosaic/canvas                mosaic canvas snapshot every `canvas_every` frames (and after the
                                 last one), JPEG, downscaled to `canvas_max_side`
    mosaic/outline               the frame's outline on the latest canvas snapshot
    metrics/...                  keypoints, matches, inliers, reproj_error_px, quality
                                 (agreement with the mosaic, mosaic.quality), ms/<stage>,
                                 ms/total, ms/viewer (this sink's own cost), fps
    log/status                   one text entry per frame: registered / failed (reason) / skipped;
                                 a registered frame under [compose] quality_threshold is FLAGGED
    log/python/...               Python `logging` records of the `mosaic` loggers
    run/config, run/video        static: the run's config (TOML) and the input's metadata
    run/report                   static, at the end: the report summary
    final/mosaic                 static, at the end: the written main mosaic (after pose-graph
                                 refinement and re-rendering), JPEG, downscaled to
                                 `canvas_max_side`

`mosaic compare` (`RerunViewer(kind="compare")`, `comparison`): three static layers in the
baseline's pixels, one 2D space (`compare`), drawn bottom to top, each toggled in the viewer:

    compare/baseline             the baseline mosaic (RGB, lossless)
    compare/followup             the follow-up warped onto the baseline (RGBA: transparent where
                                 it shows no retina), equal to followup_warped.png
    compare/change               the change map as a heat map (RGBA: transparent below the
                                 threshold's half, opaque from twice it)
    compare/change/regions       the changed regions' boxes
    run/report                   static: compare.json's figures

Coordinates: the pipeline uses OpenCV's convention (pixel centres at integers), rerun draws
pixel (u, v) over [u, u + 1) x [v, v + 1); points are shifted by half a pixel before scaling.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import socket
import sys
import time
import uuid
import weakref
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import quote

import numpy as np

from mosaic.config import config_to_dict
from mosaic.errors import ConfigError, OutputError

if TYPE_CHECKING:
    from mosaic.canvas import Canvas
    from mosaic.compare import Comparison
    from mosaic.config import Config
    from mosaic.io import VideoInfo
    from mosaic.pipeline import FrameEvent
    from mosaic.report import BuildReport

log = logging.getLogger(__name__)

VIEWER_MODES = ("off", "spawn", "save", "serve", "connect")  # `--rerun` choices
DEFAULT_CONNECT_URL = "rerun+http://127.0.0.1:9876/proxy"
APPLICATION_ID = "retina-mosaic"

# Keypoint / match classes (class ids of the annotation context logged under `video`).
UNMATCHED, OUTLIER, INLIER = 0, 1, 2
_CLASSES = {
    UNMATCHED: ("unmatched", (150, 150, 150)),
    OUTLIER: ("outlier", (235, 60, 50)),
    INLIER: ("inlier", (40, 210, 80)),
}
_STAGE_COLORS = {
    "preprocess": (140, 140, 140),
    "detect": (70, 130, 230),
    "describe": (150, 90, 220),
    "match": (240, 160, 40),
    "estimate": (230, 70, 70),
    "compose": (40, 180, 170),
}
_LEVELS = {"registered": "INFO", "failed": "WARN", "skipped": "WARN"}
VIEWER_KINDS = ("build", "compare")  # what a recording shows: one build, or one comparison
# `mosaic compare`'s layers, in one 2D space: entity under COMPARE_ORIGIN -> draw order
COMPARE_ORIGIN = "compare"
COMPARE_LAYERS = {"baseline": 0.0, "followup": 1.0, "change": 2.0}


class Viewer(Protocol):
    """What the pipeline tells a viewer."""

    def frame(self, event: FrameEvent) -> None:
        """One frame was processed (registered, failed or skipped)."""
        ...

    def finish(self, report: BuildReport, mosaic: np.ndarray | None = None) -> None:
        """The run ended; `report` is the final report, `mosaic` the written main mosaic."""
        ...


class ComparisonViewer(Protocol):
    """What `mosaic compare` tells a viewer: one comparison, then the end."""

    def comparison(
        self, baseline: np.ndarray, comparison: Comparison, result: Mapping[str, Any]
    ) -> None:
        """Two visits on the baseline's map (`baseline`: its BGR image) and what changed."""
        ...

    def close(self) -> None:
        """Flush and detach; a saved recording is complete afterwards."""
        ...


class NullViewer:
    """Viewer off: costs nothing."""

    def frame(self, event: FrameEvent) -> None:
        pass

    def finish(self, report: BuildReport, mosaic: np.ndarray | None = None) -> None:
        pass

    def comparison(
        self, baseline: np.ndarray, comparison: Comparison, result: Mapping[str, Any]
    ) -> None:
        pass

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------------------------
# Pure helpers (numpy / OpenCV only)
# --------------------------------------------------------------------------------------------


def fit_scale(shape: tuple[int, ...], max_side: int) -> float:
    """Downscale factor (<= 1) bringing the longer side of an image of `shape` to `max_side`."""
    return min(1.0, max_side / max(shape[0], shape[1], 1))


def encode_jpeg(image: np.ndarray, scale: float, quality: int) -> tuple[bytes, tuple[float, float]]:
    """JPEG bytes of a BGR/grey uint8 image resized by `scale`, and the exact (sx, sy) used."""
    import cv2

    h, w = image.shape[:2]
    if scale < 1.0:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise OutputError(f"cannot JPEG-encode a {w}x{h} image for the viewer")
    return buf.tobytes(), (image.shape[1] / w, image.shape[0] / h)


def to_display(xy: np.ndarray, scale_xy: tuple[float, float]) -> np.ndarray:
    """(N, 2) OpenCV pixel coords -> rerun coords of the image shown at (sx, sy)."""
    return ((xy + 0.5) * np.asarray(scale_xy, np.float32)).astype(np.float32, copy=False)


def keypoint_classes(n_keypoints: int, idx_b: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """Class of each current keypoint: INLIER, OUTLIER (matched but rejected) or UNMATCHED."""
    classes = np.full(n_keypoints, UNMATCHED, np.uint16)
    classes[idx_b] = OUTLIER
    classes[idx_b[inliers]] = INLIER
    return classes


def frame_outline(H_frame_to_display: np.ndarray, width: int, height: int) -> np.ndarray:
    """Closed (5, 2) outline of a width x height frame (pixel edges) mapped by a homography."""
    x1, y1 = width - 0.5, height - 0.5
    corners = np.array([[-0.5, -0.5, 1], [x1, -0.5, 1], [x1, y1, 1], [-0.5, y1, 1]], np.float64)
    mapped = corners @ H_frame_to_display.T
    pts = (mapped[:, :2] / mapped[:, 2:]).astype(np.float32)
    return np.vstack([pts, pts[:1]])


def compare_layers(
    baseline: np.ndarray,
    warped: np.ndarray,
    warped_covered: np.ndarray,
    change: np.ndarray,
    threshold: float,
) -> dict[str, np.ndarray]:
    """The three layers of a comparison as rerun shows them (uint8, baseline's pixels):
    baseline RGB; follow-up RGBA, transparent where it has no retina (so the baseline shows
    through); change RGBA, an inferno heat map of `change` (spreads) up to twice `threshold`,
    transparent below half the threshold and opaque from twice it."""
    import cv2

    def rgb(image: np.ndarray) -> np.ndarray:
        code = cv2.COLOR_GRAY2RGB if image.ndim == 2 else cv2.COLOR_BGR2RGB
        return cv2.cvtColor(image, code)

    alpha = np.where(warped_covered, 255, 0).astype(np.uint8)
    level = np.clip(change / (2 * threshold), 0, 1)
    heat = cv2.applyColorMap((level * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    opacity = np.clip((change - 0.5 * threshold) / (1.5 * threshold), 0, 1)
    return {
        "baseline": rgb(baseline),
        "followup": np.dstack([rgb(warped), alpha]),
        "change": np.dstack([rgb(heat), (opacity * 255).astype(np.uint8)]),
    }


def draw_pair_matches(
    fixed: np.ndarray,
    moving: np.ndarray,
    xy_fixed: np.ndarray,
    xy_moving: np.ndarray,
    idx_fixed: np.ndarray,
    idx_moving: np.ndarray,
    inliers: np.ndarray,
    max_lines: int = 50,
) -> np.ndarray:
    """FIXED | MOVING side by side (BGR uint8, height of the taller, widths added) with every
    keypoint drawn (the viewer's colours: green inlier, red matched but rejected, grey
    unmatched) and a green line for each inlier match (fixed point to moving point); at most
    `max_lines` of them, evenly picked in match order, so that the images stay visible.

    `xy_*`: (N, 2) keypoints in each image's pixels; match k pairs `xy_fixed[idx_fixed[k]]` with
    `xy_moving[idx_moving[k]]`; `inliers`: (M,) bool over the matches."""
    import cv2

    def bgr(image: np.ndarray) -> np.ndarray:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image

    (hf, wf), (hm, wm) = fixed.shape[:2], moving.shape[:2]
    out = np.zeros((max(hf, hm), wf + wm, 3), np.uint8)
    out[:hf, :wf] = bgr(fixed)
    out[:hm, wf:] = bgr(moving)
    thick = max(1, round(max(out.shape[:2]) / 800))
    radius = thick + 1
    idx_fixed, idx_moving = np.asarray(idx_fixed, np.intp), np.asarray(idx_moving, np.intp)
    inliers = np.asarray(inliers, bool)
    offset = np.array([wf, 0], np.float64)
    for xy, idx, shift in ((xy_fixed, idx_fixed, 0 * offset), (xy_moving, idx_moving, offset)):
        classes = keypoint_classes(len(xy), idx, inliers)
        for cls in (UNMATCHED, OUTLIER, INLIER):  # inliers drawn last, on top
            colour = _CLASSES[cls][1][::-1]  # RGB -> BGR
            for x, y in np.round(np.asarray(xy)[classes == cls] + shift).astype(int).tolist():
                cv2.circle(out, (x, y), radius, colour, thick, lineType=cv2.LINE_AA)
    colour = _CLASSES[INLIER][1][::-1]
    picked = np.flatnonzero(inliers)
    if len(picked) > max_lines:
        picked = picked[np.linspace(0, len(picked) - 1, max_lines).round().astype(int)]
    a = np.round(np.asarray(xy_fixed)[idx_fixed[picked]]).astype(int)
    b = np.round(np.asarray(xy_moving)[idx_moving[picked]] + offset).astype(int)
    for p, q in zip(a.tolist(), b.tolist(), strict=True):
        cv2.line(out, tuple(p), tuple(q), colour, thick, lineType=cv2.LINE_AA)
    return out


def pair_matches_picture(
    fixed: np.ndarray,
    moving: np.ndarray,
    config: Config,
    extractor: Any,
    H_moving_to_fixed: np.ndarray | None,
    Q_moving_to_fixed: np.ndarray | None = None,
    inverted: tuple[bool, bool] = (False, False),
) -> np.ndarray:
    """`mosaic register --matches`: the pair's keypoints and matches as `register_pair` finds
    them (`pairs.match_pair`: each image at its working size, mapped to its full-resolution
    pixels), an inlier being a match that the final transform (Q if given, else H; none when
    failed) carries to within RANSAC's threshold at full resolution; drawn by
    `draw_pair_matches`. `inverted`: (fixed, moving) registered inverted
    (`Registration.inverted`, reversed)."""
    from mosaic.features import to_frame_pixels
    from mosaic.pairs import match_pair
    from mosaic.preprocess import inverted_as
    from mosaic.registration import apply_homography, apply_quadratic

    shown = fixed, moving
    paired = match_pair(*inverted_as(fixed, moving, inverted), config, extractor)
    xys, scales = [], []
    for features, S in ((paired.fixed, paired.S_fixed), (paired.moving, paired.S_moving)):
        scale = 1.0 if S is None else float(S[0, 0])
        xys.append(to_frame_pixels(features.xy, np.float32(1.0 / scale)))
        scales.append(scale)
    matches = paired.matches
    a, b = xys[0][matches.idx_a], xys[1][matches.idx_b]
    inliers = np.zeros(len(matches), bool)
    if H_moving_to_fixed is not None and len(matches):
        if Q_moving_to_fixed is not None:
            mapped = apply_quadratic(np.asarray(Q_moving_to_fixed), b)
        else:
            mapped = apply_homography(np.asarray(H_moving_to_fixed), b)
        error = np.linalg.norm(mapped - a, axis=1)
        inliers = error <= config.registration.reproj_threshold_px / min(scales)
    return draw_pair_matches(*shown, *xys, matches.idx_a, matches.idx_b, inliers)


def config_toml(tables: Mapping[str, Mapping[str, Any]]) -> str:
    """The config as TOML text (what a `--config` file with these values would contain)."""
    lines: list[str] = []
    for table, values in tables.items():
        lines.append(f"[{table}]")
        lines += [f"{key} = {json.dumps(value)}" for key, value in values.items()]
        lines.append("")
    return "\n".join(lines)


def _markdown_table(rows: Mapping[str, Any]) -> str:
    body = "\n".join(f"| {key} | {value} |" for key, value in rows.items())
    return f"| | |\n|---|---|\n{body}\n"


def _scale_translate(sx: float, sy: float, tx: float, ty: float) -> np.ndarray:
    return np.array([[sx, 0.0, sx * tx], [0.0, sy, sy * ty], [0.0, 0.0, 1.0]])


def _status_text(event: FrameEvent) -> str:
    record = event.record
    head = f"frame {record.index} {record.status}"
    if record.reason is not None:
        return f"{head}: {record.reason}"
    if record.n_matches == 0:
        return f"{head}: reference of segment {record.segment}, {record.n_keypoints} keypoints"
    if record.flagged:
        head = f"{head}, FLAGGED (disagrees with the mosaic)"
    quality = "" if math.isnan(record.quality) else f", quality {record.quality:.2f}"
    return (
        f"{head}: {record.n_inliers}/{record.n_matches} inliers, "
        f"{record.reproj_error_px:.2f} px{quality}, {record.time_ms:.0f} ms"
    )


# --------------------------------------------------------------------------------------------
# The rerun viewer
# --------------------------------------------------------------------------------------------


class RerunViewer:
    """Logs every processed frame to a dedicated rerun recording (spawn, save, serve, connect)."""

    def __init__(
        self,
        mode: str,
        target: str | Path | None = None,
        config: Config | None = None,
        video_info: VideoInfo | None = None,
        *,
        canvas_every: int = 10,
        canvas_max_side: int = 1024,
        frame_max_side: int = 1024,
        jpeg_quality: int = 80,
        grpc_port: int = 9876,
        web_port: int = 9090,
        open_browser: bool = False,
        flush_tick_s: float = 1.0,
        logger_name: str = "mosaic",
        kind: str = "build",
        layer_max_side: int = 4096,
    ) -> None:
        import rerun as rr

        if kind not in VIEWER_KINDS:
            raise ConfigError(f"unknown viewer kind {kind!r} (choices: {', '.join(VIEWER_KINDS)})")
        if mode not in VIEWER_MODES or mode == "off":
            raise ConfigError(f"unknown rerun mode {mode!r} (choices: spawn, save, serve, connect)")
        if canvas_every < 1:
            raise ConfigError(f"canvas_every must be >= 1, got {canvas_every}")
        self.mode = mode
        self.url: str | None = None  # serve: the web viewer's URL; connect/spawn: the gRPC URL
        self.canvas_every = canvas_every
        self.canvas_max_side = canvas_max_side
        self.frame_max_side = frame_max_side
        self.jpeg_quality = jpeg_quality
        self.kind = kind
        self.layer_max_side = layer_max_side
        self._rr = rr
        # Batches of ~1 s instead of rerun's 0.2 s: several times fewer, larger chunks (each
        # carries ~2 KB of overhead), hence a smaller .rrd, at the price of ~1 s live latency.
        batching = rr.ChunkBatcherConfig(flush_tick=flush_tick_s)
        self._rec = rr.RecordingStream(
            APPLICATION_ID, recording_id=uuid.uuid4(), batcher_config=batching
        )
        self._open_sink(mode, target, grpc_port, web_port, open_browser)
        self._finished = False
        self._n_events = 0
        self._last_t = time.perf_counter()
        self._dt_ema: float | None = None
        self._last_index: int | None = None
        self._last_canvas: Canvas | None = None  # latest canvas seen, for the final snapshot
        self._last_H_frame_to_ref: np.ndarray | None = None
        self._last_frame_size: tuple[int, int] | None = None
        self._snapshot_of: weakref.ref[Canvas] | None = None
        self._snapshot_n_frames = 0
        self._H_ref_to_snapshot = np.eye(3)  # reference frame -> rerun coords of the snapshot
        self._composed_px: np.ndarray | None = None  # decoded pixels into the canvas'
        self._log_static(config, video_info)
        self._handler = _RecordingLogHandler(self._rec, "log/python")
        self._logger = logging.getLogger(logger_name)
        self._logger.addHandler(self._handler)

    # ------------------------------------------------------------------------------ set-up

    def _open_sink(
        self, mode: str, target: str | Path | None, grpc_port: int, web_port: int, browser: bool
    ) -> None:
        blueprint = make_compare_blueprint() if self.kind == "compare" else make_blueprint()
        rec = self._rec
        try:
            if mode == "save":
                if target is None:
                    raise ConfigError("rerun save needs a target .rrd file")
                rec.save(Path(target), default_blueprint=blueprint)
            elif mode == "connect":
                self.url = str(target) if target else DEFAULT_CONNECT_URL
                rec.connect_grpc(self.url, default_blueprint=blueprint)
            elif mode == "serve":
                _check_port_free(grpc_port)  # rerun reports a busy gRPC port only in its log
                grpc_url = rec.serve_grpc(grpc_port=grpc_port, default_blueprint=blueprint)
                self._rr.serve_web_viewer(
                    web_port=web_port, open_browser=browser, connect_to=grpc_url
                )
                self.url = f"http://localhost:{web_port}/?url={quote(grpc_url, safe='')}"
            else:  # spawn
                self._rr.spawn(
                    port=grpc_port,
                    executable_path=_viewer_executable(),
                    default_blueprint=blueprint,
                    recording=rec,
                )
                self.url = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        except (RuntimeError, OSError) as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise OutputError(f"cannot open the rerun viewer ({mode}): {first}") from exc

    def _log_static(self, config: Config | None, video_info: VideoInfo | None) -> None:
        rr, rec = self._rr, self._rec
        if video_info is not None:
            rec.send_recording_name(Path(str(video_info.path)).name)
        md = rr.MediaType.MARKDOWN
        if config is not None:
            text = f"```toml\n{config_toml(config_to_dict(config))}```\n"
            rec.log("run/config", rr.TextDocument(text, media_type=md), static=True)
        if video_info is not None:
            rows = dataclasses.asdict(video_info)
            rec.log("run/video", rr.TextDocument(_markdown_table(rows), media_type=md), static=True)
        if self.kind == "compare":
            return  # no frames, keypoints or metrics
        classes = [
            rr.ClassDescription(info=rr.AnnotationInfo(id=i, label=label, color=color))
            for i, (label, color) in _CLASSES.items()
        ]
        rec.log("video", rr.AnnotationContext(classes), static=True)
        series = {
            "keypoints": (150, 150, 150),
            "matches": (240, 160, 40),
            "inliers": (40, 210, 80),
            "reproj_error_px": (70, 130, 230),
            "quality": (250, 140, 60),
            "fps": (200, 80, 200),
            "ms/total": (230, 230, 230),
            "ms/viewer": (250, 220, 60),
        } | {f"ms/{stage}": color for stage, color in _STAGE_COLORS.items()}
        for name, color in series.items():
            style = rr.SeriesLines(colors=[color], names=[name.removeprefix("ms/")])
            rec.log(f"metrics/{name}", style, static=True)

    # ------------------------------------------------------------------------------ per frame

    def frame(self, event: FrameEvent) -> None:
        """Log one processed frame: image, keypoints, matches, canvas, outline, status, metrics."""
        start = time.perf_counter()
        rr, rec, record = self._rr, self._rec, event.record
        rec.set_time("frame", sequence=record.index)
        self._last_index = record.index
        if event.image is not None:
            self._log_frame(event)
        else:
            rec.log("video/frame", rr.Clear(recursive=True))
        self._composed_px = event.composed_px
        if event.canvas is not None and event.canvas.n_frames > 0:
            self._last_canvas = event.canvas
            new_segment = self._snapshot_of is None or self._snapshot_of() is not event.canvas
            if new_segment or self._n_events % self.canvas_every == 0:
                self._log_canvas(event.canvas)
        if record.H_frame_to_ref is not None and event.image is not None:
            self._last_H_frame_to_ref = record.H_frame_to_ref
            self._last_frame_size = (event.image.shape[1], event.image.shape[0])
            self._log_outline()
        else:
            self._last_H_frame_to_ref = None
            rec.log("mosaic/outline", rr.Clear(recursive=False))
        level = "WARN" if record.flagged else _LEVELS.get(record.status, "INFO")
        rec.log("log/status", rr.TextLog(_status_text(event), level=level))
        self._log_metrics(event)
        self._n_events += 1
        rec.log("metrics/ms/viewer", rr.Scalars((time.perf_counter() - start) * 1e3))

    def _log_frame(self, event: FrameEvent) -> None:
        rr, rec = self._rr, self._rec
        assert event.image is not None
        scale = fit_scale(event.image.shape, self.frame_max_side)
        jpeg, scale_xy = encode_jpeg(event.image, scale, self.jpeg_quality)
        rec.log("video/frame", rr.EncodedImage(contents=jpeg, media_type="image/jpeg"))
        features = event.features
        if features is None:
            rec.log("video/frame/keypoints", rr.Clear(recursive=False))
            rec.log("video/frame/matches", rr.Clear(recursive=False))
            return
        xy = to_display(features.xy, scale_xy)
        matches, reference = event.matches, event.reference
        inliers = np.zeros(0 if matches is None else len(matches), bool)
        if event.registration is not None and len(event.registration.inliers) == len(inliers):
            inliers = event.registration.inliers
        if matches is not None:
            classes = keypoint_classes(len(features), matches.idx_b, inliers)
        else:
            classes = np.full(len(features), UNMATCHED, np.uint16)
        radius = rr.Radius.ui_points(2.0)
        rec.log("video/frame/keypoints", rr.Points2D(xy, class_ids=classes, radii=radius))
        if matches is None or reference is None or len(matches) == 0:
            rec.log("video/frame/matches", rr.LineStrips2D(np.zeros((0, 2, 2), np.float32)))
            return
        ref_xy = to_display(reference.xy[matches.idx_a], scale_xy)
        segments = np.stack([xy[matches.idx_b], ref_xy], axis=1)
        match_classes = np.where(inliers, INLIER, OUTLIER).astype(np.uint16)
        strips = rr.LineStrips2D(segments, class_ids=match_classes, radii=rr.Radius.ui_points(0.75))
        rec.log("video/frame/matches", strips)

    def _log_canvas(self, canvas: Canvas) -> None:
        """Log a downscaled snapshot of the canvas and remember how reference coords map onto it."""
        image = canvas.render()
        jpeg, (sx, sy) = encode_jpeg(
            image, fit_scale(image.shape, self.canvas_max_side), self.jpeg_quality
        )
        self._rec.log(
            "mosaic/canvas", self._rr.EncodedImage(contents=jpeg, media_type="image/jpeg")
        )
        # canvas pixel c (OpenCV) is drawn at (c + 0.5) * s in the snapshot
        H_ref_to_canvas = canvas.H_ref_to_canvas
        if self._composed_px is not None:  # the canvas composed at another size
            H_ref_to_canvas = H_ref_to_canvas @ self._composed_px
        self._H_ref_to_snapshot = _scale_translate(sx, sy, 0.5, 0.5) @ H_ref_to_canvas
        self._snapshot_of = weakref.ref(canvas)
        self._snapshot_n_frames = canvas.n_frames

    def _log_outline(self) -> None:
        assert self._last_H_frame_to_ref is not None and self._last_frame_size is not None
        H = self._H_ref_to_snapshot @ self._last_H_frame_to_ref
        outline = frame_outline(H, *self._last_frame_size)
        self._rec.log(
            "mosaic/outline",
            self._rr.LineStrips2D(
                [outline], colors=[(255, 220, 0)], radii=self._rr.Radius.ui_points(1.5)
            ),
        )

    def _log_metrics(self, event: FrameEvent) -> None:
        rr, rec, record = self._rr, self._rec, event.record
        now = time.perf_counter()
        dt, self._last_t = now - self._last_t, now
        self._dt_ema = dt if self._dt_ema is None else 0.8 * self._dt_ema + 0.2 * dt
        values = {
            "keypoints": record.n_keypoints,
            "matches": record.n_matches,
            "inliers": record.n_inliers,
            "reproj_error_px": record.reproj_error_px,
            "quality": record.quality,
            "fps": 1.0 / self._dt_ema if self._dt_ema > 0 else math.nan,
            "ms/total": record.time_ms,
        } | {f"ms/{stage}": ms for stage, ms in record.stage_ms.items()}
        for name, value in values.items():
            rec.log(f"metrics/{name}", rr.Scalars(float(value)))

    # ------------------------------------------------------------------------------ compare

    def comparison(
        self, baseline: np.ndarray, comparison: Comparison, result: Mapping[str, Any]
    ) -> None:
        """Log a comparison's three layers (`compare_layers`) in one space, static, lossless
        (downscaled alike when the baseline's longer side exceeds `layer_max_side`), the
        changed regions' boxes and compare.json's figures."""
        import cv2

        from mosaic.compare import CHANGE_SIGMAS

        rr, rec = self._rr, self._rec
        layers = compare_layers(
            baseline, comparison.warped, comparison.warped_covered, comparison.change,
            CHANGE_SIGMAS,
        )  # fmt: skip
        scale = fit_scale(baseline.shape, self.layer_max_side)
        for name, image in layers.items():
            if scale < 1.0:
                size = (
                    max(1, round(image.shape[1] * scale)),
                    max(1, round(image.shape[0] * scale)),
                )
                image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            path = f"{COMPARE_ORIGIN}/{name}"
            rec.log(path, rr.Image(image, draw_order=COMPARE_LAYERS[name]), static=True)
        boxes = np.array([r.bbox for r in comparison.regions], np.float64).reshape(-1, 4)
        rec.log(
            f"{COMPARE_ORIGIN}/change/regions",
            rr.Boxes2D(
                mins=boxes[:, :2] * scale,
                sizes=(boxes[:, 2:] - boxes[:, :2] + 1) * scale,
                labels=[f"{r.mean_change:.1f}" for r in comparison.regions],
                colors=[(0, 255, 255)],
                draw_order=3.0,
            ),
            static=True,
        )
        keys = ("status", "model", "residual_px", "n_inliers", "correlation", "overlap_share")
        rows = {k: result.get(k) for k in keys} | {"regions": len(comparison.regions)}
        text = "# Comparison\n\n" + _markdown_table(rows)
        rec.log("run/report", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)

    # ------------------------------------------------------------------------------ end

    def finish(self, report: BuildReport, mosaic: np.ndarray | None = None) -> None:
        """Log the final canvas snapshot, the written mosaic (after refinement and
        re-rendering, it can differ from the live canvas) and the report, then `close`."""
        if self._finished:
            return
        rr, rec = self._rr, self._rec
        canvas = self._last_canvas
        if canvas is not None and self._last_index is not None:
            fresh = self._snapshot_of is not None and self._snapshot_of() is canvas
            if not (fresh and self._snapshot_n_frames == canvas.n_frames):
                rec.set_time("frame", sequence=self._last_index)
                self._log_canvas(canvas)
                if self._last_H_frame_to_ref is not None:
                    self._log_outline()
        self._last_canvas = None
        if mosaic is not None and mosaic.size:
            jpeg, _ = encode_jpeg(mosaic, fit_scale(mosaic.shape, self.canvas_max_side), 90)
            rec.log(
                "final/mosaic",
                rr.EncodedImage(contents=jpeg, media_type="image/jpeg"),
                static=True,
            )
        text = "# Run report\n\n" + _markdown_table(report.summary.to_dict())
        if report.segments:
            text += "\n## Segments\n\n" + "\n".join(
                f"- segment {s.index}: {s.frames} frames, {s.width}x{s.height} px"
                for s in report.segments
            )
        rec.log("run/report", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
        self.close()

    def close(self) -> None:
        """Detach from `logging` and flush; the file of `save` is complete afterwards."""
        if self._finished:
            return
        self._finished = True
        self._logger.removeHandler(self._handler)
        try:
            self._rec.flush(timeout_sec=10.0)
        except RuntimeError as exc:  # e.g. no viewer listening at the connect/spawn URL
            log.warning("rerun viewer did not receive everything: %s", str(exc).splitlines()[0])
        if self.mode != "serve":  # serve keeps the server alive for late viewers
            self._rec.disconnect()


class _RecordingLogHandler(logging.Handler):
    """rerun's logging handler, writing into a dedicated recording instead of the global one."""

    def __init__(self, recording: Any, path_prefix: str) -> None:
        import rerun as rr

        super().__init__()
        self._rr = rr
        self._rec = recording
        self._prefix = path_prefix
        self._levels = rr.LoggingHandler.LVL2NAME

    def emit(self, record: logging.LogRecord) -> None:
        try:
            level = self._levels.get(record.levelno) or record.levelname
            path = f"{self._prefix}/{record.name.replace('.', '/')}"
            self._rec.log(path, self._rr.TextLog(record.getMessage(), level=level))
        except Exception:  # a logging handler must never raise into the caller
            self.handleError(record)


def _check_port_free(port: int) -> None:
    with socket.socket() as probe:
        try:
            probe.bind(("0.0.0.0", port))
        except OSError as exc:
            raise OutputError(
                f"cannot serve the rerun viewer: port {port} is in use ({exc.strerror})"
            ) from exc


def _viewer_executable() -> str:
    """The native `rerun` viewer for `spawn` (PATH, else beside this Python: an unactivated
    venv); fails early with advice on a headless Linux machine, where no window can open."""
    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        raise OutputError(
            "rerun spawn needs a display (DISPLAY/WAYLAND_DISPLAY unset): "
            "use --rerun serve and open the printed URL, or --rerun save --rerun-target FILE.rrd"
        )
    found = shutil.which("rerun") or shutil.which("rerun", path=str(Path(sys.executable).parent))
    if found is None:
        raise OutputError("rerun spawn needs the `rerun` viewer executable (pip install rerun-sdk)")
    return found


def make_blueprint() -> Any:
    """Layout: frame + keypoints and time series on the left; canvas and logs on the right."""
    import rerun.blueprint as rrb

    counts = ["+ metrics/keypoints", "+ metrics/matches", "+ metrics/inliers"]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(origin="video/frame", name="frame + keypoints"),
                rrb.Tabs(
                    rrb.TimeSeriesView(origin="metrics", contents=counts, name="keypoints"),
                    rrb.TimeSeriesView(origin="metrics/ms", name="ms per stage"),
                    rrb.TimeSeriesView(origin="metrics/reproj_error_px", name="reproj error"),
                    rrb.TimeSeriesView(origin="metrics/quality", name="quality"),
                    rrb.TimeSeriesView(origin="metrics/fps", name="fps"),
                ),
                row_shares=[3, 2],
            ),
            rrb.Vertical(
                rrb.Tabs(
                    rrb.Spatial2DView(origin="mosaic", name="mosaic"),
                    rrb.Spatial2DView(origin="final", name="final mosaic"),
                ),
                rrb.Tabs(
                    rrb.TextLogView(origin="log", name="log"),
                    rrb.TextDocumentView(origin="run/report", name="report"),
                    rrb.TextDocumentView(origin="run/config", name="config"),
                    rrb.TextDocumentView(origin="run/video", name="video"),
                ),
                row_shares=[3, 2],
            ),
        ),
        rrb.TimePanel(expanded=True),
        collapse_panels=False,
    )


def make_compare_blueprint() -> Any:
    """Layout of a comparison: the three layers in one 2D space (toggle each in the blueprint
    panel), the figures beside it."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin=COMPARE_ORIGIN, name="visits on the baseline's map"),
            rrb.TextDocumentView(origin="run/report", name="comparison"),
            column_shares=[4, 1],
        ),
        collapse_panels=False,
    )


def make_compare_viewer(mode: str, target: str | Path | None, **options: Any) -> ComparisonViewer:
    """The viewer of `mosaic compare --rerun MODE`: `NullViewer` for off, else a rerun
    recording laid out for a comparison (`make_viewer`'s modes and targets)."""
    viewer = make_viewer(mode, target, None, None, kind="compare", **options)
    assert isinstance(viewer, NullViewer | RerunViewer)
    return viewer


def make_viewer(
    mode: str,
    target: str | Path | None,
    config: Config | None,
    video_info: VideoInfo | None,
    **options: Any,
) -> Viewer:
    """The viewer for `--rerun MODE`: `NullViewer` for off (rerun not imported), else rerun.

    `target` is the .rrd file for save and the gRPC URL for connect (default
    rerun+http://127.0.0.1:9876/proxy); the other modes take none. `options` go to `RerunViewer`.
    """
    if mode not in VIEWER_MODES:
        raise ConfigError(f"unknown rerun mode {mode!r} (choices: {', '.join(VIEWER_MODES)})")
    if target is not None and mode not in ("save", "connect"):
        raise ConfigError(f"a rerun target is only used with save or connect, not {mode}")
    if mode == "off":
        return NullViewer()
    return RerunViewer(mode, target, config, video_info, **options)
