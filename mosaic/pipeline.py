"""The mosaicking pipeline: each frame goes read → preprocess → detect → describe → match →
estimate → check → compose, and is accounted for in the report.

`MosaicBuilder.process` takes one decoded frame at a time (frames are streamed, never stored);
`MosaicBuilder.finish` renders the mosaic segment(s) and the report. Reading files, progress bars
and the viewer stay outside: the viewer is injected and is a no-op unless the user turns it on.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mosaic.compose import Canvas
from mosaic.config import Config, config_to_dict
from mosaic.errors import CanvasLimitError
from mosaic.features import FeatureExtractor, Features
from mosaic.matching import Matches, match_descriptors
from mosaic.preprocess import Prepared, prepare
from mosaic.registration import Registration, estimate_homography
from mosaic.viz import NullViewer, Viewer

log = logging.getLogger(__name__)

STAGES = ("preprocess", "detect", "describe", "match", "estimate", "compose")
REGISTERED, FAILED, SKIPPED = "registered", "failed", "skipped"


@dataclass
class FrameRecord:
    """What happened to one frame; becomes one entry of the report."""

    index: int
    status: str = SKIPPED
    reason: str | None = None
    segment: int | None = None
    H_frame_to_ref: np.ndarray | None = None  # into the segment's reference (first) frame
    n_keypoints: int = 0
    n_matches: int = 0
    n_inliers: int = 0
    reproj_error_px: float = float("nan")
    stage_ms: dict[str, float] = field(default_factory=dict)

    @property
    def time_ms(self) -> float:
        return float(sum(self.stage_ms.values()))


@dataclass(frozen=True)
class FrameEvent:
    """Everything the viewer may show about one processed frame."""

    record: FrameRecord
    image: np.ndarray | None
    prepared: Prepared | None
    features: Features | None
    matches: Matches | None
    registration: Registration | None
    canvas: Canvas | None


@dataclass(frozen=True)
class SegmentMosaic:
    """A rendered mosaic segment and the map from its reference frame into the image."""

    index: int
    image: np.ndarray  # uint8 HxWx3, the bounding box of the placed frames
    H_ref_to_mosaic: np.ndarray
    n_frames: int


@dataclass(frozen=True)
class MosaicResult:
    """Rendered segments (largest first is `main`) and the JSON-ready report."""

    segments: list[SegmentMosaic]
    report: dict[str, Any]

    @property
    def main(self) -> SegmentMosaic | None:
        """The segment holding the most frames: the mosaic written to the requested output."""
        return max(self.segments, key=lambda s: s.n_frames, default=None)


class _Timer:
    """Accumulates wall time per stage into a record."""

    def __init__(self, record: FrameRecord):
        self._record = record

    def run(self, stage: str, fn: Callable[..., Any], *args: Any) -> Any:
        start = time.perf_counter()
        out = fn(*args)
        self._record.stage_ms[stage] = (time.perf_counter() - start) * 1e3
        return out


class MosaicBuilder:
    """Registers frames one by one (frame-to-frame chaining) and accumulates the mosaic."""

    def __init__(
        self,
        config: Config,
        extractor: FeatureExtractor | None = None,
        viewer: Viewer | None = None,
    ):
        self.config = config
        self.extractor = extractor if extractor is not None else FeatureExtractor(config.features)
        self.viewer = viewer if viewer is not None else NullViewer()
        self.records: list[FrameRecord] = []
        self.stopped = False  # set by on_failure = "stop" at the first failed frame
        self._segments: list[SegmentMosaic] = []
        self._canvas: Canvas | None = None
        self._prev: Features | None = None
        self._H_prev_to_ref = np.eye(3)
        self._started = time.perf_counter()

    def process(
        self, index: int, image: np.ndarray | None, error: str | None = None
    ) -> FrameRecord:
        """Register and compose one frame; a frame that could not be decoded is skipped."""
        record = FrameRecord(index=index)
        self.records.append(record)
        if image is None:
            record.reason = error or "frame could not be decoded"
            log.warning("frame %d skipped: %s", index, record.reason)
            self.viewer.frame(FrameEvent(record, None, None, None, None, None, None))
            return record
        timer = _Timer(record)
        prepared = timer.run("preprocess", prepare, image, self.config.preprocess)
        detected = timer.run("detect", self.extractor.detect, prepared)
        features = timer.run("describe", self.extractor.describe, prepared, detected)
        record.n_keypoints = len(features)

        matches = registration = None
        if self._prev is None:
            self._start_segment(record, image, prepared, features, timer, reason=None)
        else:
            matches = timer.run(
                "match",
                match_descriptors,
                self._prev.descriptors,
                features.descriptors,
                self.config.matching,
            )
            registration = timer.run(
                "estimate",
                estimate_homography,
                features.xy[matches.idx_b],
                self._prev.xy[matches.idx_a],
                self.config.registration,
            )
            record.n_matches, record.n_inliers = registration.n_matches, registration.n_inliers
            record.reproj_error_px = registration.reproj_error_px
            reason = registration.reason
            if registration.ok:
                H_frame_to_ref = self._H_prev_to_ref @ registration.H_cur_to_prev
                reason = self._compose(record, image, prepared, H_frame_to_ref, timer)
            if reason is not None:
                self._fail(record, image, prepared, features, timer, reason)
            else:
                self._advance(record, features)
        self.viewer.frame(
            FrameEvent(record, image, prepared, features, matches, registration, self._canvas)
        )
        return record

    def _compose(
        self,
        record: FrameRecord,
        image: np.ndarray,
        prepared: Prepared,
        H_frame_to_ref: np.ndarray,
        timer: _Timer,
    ) -> str | None:
        assert self._canvas is not None
        try:
            timer.run("compose", self._canvas.add, image, H_frame_to_ref, prepared.mask)
        except CanvasLimitError as exc:
            return str(exc)
        record.status, record.H_frame_to_ref = REGISTERED, H_frame_to_ref
        record.segment = len(self._segments)
        return None

    def _advance(self, record: FrameRecord, features: Features) -> None:
        self._prev, self._H_prev_to_ref = features, record.H_frame_to_ref

    def _fail(
        self,
        record: FrameRecord,
        image: np.ndarray,
        prepared: Prepared,
        features: Features,
        timer: _Timer,
        reason: str,
    ) -> None:
        record.status, record.reason = FAILED, reason
        policy = self.config.pipeline.on_failure
        log.info("frame %d failed (%s): %s", record.index, policy, reason)
        if policy == "stop":
            self.stopped = True
        elif policy == "restart":
            self._close_segment()
            self._start_segment(record, image, prepared, features, timer, reason)

    def _start_segment(
        self,
        record: FrameRecord,
        image: np.ndarray,
        prepared: Prepared,
        features: Features,
        timer: _Timer,
        reason: str | None,
    ) -> None:
        """Make this frame the reference of a new mosaic segment."""
        self._canvas = Canvas(self.config.compose)
        self._compose(record, image, prepared, np.eye(3), timer)
        if reason is not None:  # a restart: the frame failed against the previous segment
            record.status, record.reason = FAILED, f"{reason}; started segment {record.segment}"
        self._advance(record, features)

    def _close_segment(self) -> None:
        if self._canvas is None or self._canvas.n_frames == 0:
            return
        canvas = self._canvas
        self._segments.append(
            SegmentMosaic(
                len(self._segments), canvas.render(), canvas.H_ref_to_canvas, canvas.n_frames
            )
        )
        self._canvas = None

    def finish(self, interrupted: bool = False) -> MosaicResult:
        """Render the open segment and build the report (also after an interruption)."""
        self._close_segment()
        report = build_report(self, interrupted)
        self.viewer.finish(report)
        return MosaicResult(list(self._segments), report)


def _leading_run(statuses: list[str]) -> int:
    """Registered frames from the first one until the first failure (skipped frames ignored)."""
    count = 0
    for status in statuses:
        if status == FAILED:
            break
        count += status == REGISTERED
    return count


def _longest_run(statuses: list[str]) -> int:
    best = run = 0
    for status in statuses:
        if status == FAILED:
            run = 0
        elif status == REGISTERED:
            run += 1
            best = max(best, run)
    return best


def _frame_entry(record: FrameRecord, segments: list[SegmentMosaic]) -> dict[str, Any]:
    H_to_canvas = None
    if record.H_frame_to_ref is not None and record.segment is not None:
        H = segments[record.segment].H_ref_to_mosaic @ record.H_frame_to_ref
        H_to_canvas = (H / H[2, 2]).tolist()
    entry: dict[str, Any] = {
        "index": record.index,
        "status": record.status,
        "segment": record.segment,
        "H_to_canvas": H_to_canvas,
        "n_keypoints": record.n_keypoints,
        "n_matches": record.n_matches,
        "n_inliers": record.n_inliers,
        "reproj_error_px": None
        if np.isnan(record.reproj_error_px)
        else round(record.reproj_error_px, 3),
        "time_ms": round(record.time_ms, 2),
    }
    if record.reason is not None:
        entry["reason"] = record.reason
    return entry


def build_report(builder: MosaicBuilder, interrupted: bool) -> dict[str, Any]:
    """The JSON-ready report: summary, configuration and one entry per frame."""
    records = builder.records
    statuses = [r.status for r in records]
    attempts = [r for r in records if r.status != SKIPPED and r.n_matches > 0]
    stage_ms = {
        stage: round(float(np.mean(vals)), 3)
        for stage in STAGES
        if (vals := [r.stage_ms[stage] for r in records if stage in r.stage_ms])
    }
    elapsed = time.perf_counter() - builder._started
    summary = {
        "frames_read": len(records),
        "registered": statuses.count(REGISTERED),
        "failed": statuses.count(FAILED),
        "skipped": statuses.count(SKIPPED),
        "frames_until_failure": _leading_run(statuses),
        "longest_registered_run": _longest_run(statuses),
        "segments": len(builder._segments),
        "mean_matches": round(float(np.mean([r.n_matches for r in attempts])), 2)
        if attempts
        else 0.0,
        "mean_inliers": round(float(np.mean([r.n_inliers for r in attempts])), 2)
        if attempts
        else 0.0,
        "total_time_s": round(elapsed, 3),
        "fps": round(len(records) / elapsed, 2) if elapsed > 0 else 0.0,
        "mean_stage_ms": stage_ms,
        "detector": builder.extractor.detector.name,
        "strategy": "chain",
        "on_failure": builder.config.pipeline.on_failure,
        "stopped_at_failure": builder.stopped,
        "interrupted": interrupted,
    }
    return {
        "summary": summary,
        "segments": [
            {
                "index": s.index,
                "frames": s.n_frames,
                "width": int(s.image.shape[1]),
                "height": int(s.image.shape[0]),
            }
            for s in builder._segments
        ],
        "config": config_to_dict(builder.config),
        "frames": [_frame_entry(r, builder._segments) for r in records],
    }


def register_pair(
    fixed: np.ndarray, moving: np.ndarray, config: Config, extractor: FeatureExtractor
) -> Registration:
    """Register one image pair: the result's `H_cur_to_prev` maps `moving` into `fixed`."""
    prepared_fixed = prepare(fixed, config.preprocess)
    prepared_moving = prepare(moving, config.preprocess)
    features_fixed = extractor(prepared_fixed)
    features_moving = extractor(prepared_moving)
    matches = match_descriptors(
        features_fixed.descriptors, features_moving.descriptors, config.matching
    )
    return estimate_homography(
        features_moving.xy[matches.idx_b], features_fixed.xy[matches.idx_a], config.registration
    )
