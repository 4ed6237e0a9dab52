"""The report of a build: a summary, the configuration and one entry per frame, JSON-ready.

`build_report` reads the builder through `ReportInputs` (`MosaicBuilder.summary_inputs`), its
public read-only view; the names here (frame statuses, stages) are the report's vocabulary.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mosaic.compose import photometry_report
from mosaic.config import Config, config_to_dict
from mosaic.photometry import VideoPhotometry
from mosaic.registration import MODELS

if TYPE_CHECKING:
    from mosaic.pipeline import FrameRecord, SegmentMosaic

STAGES = ("preprocess", "detect", "describe", "match", "estimate", "compose")
REGISTERED, FAILED, SKIPPED = "registered", "failed", "skipped"


@dataclass(frozen=True)
class ReportInputs:
    """What the report reads of a `MosaicBuilder` (`MosaicBuilder.summary_inputs`)."""

    records: list[FrameRecord]
    started: float  # time.perf_counter() when the builder was made
    config: Config
    detector: str
    precision: str | None  # GLAMpoints' network precision ("auto" resolved), else None
    overlap: bool | None  # what `[pipeline] overlap` chose (None: not decided yet)
    stopped: bool  # stopped at the first failed frame (on_failure = "stop")
    field_offset_px: float | None  # median offset of the odd rows from the even rows
    looks_interlaced: bool
    H_frame_to_work: np.ndarray | None  # the frames' working size (None: as decoded)
    retina_diameter_px: float | None
    tracker_stats: list[dict[str, Any]]  # each segment's tracker counters, in segment order
    joined_stats: list[dict[str, Any]]  # the tracker counters of the segments joined
    rerendered: bool  # a segment's poses were refined (and the mosaic rendered again)
    blends: list[str]  # each segment's blending, in segment order
    photometry: VideoPhotometry
    frame_shape: tuple[int, int] | None  # (h, w) of the frames as decoded
    gain_solution: str | None


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


def _frame_entry(record: FrameRecord, mosaics: dict[int, SegmentMosaic]) -> dict[str, Any]:
    H_to_canvas = None
    if record.H_frame_to_ref is not None and record.segment in mosaics:
        H = mosaics[record.segment].H_ref_to_mosaic @ record.H_frame_to_ref
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
        "quality": None if np.isnan(record.quality) else round(record.quality, 3),
        "flagged": record.flagged,
        "deinterlaced": record.deinterlaced,
        "reflexes": record.reflexes,
        "lens_rim": None if record.lens_rim is None else [round(v, 1) for v in record.lens_rim],
        "blurred": record.blurred is not None,
        "blended": record.status == REGISTERED and record.blurred is None,
        "by_flow": record.by_flow,
        "gain": None if record.gain is None else round(record.gain, 4),
        "time_ms": round(record.time_ms, 2),
    }
    if record.status == REGISTERED and record.reference is not None:
        entry["reference"] = record.reference
        entry["model"] = record.model
        entry["coverage"] = None if np.isnan(record.coverage) else round(record.coverage, 3)
    if record.reason is not None:
        entry["reason"] = record.reason
    return entry


def _model_counts(records: list[FrameRecord]) -> dict[str, int]:
    """Registered frames per motion model (a segment's first frame has none), in MODELS order."""
    counts = Counter(r.model for r in records if r.status == REGISTERED and r.reference is not None)
    return {m: counts[m] for m in MODELS if counts[m]}


def _tracking_summary(inputs: ReportInputs) -> dict[str, Any]:
    """Keyframes, relocalisations, loop closures and refinement residuals over all segments."""
    per_segment = inputs.tracker_stats + inputs.joined_stats
    totals: dict[str, Any] = {}
    counted = ("keyframes", "relocalised", "placed_by_previous", "placed_by_flow", "loop_closures",
               "loop_attempts")  # fmt: skip
    for key in (*counted, "extra_links", "tracked_registrations", "perspective_relaxed"):
        values = [stats[key] for stats in per_segment if key in stats]
        if values:
            totals[key] = int(sum(values))
    refinements = [stats.get("refinement") for stats in per_segment]
    if any(refinements):
        totals["refinement"] = refinements
    totals["rerendered"] = inputs.rerendered
    totals["joined_segments"] = len(inputs.joined_stats)
    return totals


def build_report(
    inputs: ReportInputs, mosaics: list[SegmentMosaic], interrupted: bool
) -> dict[str, Any]:
    """The JSON-ready report: summary, configuration and one entry per frame."""
    records = inputs.records
    by_index = {m.index: m for m in mosaics}
    statuses = [r.status for r in records]
    attempts = [r for r in records if r.status != SKIPPED and r.n_matches > 0]
    scores = [r.quality for r in records if r.status == REGISTERED and not np.isnan(r.quality)]
    stage_ms = {
        stage: round(float(np.mean(vals)), 3)
        for stage in STAGES
        if (vals := [r.stage_ms[stage] for r in records if stage in r.stage_ms])
    }
    elapsed = time.perf_counter() - inputs.started
    summary = {
        "frames_read": len(records),
        "registered": statuses.count(REGISTERED),
        "failed": statuses.count(FAILED),
        "skipped": statuses.count(SKIPPED),
        "frames_until_failure": _leading_run(statuses),
        "longest_registered_run": _longest_run(statuses),
        "segments": len(mosaics),
        "mean_matches": round(float(np.mean([r.n_matches for r in attempts])), 2)
        if attempts
        else 0.0,
        "mean_inliers": round(float(np.mean([r.n_inliers for r in attempts])), 2)
        if attempts
        else 0.0,
        "quality": round(float(np.median(scores)), 3) if scores else None,
        "quality_flagged": sum(r.flagged for r in records if r.status == REGISTERED),
        "deinterlaced": sum(r.deinterlaced for r in records),
        "reflex_frames": sum(r.reflexes for r in records),
        "lens_rim_frames": sum(r.lens_rim is not None for r in records),
        "blurred_registered": sum(r.blurred is not None for r in records if r.status == REGISTERED),
        "field_offset_px": None
        if inputs.field_offset_px is None
        else round(inputs.field_offset_px, 2),
        "looks_interlaced": inputs.looks_interlaced,
        "total_time_s": round(elapsed, 3),
        "fps": round(len(records) / elapsed, 2) if elapsed > 0 else 0.0,
        "mean_stage_ms": stage_ms,
        "detector": inputs.detector,
        # GLAMpoints' network precision ("auto" resolved: figures differ between the two)
        "precision": inputs.precision,
        "working_scale": 1.0
        if inputs.H_frame_to_work is None
        else round(float(inputs.H_frame_to_work[0, 0]), 4),
        "retina_diameter_px": None
        if inputs.retina_diameter_px is None
        else round(inputs.retina_diameter_px, 1),
        "strategy": inputs.config.pipeline.strategy,
        "overlap": inputs.overlap,
        "models": _model_counts(records),
        "tracking": _tracking_summary(inputs),
        "on_failure": inputs.config.pipeline.on_failure,
        "stopped_at_failure": inputs.stopped,
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
                "blend": inputs.blends[s.index],
            }
            for s in mosaics
        ],
        "compose": photometry_report(
            inputs.config.compose,
            inputs.photometry,
            inputs.frame_shape,
            {r.index: r.gain for r in records if r.gain is not None},
            inputs.gain_solution,
        ),
        "config": config_to_dict(inputs.config),
        "frames": [_frame_entry(r, by_index) for r in records],
    }
