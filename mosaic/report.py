"""The report of a build: a summary, the configuration and one entry per frame.

The report's schema lives here: `BuildReport` and the frozen dataclasses it holds, one per
section of the JSON (`docs/report.md` says what each key means). `to_dict` / `to_json` give
the JSON `mosaic build` writes (keys, order and rounding as before the schema was typed), and
`from_dict` / `from_json` read one back; a report written before a key existed reads it as
None, False or 0 (as its docstring says).

`build_report` reads the builder through `ReportInputs` (`MosaicBuilder.summary_inputs`), its
public read-only view; the names here (frame statuses, stages) are the report's vocabulary.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from mosaic.config import ComposeConfig, Config, config_to_dict
from mosaic.io import VideoInfo, json_text
from mosaic.photometry import FlatFieldEstimator, SideBands, VideoPhotometry, shading_terms
from mosaic.registration import MODELS

if TYPE_CHECKING:
    from mosaic.pipeline import FrameRecord
    from mosaic.segments import SegmentMosaic

STAGES = ("preprocess", "detect", "describe", "match", "estimate", "compose")
REGISTERED, FAILED, SKIPPED = "registered", "failed", "skipped"


def _present(**items: Any) -> dict[str, Any]:
    """The items whose value is not None: keys a report leaves out rather than write null."""
    return {k: v for k, v in items.items() if v is not None}


# ------------------------------------------------------------------------------------ frames


@dataclass(frozen=True)
class FrameEntry:
    """One frame read (`frames[i]`). `reference`, `model` and `coverage` are written for a
    registered frame with a reference (not a segment's first), `reason` for one that was not
    registered; None leaves them out. Read from a report that predates them, the flags are
    False, `lens_rim` and `gain` None and `blended` says registered."""

    index: int
    status: str  # REGISTERED | FAILED | SKIPPED
    segment: int | None
    H_to_canvas: list[list[float]] | None  # frame pixels into its segment's written mosaic
    n_keypoints: int
    n_matches: int
    n_inliers: int
    reproj_error_px: float | None
    quality: float | None  # agreement with the mosaic under it (None: not judged)
    flagged: bool
    deinterlaced: bool
    reflexes: bool
    lens_rim: list[float] | None  # [cx, cy, r] frame px
    surround_lifted: bool  # the camera's dark surround, lifted by haze, left out of it
    blurred: bool
    blended: bool
    by_flow: bool
    gain: float | None
    time_ms: float
    reference: int | None = None  # input index of the frame it was registered against
    model: str | None = None
    coverage: float | None = None
    aligned_px: float | None = None  # None: not aligned (no tracking, or the alignment declined)
    reason: str | None = None

    def to_dict(self) -> dict[str, Any]:
        entry = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)[:-5]}
        if self.reference is not None:
            entry |= {
                "reference": self.reference,
                "model": self.model,
                "coverage": self.coverage,
                "aligned_px": self.aligned_px,
            }
        return entry | _present(reason=self.reason)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FrameEntry:
        return cls(
            index=data["index"],
            status=data["status"],
            segment=data["segment"],
            H_to_canvas=data["H_to_canvas"],
            n_keypoints=data["n_keypoints"],
            n_matches=data["n_matches"],
            n_inliers=data["n_inliers"],
            reproj_error_px=data["reproj_error_px"],
            quality=data.get("quality"),
            flagged=data.get("flagged", False),
            deinterlaced=data.get("deinterlaced", False),
            reflexes=data.get("reflexes", False),
            lens_rim=data.get("lens_rim"),
            surround_lifted=data.get("surround_lifted", False),
            blurred=data.get("blurred", False),
            blended=data.get("blended", data["status"] == REGISTERED),
            by_flow=data.get("by_flow", False),
            gain=data.get("gain"),
            time_ms=data["time_ms"],
            reference=data.get("reference"),
            model=data.get("model"),
            coverage=data.get("coverage"),
            aligned_px=data.get("aligned_px"),
            reason=data.get("reason"),
        )


# ----------------------------------------------------------------------------------- summary

_TRACKING_COUNTERS = (
    "keyframes", "relocalised", "placed_by_previous", "placed_by_flow", "loop_closures",
    "loop_attempts", "extra_links", "tracked_registrations", "aligned_registrations",
    "perspective_relaxed",
)  # fmt: skip


@dataclass(frozen=True)
class TrackingSummary:
    """`summary.tracking`: the trackers' counters summed over the segments (None: the strategy
    does not count it; left out), each segment's pose-graph figures (`refinement`, None: no
    segment refined), whether the mosaic was re-rendered from refined poses, and the later
    segments joined into the first."""

    keyframes: int | None = None
    relocalised: int | None = None
    placed_by_previous: int | None = None
    placed_by_flow: int | None = None
    loop_closures: int | None = None
    loop_attempts: int | None = None
    extra_links: int | None = None
    tracked_registrations: int | None = None
    aligned_registrations: int | None = None
    perspective_relaxed: int | None = None
    refinement: list[dict[str, Any] | None] | None = None  # posegraph's figures, per segment
    rerendered: bool = False
    joined_segments: int = 0

    def to_dict(self) -> dict[str, Any]:
        counters = {key: getattr(self, key) for key in _TRACKING_COUNTERS}
        return _present(**counters, refinement=self.refinement) | {
            "rerendered": self.rerendered,
            "joined_segments": self.joined_segments,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrackingSummary:
        names = (*_TRACKING_COUNTERS, "refinement", "rerendered", "joined_segments")
        return cls(**{key: data[key] for key in names if key in data})


@dataclass(frozen=True)
class Summary:
    """`summary`: the run in figures. `complete`, `checkpoint`, `error` and `wall_time_s` are
    the writer's (`runner`): None until written (and `error` None: no error), left out then.
    Read from a report that predates them, the counts are 0, the flags False and the rest
    None."""

    frames_read: int
    registered: int
    failed: int
    skipped: int
    frames_until_failure: int
    longest_registered_run: int
    segments: int
    mean_matches: float
    mean_inliers: float
    quality: float | None
    quality_flagged: int
    deinterlaced: int
    reflex_frames: int
    lens_rim_frames: int
    surround_lifted_frames: int
    blurred_registered: int
    field_offset_px: float | None
    looks_interlaced: bool
    total_time_s: float
    fps: float
    mean_stage_ms: dict[str, float]  # per stage of STAGES that ran
    detector: str
    precision: str | None  # GLAMpoints' network precision ("auto" resolved), else None
    working_scale: float
    retina_diameter_px: float | None
    strategy: str
    overlap: bool | None
    extraction: str | None  # serial | overlapped | turns (`scheduling.OverlapTrial`)
    models: dict[str, int]  # registered frames per motion model, in MODELS order
    tracking: TrackingSummary
    on_failure: str
    stopped_at_failure: bool
    interrupted: bool
    complete: bool | None = None
    checkpoint: bool | None = None
    error: str | None = None
    wall_time_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)[:-4]}
        fields["tracking"] = self.tracking.to_dict()
        return fields | _present(
            complete=self.complete,
            checkpoint=self.checkpoint,
            error=self.error,
            wall_time_s=self.wall_time_s,
        )

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Summary:
        later = {  # keys older reports lack, and what they read as
            "quality_flagged": 0, "deinterlaced": 0, "reflex_frames": 0, "lens_rim_frames": 0,
            "surround_lifted_frames": 0, "blurred_registered": 0, "looks_interlaced": False,
        }  # fmt: skip
        values = {}
        for f in dataclasses.fields(cls):
            if f.name in data:
                values[f.name] = data[f.name]
            elif f.name in later:
                values[f.name] = later[f.name]
            elif f.default is dataclasses.MISSING:  # the rest: None
                values[f.name] = None
        values["tracking"] = TrackingSummary.from_dict(data["tracking"])
        return cls(**values)


# ---------------------------------------------------------------------------------- segments


@dataclass(frozen=True)
class SegmentEntry:
    """One mosaic segment (`segments[i]`); `mosaic`: its file, once written (else left out)."""

    index: int
    frames: int
    width: int
    height: int
    blend: str | None  # the blend applied (None: a report that predates it)
    mosaic: str | None = None

    def to_dict(self) -> dict[str, Any]:
        entry = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)[:-1]}
        return entry | _present(mosaic=self.mosaic)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SegmentEntry:
        return cls(
            index=data["index"],
            frames=data["frames"],
            width=data["width"],
            height=data["height"],
            blend=data.get("blend"),
            mosaic=data.get("mosaic"),
        )


# ----------------------------------------------------------------------------------- compose


@dataclass(frozen=True)
class SideBandsReport:
    """`compose.side_bands`: px left out along each side, and the same as half-open
    [start, end) columns and rows of the frame as decoded (empty where its size is unknown)."""

    left: int
    right: int
    top: int
    bottom: int
    columns: list[list[int]]
    rows: list[list[int]]


@dataclass(frozen=True)
class FlatfieldReport:
    """`compose.flatfield`: the vignetting divided out, in a few numbers."""

    model: str
    coefficients: list[float] | None  # of the log-shading model (None: clipped everywhere)
    relative_to_centre: dict[str, float]  # at the corners and mid-sides (FLAT_PLACES)
    min_relative_to_centre: float
    frames: int


@dataclass(frozen=True)
class ExposureReport:
    """`compose.exposure`: how the frames' gains were found and their range. `model` is left
    out (None) where no frame has a gain."""

    solution: str | None  # "global" | "live" | None
    model: str | None
    frames: int
    min: float | None
    median: float | None
    max: float | None

    def to_dict(self) -> dict[str, Any]:
        return {"solution": self.solution, **_present(model=self.model)} | {
            "frames": self.frames,
            "min": self.min,
            "median": self.median,
            "max": self.max,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ExposureReport:
        return cls(**{"model": None, **data})


@dataclass(frozen=True)
class ComposeReport:
    """`compose`: what the compositing estimated from the frames; None where its `[compose]`
    switch is off (or there is no estimate yet)."""

    frame_size: list[int] | None  # [width, height] of the frames as decoded
    side_bands: SideBandsReport | None
    flatfield: FlatfieldReport | None
    exposure: ExposureReport | None

    def to_dict(self) -> dict[str, Any]:
        return {
            "frame_size": self.frame_size,
            "side_bands": None if self.side_bands is None else dataclasses.asdict(self.side_bands),
            "flatfield": None if self.flatfield is None else dataclasses.asdict(self.flatfield),
            "exposure": None if self.exposure is None else self.exposure.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ComposeReport:
        bands, flat, exposure = data["side_bands"], data["flatfield"], data["exposure"]
        return cls(
            frame_size=data["frame_size"],
            side_bands=None if bands is None else SideBandsReport(**bands),
            flatfield=None if flat is None else FlatfieldReport(**flat),
            exposure=None if exposure is None else ExposureReport.from_dict(exposure),
        )


# ---------------------------------------------------------------------------------- the report


@dataclass(frozen=True, kw_only=True)
class BuildReport:
    """The whole report. `build_report` makes it; the writer (`runner`) adds the input, the
    written files (`mosaic`, `main_segment`, `thumbnail`, each segment's `mosaic`) and the
    summary's completeness. `compose` is None only in a report that predates it."""

    input: VideoInfo | None = None
    summary: Summary
    segments: list[SegmentEntry]
    compose: ComposeReport | None
    config: dict[str, Any]  # the configuration used, as `config.config_to_dict` writes it
    frames: list[FrameEntry]
    mosaic: str | None = None  # the main mosaic's path
    main_segment: int | None = None  # the segment written as the main mosaic
    thumbnail: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready report, keys in the order written."""
        info = None if self.input is None else dataclasses.asdict(self.input)
        compose = None if self.compose is None else self.compose.to_dict()
        return (
            _present(input=info)
            | {
                "summary": self.summary.to_dict(),
                "segments": [s.to_dict() for s in self.segments],
            }
            | _present(compose=compose)
            | {"config": self.config, "frames": [f.to_dict() for f in self.frames]}
            | _present(mosaic=self.mosaic, main_segment=self.main_segment)
            | _present(thumbnail=self.thumbnail)
        )

    def to_json(self) -> str:
        """The report as `mosaic build` writes it (without the final newline)."""
        return json_text(self.to_dict())

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BuildReport:
        info, compose = data.get("input"), data.get("compose")
        return cls(
            input=None if info is None else VideoInfo(**info),
            summary=Summary.from_dict(data["summary"]),
            segments=[SegmentEntry.from_dict(s) for s in data["segments"]],
            compose=None if compose is None else ComposeReport.from_dict(compose),
            config=data["config"],
            frames=[FrameEntry.from_dict(f) for f in data["frames"]],
            mosaic=data.get("mosaic"),
            main_segment=data.get("main_segment"),
            thumbnail=data.get("thumbnail"),
        )

    @classmethod
    def from_json(cls, text: str) -> BuildReport:
        """A report read back from its JSON text (KeyError, TypeError or ValueError: not one)."""
        return cls.from_dict(json.loads(text))


def read_report(path: Path) -> BuildReport | None:
    """The report in the file at `path`; None where it cannot be read or is not a report."""
    try:
        return BuildReport.from_json(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


@dataclass(frozen=True)
class ReportInputs:
    """What the report reads of a `MosaicBuilder` (`MosaicBuilder.summary_inputs`)."""

    records: list[FrameRecord]
    started: float  # time.perf_counter() when the builder was made
    config: Config
    detector: str
    precision: str | None  # GLAMpoints' network precision ("auto" resolved), else None
    overlap: bool | None  # what `[pipeline] overlap` chose (None: not decided yet)
    extraction: str | None  # ... and how: serial, overlapped, turns (None: not decided yet)
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


def _rounded(value: float, digits: int) -> float | None:
    """`value` rounded for the report; None for NaN (not measured)."""
    return None if np.isnan(value) else round(value, digits)


def _frame_entry(record: FrameRecord, mosaics: dict[int, SegmentMosaic]) -> FrameEntry:
    H_to_canvas = None
    if record.H_frame_to_ref is not None and record.segment in mosaics:
        H = mosaics[record.segment].H_ref_to_mosaic @ record.H_frame_to_ref
        H_to_canvas = (H / H[2, 2]).tolist()
    placed = record.status == REGISTERED and record.reference is not None
    return FrameEntry(
        index=record.index,
        status=record.status,
        segment=record.segment,
        H_to_canvas=H_to_canvas,
        n_keypoints=record.n_keypoints,
        n_matches=record.n_matches,
        n_inliers=record.n_inliers,
        reproj_error_px=_rounded(record.reproj_error_px, 3),
        quality=_rounded(record.quality, 3),
        flagged=record.flagged,
        deinterlaced=record.deinterlaced,
        reflexes=record.reflexes,
        lens_rim=None if record.lens_rim is None else [round(v, 1) for v in record.lens_rim],
        surround_lifted=record.surround_lifted,
        blurred=record.blurred is not None,
        blended=record.status == REGISTERED and record.blurred is None,
        by_flow=record.by_flow,
        gain=None if record.gain is None else round(record.gain, 4),
        time_ms=round(record.time_ms, 2),
        reference=record.reference if placed else None,
        model=record.model if placed else None,
        coverage=_rounded(record.coverage, 3) if placed else None,
        aligned_px=_rounded(record.aligned_px, 2) if placed else None,
        reason=record.reason,
    )


def _model_counts(records: list[FrameRecord]) -> dict[str, int]:
    """Registered frames per motion model (a segment's first frame has none), in MODELS order."""
    counts = Counter(r.model for r in records if r.status == REGISTERED and r.reference is not None)
    return {m: counts[m] for m in MODELS if counts[m]}


def _tracking_summary(inputs: ReportInputs) -> TrackingSummary:
    """Keyframes, relocalisations, loop closures and refinement residuals over all segments."""
    per_segment = inputs.tracker_stats + inputs.joined_stats
    totals: dict[str, Any] = {}
    for key in _TRACKING_COUNTERS:
        values = [stats[key] for stats in per_segment if key in stats]
        if values:
            totals[key] = int(sum(values))
    refinements = [stats.get("refinement") for stats in per_segment]
    return TrackingSummary(
        **totals,
        refinement=refinements if any(refinements) else None,
        rerendered=inputs.rerendered,
        joined_segments=len(inputs.joined_stats),
    )


def build_report(
    inputs: ReportInputs, mosaics: list[SegmentMosaic], interrupted: bool
) -> BuildReport:
    """The report of the builder as it is: summary, configuration and one entry per frame."""
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
    summary = Summary(
        frames_read=len(records),
        registered=statuses.count(REGISTERED),
        failed=statuses.count(FAILED),
        skipped=statuses.count(SKIPPED),
        frames_until_failure=_leading_run(statuses),
        longest_registered_run=_longest_run(statuses),
        segments=len(mosaics),
        mean_matches=round(float(np.mean([r.n_matches for r in attempts])), 2) if attempts else 0.0,
        mean_inliers=round(float(np.mean([r.n_inliers for r in attempts])), 2) if attempts else 0.0,
        quality=round(float(np.median(scores)), 3) if scores else None,
        quality_flagged=sum(r.flagged for r in records if r.status == REGISTERED),
        deinterlaced=sum(r.deinterlaced for r in records),
        reflex_frames=sum(r.reflexes for r in records),
        lens_rim_frames=sum(r.lens_rim is not None for r in records),
        surround_lifted_frames=sum(r.surround_lifted for r in records),
        blurred_registered=sum(r.blurred is not None for r in records if r.status == REGISTERED),
        field_offset_px=None
        if inputs.field_offset_px is None
        else round(inputs.field_offset_px, 2),
        looks_interlaced=inputs.looks_interlaced,
        total_time_s=round(elapsed, 3),
        fps=round(len(records) / elapsed, 2) if elapsed > 0 else 0.0,
        mean_stage_ms=stage_ms,
        detector=inputs.detector,
        precision=inputs.precision,
        working_scale=1.0
        if inputs.H_frame_to_work is None
        else round(float(inputs.H_frame_to_work[0, 0]), 4),
        retina_diameter_px=None
        if inputs.retina_diameter_px is None
        else round(inputs.retina_diameter_px, 1),
        strategy=inputs.config.pipeline.strategy,
        overlap=inputs.overlap,
        extraction=inputs.extraction,
        models=_model_counts(records),
        tracking=_tracking_summary(inputs),
        on_failure=inputs.config.pipeline.on_failure,
        stopped_at_failure=inputs.stopped,
        interrupted=interrupted,
    )
    return BuildReport(
        summary=summary,
        segments=[
            SegmentEntry(
                index=s.index,
                frames=s.n_frames,
                width=int(s.image.shape[1]),
                height=int(s.image.shape[0]),
                blend=inputs.blends[s.index],
            )
            for s in mosaics
        ],
        compose=photometry_report(
            inputs.config.compose,
            inputs.photometry,
            inputs.frame_shape,
            {r.index: r.gain for r in records if r.gain is not None},
            inputs.gain_solution,
        ),
        config=config_to_dict(inputs.config),
        frames=[_frame_entry(r, by_index) for r in records],
    )


# ------------------------------------------------------------------------ the compose section

# where the report reads the flat-field out: (name, x, y), -1 / 1 the centre of the first /
# last pixel along a side, 0 the frame's centre
FLAT_PLACES = (
    ("top_left", -1, -1),
    ("top_right", 1, -1),
    ("bottom_left", -1, 1),
    ("bottom_right", 1, 1),
    ("left", -1, 0),
    ("right", 1, 0),
    ("top", 0, -1),
    ("bottom", 0, 1),
)


def photometry_report(
    config: ComposeConfig,
    photometry: VideoPhotometry,
    frame_shape: tuple[int, int] | None,
    gains: dict[int, float],
    solution: str | None,
) -> ComposeReport:
    """What the compositing estimated, compact (the report's `compose`): the
    frame size, the side bands left out (px per side), the flat-field (its model's
    coefficients and its value at the frame's corners and mid-sides relative to the centre) and
    a summary of the exposure gains (`gains`: frame index -> gain; `solution`: "global", "live"
    or None). None where a correction is off or has no estimate yet."""
    bands = photometry.bands if config.side_bands else None
    return ComposeReport(
        frame_size=None if frame_shape is None else [frame_shape[1], frame_shape[0]],
        side_bands=None if bands is None else _bands_report(bands, frame_shape),
        flatfield=_flatfield_report(photometry) if config.flatfield else None,
        exposure=_gains_report(gains, solution) if config.exposure else None,
    )


def _bands_report(bands: SideBands, frame_shape: tuple[int, int] | None) -> SideBandsReport:
    """Widths (px) left out along each side, and the columns / rows they are (half-open
    [start, end) ranges of the frame as decoded; empty where the frame size is unknown)."""
    widths = {side: int(getattr(bands, side)) for side in ("left", "right", "top", "bottom")}
    columns: list[list[int]] = []
    rows: list[list[int]] = []
    if frame_shape is not None:
        h, w = frame_shape
        columns = [[0, widths["left"]]] if widths["left"] else []
        columns += [[w - widths["right"], w]] if widths["right"] else []
        rows = [[0, widths["top"]]] if widths["top"] else []
        rows += [[h - widths["bottom"], h]] if widths["bottom"] else []
    return SideBandsReport(**widths, columns=columns, rows=rows)


def _flatfield_report(photometry: VideoPhotometry) -> FlatfieldReport | None:
    """The flat-field profile in a few numbers: the coefficients c of its log-shading model
    (`photometry.shading_terms`: x², xy, y², r⁴ in normalised frame coordinates, fitted back
    to the profile), its value at the corners and mid-sides relative to the frame's centre
    (0.65: 35 % darker there), and its lowest value, likewise."""
    flat = photometry.flatfield
    if flat is None:
        return None
    profile = flat.profile
    h, w = profile.shape
    step = max(1, max(h, w) // 160)  # a grid of ~160 along the longer side is plenty
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    xn = (xs - (w - 1) / 2) / (w / 2)
    yn = (ys - (h - 1) / 2) / (h / 2)
    values = profile[ys, xs].astype(np.float64)
    fitted = values > FlatFieldEstimator.MIN_PROFILE * 1.001  # not where it was clipped
    coefficients = None  # (a profile clipped almost everywhere has none)
    if fitted.sum() >= 10:
        design = np.column_stack([shading_terms(xn, yn)[fitted], np.ones(int(fitted.sum()))])
        coef = np.linalg.lstsq(design, np.log(values[fitted]), rcond=None)[0]
        coefficients = [round(float(c), 4) for c in coef[:-1]]

    def at(x: float, y: float) -> float:  # bilinear, at normalised (x, y) of pixel centres
        px = (w - 1) / 2 + x * (w - 1) / 2
        py = (h - 1) / 2 + y * (h - 1) / 2
        return float(cv2.getRectSubPix(profile, (1, 1), (px, py))[0, 0])

    centre = at(0.0, 0.0)
    return FlatfieldReport(
        model="log shading = c . (x^2, xy, y^2, r^4), x, y in [-1, 1] over the frame",
        coefficients=coefficients,
        relative_to_centre={name: round(at(x, y) / centre, 4) for name, x, y in FLAT_PLACES},
        min_relative_to_centre=round(float(profile.min()) / centre, 4),
        frames=photometry.flat_estimator.n_frames,
    )


def _gains_report(gains: dict[int, float], solution: str | None) -> ExposureReport:
    """How the per-frame gains (each frame's entry has its own) were found, and their range."""
    values = np.array([g for g in gains.values() if g is not None and np.isfinite(g)], float)
    if not len(values):
        return ExposureReport(None, None, frames=0, min=None, median=None, max=None)
    return ExposureReport(
        solution=solution,
        model="gain",  # one factor per frame for all channels; no bias
        frames=len(values),
        min=round(float(values.min()), 4),
        median=round(float(np.median(values)), 4),
        max=round(float(values.max()), 4),
    )
