"""The mosaicking pipeline: each frame goes read → preprocess → gate → detect → describe →
track (match → estimate → check, against the previous frame and/or the keyframes) → compose, and
is accounted for in the report; at the end the poses are refined and the mosaic rendered (with
each frame's quality score against it).

`MosaicBuilder.process` takes one decoded frame at a time (frames are streamed, never stored);
it is `extract` (preprocess → describe: needs no other frame) then `add_frame` (track → compose,
in frame order), into the segment `segments.Segments` says. `stream` runs them over a video
with, when `[pipeline] overlap` is on (or `auto` measured it faster: `scheduling.OverlapTrial`),
the extraction of the next frames in a background thread while the current one is registered
(OpenCV and torch release the GIL), a network on every core taking turns with the registration
(`scheduling.Turns`).
`MosaicBuilder.finish` renders the mosaic segment(s) and the report. Reading files, progress
bars and the viewer stay outside: the viewer is injected and is a no-op unless the user turns
it on.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from mosaic.camera_fixed import (
    OverlayMask,
    ReflexMask,
    Spots,
    SurroundMask,
    cleared,
)
from mosaic.canvas import Canvas
from mosaic.compose import LiveCompositor
from mosaic.config import Config
from mosaic.errors import CanvasLimitError
from mosaic.features import FeatureExtractor, Features
from mosaic.io import UNDECODABLE, Frame, Lookahead
from mosaic.lens_rim import Circle, LensRimMask, outside_rim_removed
from mosaic.matching import Matches
from mosaic.photometry import VideoPhotometry
from mosaic.pixel_refine import coarse_texture, lk_texture
from mosaic.preprocess import (
    Deinterlacer,
    FrameGate,
    Prepared,
    first_field,
    prepare,
)
from mosaic.quality import frame_vs_canvas
from mosaic.registration import Registration
from mosaic.render import FrameSource, ReadAhead, render_segments
from mosaic.report import (
    FAILED,
    REGISTERED,
    SKIPPED,
    BuildReport,
    ReportInputs,
    build_report,
)
from mosaic.scheduling import OverlapTrial, Turns
from mosaic.segments import Segment, SegmentMosaic, Segments, note_registration
from mosaic.tracking import Track
from mosaic.viz import NullViewer, Viewer
from mosaic.working_size import WorkingSize, circle_in_frame, conjugated

log = logging.getLogger(__name__)


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
    model: str | None = None  # motion model of the registration that placed it
    coverage: float = float("nan")  # share of the frame inside its inliers' convex hull
    aligned_px: float = float("nan")  # how far the windows' alignment moved its registration
    reference: int | None = None  # input index of the frame it was registered against
    quality: float = float("nan")  # agreement with the mosaic under it (mosaic.quality)
    flagged: bool = False  # quality under [compose] quality_threshold: likely misregistered
    gain: float | None = None  # exposure gain the frame was composed with (None: none)
    deinterlaced: bool = False  # replaced by its first field (`[preprocess] deinterlace`)
    reflexes: bool = False  # lens reflexes left out of it (`[preprocess] reflex_mask`)
    lens_rim: Circle | None = None  # (cx, cy, r) px of a handheld lens's rim, outside which
    # nothing of it was used (`[preprocess] lens_rim_mask`)
    surround_lifted: bool = False  # the camera's surround, lifted by haze, left out of it
    # (`[preprocess] surround_mask`)
    blurred: str | None = None  # too blurred to blend (the gate's reason): registered all the
    # same where it can be, and left out of the mosaic (`[gating] blurred = "track"`)
    by_flow: bool = False  # placed by optical flow from its predecessor (`[registration]
    # flow_fallback`): no descriptors registered it
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
    reference: Features | None = None  # what the frame was matched against (matches.idx_a)
    composed_px: np.ndarray | None = None  # decoded pixels into the canvas' (None: the same)


@dataclass(frozen=True)
class Extracted:
    """A frame after the stages that need no other frame; `skip` says why it goes no further."""

    record: FrameRecord
    image: np.ndarray | None  # as decoded (composed into the mosaic at this size)
    prepared: Prepared | None = None  # at the working size, like the features
    features: Features | None = None
    skip: str | None = None
    H_frame_to_work: np.ndarray | None = None  # None: the working size is the frame's
    work: np.ndarray | None = None  # the colour frame at the working size


@dataclass(frozen=True)
class MosaicResult:
    """Rendered segments (largest first is `main`) and the report."""

    segments: list[SegmentMosaic]
    report: BuildReport

    @property
    def main(self) -> SegmentMosaic | None:
        """The segment holding the most frames: the mosaic written to the requested output."""
        return max(self.segments, key=lambda s: s.n_frames, default=None)


class Timer:
    """Accumulates wall time per stage into a record."""

    def __init__(self, record: FrameRecord):
        self._record = record

    def run(self, stage: str, fn: Callable[..., Any], *args: Any) -> Any:
        start = time.perf_counter()
        out = fn(*args)
        elapsed = (time.perf_counter() - start) * 1e3
        self._record.stage_ms[stage] = self._record.stage_ms.get(stage, 0.0) + elapsed
        return out


Reread = Callable[[], Iterable[tuple[int, np.ndarray | None]]]


class MosaicBuilder:
    """Registers frames one by one with the configured strategy and accumulates the mosaic."""

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
        self._size = WorkingSize(config)
        self.segments = Segments(config, self._size.to_frame)
        self._gate = FrameGate(config.gating)
        self._overlay = OverlayMask(config.preprocess)
        self._surround = SurroundMask(config.preprocess)
        self._lifted: dict[int, np.ndarray] = {}  # frame index -> its lifted surround
        self._reflexes = ReflexMask(config.preprocess)
        self._reflex_spots: dict[int, Spots] = {}  # frame index -> its reflexes
        self._rim = LensRimMask(config.preprocess)
        # frame index -> its lens rim and the margin masked inside it (working px)
        self._rims: dict[int, tuple[Circle, float]] = {}
        self._fields = Deinterlacer(config.preprocess.deinterlace)
        compose = config.compose
        self._photometry = VideoPhotometry(compose.side_bands, compose.flatfield)
        # The quality score is computed where it is used: live when the viewer shows it or no
        # re-render will replace the live poses; else once, in the re-render pass, at the poses
        # the report gives (the live score would be overwritten there).
        k = config.keyframes
        rerenders = config.pipeline.strategy == "keyframes" and k.refine and k.rerender
        self._live_quality = not isinstance(self.viewer, NullViewer) or not rerenders
        # the live canvas is corrected where it is seen or kept (else the re-render redoes it)
        self._compositor = LiveCompositor(compose, self._photometry, correct=self._live_quality)
        self._gain_solution: str | None = "live" if self._live_quality else None
        self._started = time.perf_counter()
        self.overlap = OverlapTrial(
            config.pipeline.overlap, turns=self.extractor.detector.takes_every_core
        )
        self._turns = Turns(on=False)  # `stream` sets its own

    def process(
        self, index: int, image: np.ndarray | None, error: str | None = None
    ) -> FrameRecord:
        """Register and compose one frame; undecodable or unusable frames are skipped."""
        return self.add_frame(self.extract(index, image, error))

    def stream(self, frames: Iterable[Frame]) -> Iterator[FrameRecord]:
        """`process` every frame in order, extracting ahead in a background thread where
        `[pipeline] overlap` says (`OverlapTrial`); stop iterating to stop (the thread is
        stopped too)."""
        extracted = (self.extract(f.index, f.image, f.error) for f in frames)
        self._turns = turns = Turns(on=self.extractor.detector.takes_every_core)
        ahead, take_turns = self.overlap.ahead(), self.overlap.turns()
        with Lookahead(turns.ended_after(extracted), depth=2, ahead=ahead) as items, turns:
            for i, item in enumerate(items):
                # as the items in flight were asked for
                turns.before_register(i, items.ahead and take_turns)
                record = self.add_frame(item)
                turns.registered()
                yield record
                self.overlap.tick()
                items.ahead, take_turns = self.overlap.ahead(), self.overlap.turns()

    def extract(self, index: int, image: np.ndarray | None, error: str | None = None) -> Extracted:
        """Preprocess, gate, mask overlays, detect and describe one frame (independent of other
        frames but for the gate and overlay histories, so frames must come in order)."""
        before = self._turns.n_detected
        try:
            return self._extract(index, image, error)
        finally:
            if self._turns.n_detected == before:  # skipped before detection, or an error
                self._turns.detected()

    def _extract(self, index: int, image: np.ndarray | None, error: str | None) -> Extracted:
        record = FrameRecord(index=index)
        if image is None:
            return Extracted(record, None, skip=error or UNDECODABLE)
        timer = Timer(record)
        image, record.deinterlaced = timer.run("preprocess", self._fields, image)
        work, S = timer.run("preprocess", self._size.resize, image)
        prepared = timer.run("preprocess", prepare, work, self.config.preprocess)
        gate = self._gate(prepared)  # before overlay masking: sharpness of the whole view
        record.blurred = gate.blurred
        prepared = timer.run("preprocess", self._overlay, work, prepared)
        prepared = timer.run("preprocess", self._surround, prepared)
        if self._surround.lifted is not None:  # kept for the re-render: left out there too
            self._lifted[index] = self._surround.lifted
            record.surround_lifted = True
        prepared = timer.run("preprocess", self._rim, work, prepared)
        if self._rim.found is not None:  # kept for the re-render: left out there too
            self._rims[index] = (self._rim.found, self._rim.margin_px)
            record.lens_rim = circle_in_frame(self._rim.found, S)
        prepared = timer.run("preprocess", self._reflexes, work, prepared)
        if self._reflexes.found is not None:  # kept for the re-render: left out there too
            self._reflex_spots[index] = self._reflexes.found
            record.reflexes = True
        if gate.skip is not None:
            return Extracted(record, image, prepared, skip=gate.skip, H_frame_to_work=S, work=work)
        self._turns.before_detect()
        detected = timer.run("detect", self.extractor.detect, prepared)
        self._turns.detected()
        features = timer.run("describe", self.extractor.describe, prepared, detected)
        if self.config.registration.track_window_px > 0:
            texture = timer.run("describe", lk_texture, prepared.gray, prepared.mask)
            coarse = None
            if self.config.registration.align_windows:
                coarse = timer.run("describe", coarse_texture, texture)
            features = dataclasses.replace(features, texture=texture, coarse=coarse)
        record.n_keypoints = len(features)
        return Extracted(record, image, prepared, features, H_frame_to_work=S, work=work)

    def add_frame(self, extracted: Extracted) -> FrameRecord:
        """Track and compose an extracted frame (frames in order), report it to the viewer."""
        record, image, prepared = extracted.record, extracted.image, extracted.prepared
        self.records.append(record)
        if extracted.skip is not None or extracted.features is None:
            return self._skip(record, extracted.skip or "no features", image, prepared)
        assert image is not None and prepared is not None
        features = extracted.features
        self._size.settle(extracted.H_frame_to_work, image.shape, prepared.gray.shape)
        timer = Timer(record)
        segments = self.segments
        segment = segments.current or segments.new()
        shape = prepared.gray.shape
        leaf = record.blurred is not None  # see `_place`
        track = segments.back_to_first(record.index, features, shape, timer, leaf)
        if track is not None:
            segment = segments.all[0]
        else:
            track = segment.tracker.track(record.index, features, shape, timer, leaf)
        note_registration(record, track)
        reason = track.reason
        if reason is None:
            reason = self._place(segment, extracted, track, timer)
        if reason is not None and record.blurred is not None:  # as before it was tracked
            return self._skip(
                record, f"{record.blurred}; not registered: {reason}", image, prepared
            )
        if reason is not None:
            self._fail(extracted, timer, reason)
            if self.config.pipeline.on_failure == "skip":
                track = segments.start_again(extracted, timer, self._place) or track
        self.viewer.frame(
            FrameEvent(
                record,
                image,
                prepared,
                self._size.in_frame(features),
                track.matches,
                track.registration,
                segments.current.canvas if segments.current else None,
                None if track.reference is None else self._size.in_frame(track.reference),
                self._size.composed_px,
            )
        )
        return record

    def _frame_mask(self, prepared: Prepared, image: np.ndarray) -> np.ndarray:
        """The working-size mask at the decoded frame's size."""
        if prepared.mask.shape == image.shape[:2]:
            return prepared.mask
        h, w = image.shape[:2]
        return cv2.resize(prepared.mask, (w, h), interpolation=cv2.INTER_NEAREST)

    def _skip(
        self,
        record: FrameRecord,
        reason: str,
        image: np.ndarray | None = None,
        prepared: Prepared | None = None,
    ) -> FrameRecord:
        record.reason = reason
        log.warning("frame %d skipped: %s", record.index, reason)
        self.viewer.frame(FrameEvent(record, image, prepared, None, None, None, None, None))
        return record

    def _place(self, segment: Segment, frame: Extracted, track: Track, timer: Timer) -> str | None:
        """Put the frame on the canvas and let the tracker take it; or say why not."""
        record, image, prepared, features = (
            frame.record,
            frame.image,
            frame.prepared,
            frame.features,
        )
        assert image is not None and prepared is not None and features is not None
        assert track.H_frame_to_ref is not None
        H_frame_to_ref = self._size.to_frame(track.H_frame_to_ref)
        if record.blurred is not None:  # registered, kept out of the blend; a leaf of the
            # track where a keyframe registers it (else it carries the chain on)
            leaf = dataclasses.replace(track, leaf=True)
            segment.tracker.commit(record.index, features, prepared.gray.shape, leaf)
            record.status, record.H_frame_to_ref, record.segment = (
                REGISTERED,
                H_frame_to_ref,
                segment.index,
            )
            segment.records.append(record)
            return None
        image, H_mosaic = self._size.in_mosaic_px(image, frame.work, H_frame_to_ref)
        mask = self._frame_mask(prepared, image)
        # the video's side bands and vignetting, from the frames placed so far
        timer.run("compose", self._photometry.observe, image, mask)
        mask = self._photometry.frame_mask(mask)
        quality = float("nan")
        if self._live_quality and segment.canvas.n_frames:  # against the frames already there
            canvas = segment.canvas
            quality = timer.run("compose", frame_vs_canvas, canvas, image, H_mosaic, mask)
        try:
            add = self._compositor.add
            record.gain = timer.run("compose", add, segment.canvas, image, H_mosaic, mask)
        except CanvasLimitError as exc:
            return str(exc)
        segment.tracker.commit(record.index, features, prepared.gray.shape, track)
        record.status, record.H_frame_to_ref = REGISTERED, H_frame_to_ref
        record.reason = None
        self.segments.placed()
        record.segment = segment.index
        self._set_quality(record, quality)
        segment.records.append(record)
        return None

    def _set_quality(self, record: FrameRecord, quality: float) -> None:
        record.quality = quality
        record.flagged = bool(quality < self.config.compose.quality_threshold)  # NaN: False

    def _fail(self, frame: Extracted, timer: Timer, reason: str) -> None:
        record, features, prepared = frame.record, frame.features, frame.prepared
        assert features is not None and prepared is not None
        record.status, record.reason = FAILED, reason
        policy = self.config.pipeline.on_failure
        log.info("frame %d failed (%s): %s", record.index, policy, reason)
        if policy == "stop":
            self.stopped = True
        elif policy == "restart":
            segment = self.segments.new()
            first = segment.tracker.track(record.index, features, prepared.gray.shape, timer)
            if self._place(segment, frame, first, timer) is None:
                record.status = FAILED
                record.reason = f"{reason}; started segment {segment.index}"

    def _masked_frames(self, reread: Reread) -> FrameSource:
        """The registered frames read again, (index, image, mask), with the whole video's
        overlay, side-band and flat-field estimates (refreshed here): what the re-render
        reads. Independent of the poses, so it can read while they are refined."""
        registered = {r.index for r in self.records if r.status == REGISTERED}
        interlaced = {r.index for r in self.records if r.deinterlaced}
        self._photometry.refresh()
        # only the field-of-view mask of `prepare` is needed here
        mask_config = dataclasses.replace(self.config.preprocess, clahe=False, bilateral=False)

        def frames() -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
            for index, image in reread():
                if index not in registered or image is None:
                    continue
                if index in interlaced:  # the frame as it was registered
                    image = first_field(image)
                # the overlay estimate of the whole video: no overlay pixels from any frame
                work, _ = self._size.resize(image)
                prepared = self._overlay.apply(prepare(work, mask_config))
                if index in self._lifted:
                    mask = cleared(prepared.mask, self._lifted[index])
                    prepared = Prepared(prepared.gray, mask)
                if index in self._rims:
                    mask = outside_rim_removed(prepared.mask, *self._rims[index])
                    prepared = Prepared(prepared.gray, mask)
                if index in self._reflex_spots:
                    mask = self._reflex_spots[index].removed_from(prepared.mask)
                    prepared = Prepared(prepared.gray, mask)
                if self._size.composed_px is not None:  # composed at the working size
                    image = work
                yield index, image, self._photometry.frame_mask(self._frame_mask(prepared, image))

        return frames

    def _rerender(self, frames: FrameSource) -> None:
        """Render refined segments again from the video's registered frames (`frames`,
        `_masked_frames`): one or two more passes over them (`render.render_segments`).
        Later segments the camera came back from are rendered into the first
        (`Segments.joined_poses`); they join it only where that rendering succeeds."""
        segments = self.segments
        joined, segments.joins = segments.joined_poses(), []
        todo = {
            s.index: s
            for s in segments.all
            if s.refined_poses and s.records and s.index not in joined
        }
        poses = {k: dict(s.refined_poses or {}) for k, s in todo.items()}
        for later in joined.values():
            poses[0].update(later)
        C = self._size.composed_px
        if C is not None:  # into the pixels the frames are composed in
            poses = {k: {i: conjugated(H, C) for i, H in p.items()} for k, p in poses.items()}
        owner = {r.index for s in todo.values() for r in s.records}
        owner.update(index for later in joined.values() for index in later)
        owner -= {r.index for r in self.records if r.blurred is not None}  # not blended

        def owned() -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
            return ((index, image, mask) for index, image, mask in frames() if index in owner)

        quality: dict[int, float] = {}  # of the refined poses, against the re-rendered mosaic

        def score(
            index: int, canvas: Canvas, image: np.ndarray, H: np.ndarray, mask: np.ndarray
        ) -> None:
            if canvas.n_frames:
                quality[index] = frame_vs_canvas(canvas, image, H, mask)

        rendered = render_segments(self.config.compose, owned, poses, self._photometry, score)
        for k, result in rendered.items():
            segment, canvas = todo[k], result.canvas
            expected = sum(r.index in owner for r in segment.records)
            if k == 0:
                expected += sum(index in owner for later in joined.values() for index in later)
            if canvas.n_frames != expected:
                log.warning("segment %d not re-rendered: the input changed on re-reading", k)
                continue
            if k == 0 and joined:
                segments.join(joined)
            segment.canvas = canvas
            for record in segment.records:
                record.H_frame_to_ref = segment.refined_poses[record.index]  # type: ignore[index]
                record.gain = result.gains.get(record.index)
                self._set_quality(record, quality.get(record.index, float("nan")))
            self._gain_solution = "global"

    def finish(self, interrupted: bool = False, reread: Reread | None = None) -> MosaicResult:
        """Refine, render the segment(s) and build the report (also after an interruption).

        `reread` re-opens the input so that a refined mosaic is rendered from the frames again;
        without it the live canvas and its poses are kept.
        """
        if self._fields.looks_interlaced and not self._fields.on:
            log.warning(
                "the frames' odd rows lie %.1f px from their even rows (median): an interlaced "
                "camera or a scanner's line offset; [preprocess] deinterlace = true registers the "
                "first fields alone, which helps sharp views and costs magnified ones",
                self._fields.median_offset_px,
            )
        if not interrupted:
            ahead = None  # the frames read (decoded, masked) while the poses are refined
            if reread is not None and self.config.keyframes.rerender:
                ahead = ReadAhead(self._masked_frames(reread))
            try:
                self.segments.refine()
                if ahead is not None:
                    self._rerender(ahead)
            finally:
                if ahead is not None:
                    ahead.close()
        result = self.snapshot(interrupted)
        self.viewer.finish(result.report, result.main.image if result.main is not None else None)
        return result

    def snapshot(self, interrupted: bool = True) -> MosaicResult:
        """The segment canvases as they are and the report so far (no refinement, the viewer
        not told): what `finish` renders, and a run's periodic checkpoint."""
        mosaics = self.segments.mosaics(self._size.composed_px)
        return MosaicResult(mosaics, build_report(self.summary_inputs(), mosaics, interrupted))

    def summary_inputs(self) -> ReportInputs:
        """What the report reads of the builder, as it is now (a read-only view)."""
        return ReportInputs(
            records=self.records,
            started=self._started,
            config=self.config,
            detector=self.extractor.detector.name,
            precision=getattr(self.extractor.detector, "precision", None),
            overlap=self.overlap.chosen,
            extraction=self.overlap.way,
            stopped=self.stopped,
            field_offset_px=self._fields.median_offset_px,
            looks_interlaced=self._fields.looks_interlaced,
            H_frame_to_work=self._size.S,
            retina_diameter_px=self._size.retina_diameter_px,
            tracker_stats=[s.tracker.stats() for s in self.segments.all],
            joined_stats=self.segments.joined_stats,
            rerendered=any(s.refined_poses for s in self.segments.all),
            blends=[s.canvas.blend for s in self.segments.all],
            photometry=self._photometry,
            frame_shape=self._compositor.frame_shape,
            gain_solution=self._gain_solution,
        )
