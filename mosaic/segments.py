"""The mosaic segments of a video: each its own canvas, tracker and frames.

A camera that leaves the mapped area (or frames that stop registering) would leave every later
frame failed; with `[pipeline] on_failure = "skip"`, `Segments` starts the mosaic again after
failures in a row (`start_again`): a lone first frame is replaced, a segment of several frames
gets a new one beside it. Frames of a later segment are tried against the first segment first
(`back_to_first`) and, before yet another segment starts, against the later segments
(`_resume`). After the poses are refined, the later segments the camera came back from are put
into the first (`joined_poses`, `join`). Placing a frame on a canvas is the builder's
(`Place`, injected).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from mosaic.canvas import Canvas
from mosaic.config import Config
from mosaic.report import FAILED
from mosaic.tracking import Track, Tracker, make_tracker

if TYPE_CHECKING:
    from mosaic.features import Features
    from mosaic.pipeline import Extracted, FrameRecord, Timer

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Join:
    """A later segment met again: the frame that came back to the first segment also
    registered to it (`Segments.back_to_first`), which ties the two segments' references."""

    segment: int  # the later segment
    frame: int  # input index of the frame placed in the first segment
    reference: int  # input index of the later segment's frame it registered to
    H_frame_to_reference: np.ndarray  # decoded pixels


@dataclass
class Segment:
    """One mosaic under construction: its canvas, its tracker and the frames placed on it."""

    index: int
    canvas: Canvas
    tracker: Tracker
    records: list[FrameRecord] = field(default_factory=list)
    refined_poses: dict[int, np.ndarray] | None = None  # H_frame_to_ref after refinement


@dataclass(frozen=True)
class SegmentMosaic:
    """A rendered mosaic segment and the map from its reference frame into the image."""

    index: int
    image: np.ndarray  # uint8 HxWx3, the bounding box of the placed frames
    H_ref_to_mosaic: np.ndarray
    n_frames: int


# Put a frame on a segment's canvas at its track and let the tracker take it; or say why not.
Place = Callable[[Segment, "Extracted", Track, "Timer"], str | None]
# H_frame_to_ref (decoded pixels) of a homography between working-size frames.
ToFrame = Callable[[np.ndarray], np.ndarray]


class Segments:
    """The segments of one video, the one new frames go to, and the later segments the camera
    came back from."""

    def __init__(self, config: Config, to_frame: ToFrame) -> None:
        self.config = config
        self.to_frame = to_frame
        self.all: list[Segment] = []
        self.active = 0  # index of the segment new frames go to
        self.joins: list[Join] = []  # later segments the camera came back from
        self.joined_stats: list[dict[str, Any]] = []  # tracker stats of segments joined
        # failures in a row, and the last of them (`start_again`)
        self._stalled = 0
        self._last_failed: Extracted | None = None

    @property
    def current(self) -> Segment | None:
        return self.all[self.active] if self.all else None

    def new(self) -> Segment:
        """A new segment, which new frames go to."""
        segment = self._fresh(len(self.all))
        self.all.append(segment)
        self.active = segment.index
        return segment

    def _fresh(self, index: int) -> Segment:
        return Segment(index, Canvas(self.config.compose), make_tracker(self.config))

    def mosaics(self, composed_px: np.ndarray | None = None) -> list[SegmentMosaic]:
        """The segments' canvases as they are, those with frames; `composed_px`: the frames'
        decoded pixels into those the canvases are composed in (None: the same)."""

        def H_ref_to_mosaic(segment: Segment) -> np.ndarray:
            H = segment.canvas.H_ref_to_canvas
            return H if composed_px is None else H @ composed_px

        return [
            SegmentMosaic(s.index, s.canvas.picture(), H_ref_to_mosaic(s), s.canvas.n_frames)
            for s in self.all
            if s.canvas.n_frames
        ]

    def placed(self) -> None:
        """A frame was placed: no failures in a row."""
        self._stalled, self._last_failed = 0, None

    def back_to_first(
        self,
        index: int,
        features: Features,
        shape: tuple[int, int],
        timer: Timer,
        leaf: bool = False,
    ) -> Track | None:
        """While a later segment grows (`start_again`), each frame is tried against the first
        segment before it: a camera that comes back to the area mapped first continues that
        mosaic, as it would have without the later segment. The frame's track there, or None."""
        if self.active == 0 or self.config.pipeline.on_failure != "skip":
            return None
        track = self.all[0].tracker.track(index, features, shape, timer, leaf)
        if track.reason is not None:
            return None
        log.info("frame %d registers to the first segment again", index)
        later = self.all[self.active]
        self.active = 0
        back = later.tracker.track(index, features, shape, timer, leaf)
        if back.H_frame_to_ref is not None and back.reference_index is not None:
            poses = {r.index: r.H_frame_to_ref for r in later.records}
            H_reference = poses.get(back.reference_index)
            if H_reference is not None:
                H = np.linalg.solve(H_reference, self.to_frame(back.H_frame_to_ref))
                self.joins.append(Join(later.index, index, back.reference_index, H / H[2, 2]))
        return track

    def start_again(self, failed: Extracted, timer: Timer, place: Place) -> Track | None:
        """After failures in a row (`skip`), start the mosaic again from the failed frame
        before this one and this one, when they register to each other. Returns this frame's
        new track (None: nothing changed).

        - Against a segment that holds only its first frame (`[pipeline] reanchor_after`
          failures): a dark, featureless or blurred first frame would otherwise leave every
          later frame failed (measured: a magnified video that opens on a dark region, 1 of
          120 frames placed). The two frames replace it; the old first frame is reported failed.
        - Against a segment of several frames (`new_segment_after` failures): the camera has
          left the mapped area (or the frames that map the way there do not register), and
          every later frame would fail. The two frames start a new segment, written beside
          the first; frames are still tried against the first segment first
          (`back_to_first`).
        """
        segment = self.current
        if segment is None:
            return None
        first_only = len(segment.records) == 1
        pipeline = self.config.pipeline
        after = pipeline.reanchor_after if first_only else pipeline.new_segment_after
        if after <= 0:
            return None
        self._stalled += 1
        previous, self._last_failed = self._last_failed, failed
        if self._stalled < after or previous is None:
            return None
        assert previous.features is not None and previous.prepared is not None
        assert failed.features is not None and failed.prepared is not None
        shape = failed.prepared.gray.shape
        if not first_only and (resumed := self._resume(failed, shape, timer, place)) is not None:
            return resumed
        trial = make_tracker(self.config)
        trial.commit(previous.record.index, previous.features, shape, Track(np.eye(3)))
        if trial.track(failed.record.index, failed.features, shape, timer).reason is not None:
            return None
        if first_only:
            fresh = self._fresh(segment.index)
            self.all[segment.index] = fresh
        else:
            fresh = self.new()
        track = None
        for frame in (previous, failed):
            assert frame.features is not None
            track = fresh.tracker.track(frame.record.index, frame.features, shape, timer)
            note_registration(frame.record, track)
            reason = place(fresh, frame, track, timer)
            if reason is not None:
                frame.record.reason = reason
        if not first_only:
            log.warning(
                "frames did not register to the mosaic since frame %d; segment %d starts at "
                "frame %d",
                segment.records[-1].index + 1,
                fresh.index,
                previous.record.index,
            )
            return track
        dropped = segment.records[0]
        dropped.status, dropped.segment, dropped.H_frame_to_ref = FAILED, None, None
        dropped.reason = (
            f"dropped as the mosaic's first frame: the next {after} frames did not register to it"
        )
        log.warning(
            "frame %d dropped: no frame registered to it; the mosaic starts again at frame %d",
            dropped.index,
            previous.record.index,
        )
        return track

    def _resume(
        self, failed: Extracted, shape: tuple[int, int], timer: Timer, place: Place
    ) -> Track | None:
        """Before another segment starts: a camera lost again may be back over the area of a
        later segment it left, so the frame is tried against each (the most recent first);
        where it registers, that segment goes on. Tried where a new segment would be (each
        failure from the `new_segment_after`-th on), one registration per later segment."""
        assert failed.features is not None
        for other in reversed(self.all[1:]):
            if other.index == self.active or not other.records:
                continue
            track = other.tracker.track(failed.record.index, failed.features, shape, timer)
            if track.reason is not None:
                continue
            if place(other, failed, track, timer) is not None:
                continue
            note_registration(failed.record, track)
            self.active = other.index
            index = failed.record.index
            log.warning("frame %d registers to segment %d again; it goes on", index, other.index)
            return track
        return None

    def refine(self) -> None:
        """Global refinement of each segment's poses (keyframe strategy)."""
        for segment in self.all:
            if segment.tracker.refine() is None:
                continue
            poses = {r.index: segment.tracker.pose(r.index) for r in segment.records}
            segment.refined_poses = {k: self.to_frame(H) for k, H in poses.items() if H is not None}

    def joined_poses(self) -> dict[int, dict[int, np.ndarray]]:
        """The refined poses, in the first segment's frame, of the frames of each later segment
        the camera came back from (`Join`), carried over by the frame that registered to both:
        {later segment: {frame: H_frame_to_ref}}."""
        first = self.all[0] if self.all else None
        joined: dict[int, dict[int, np.ndarray]] = {}
        for join in self.joins:
            later = self.all[join.segment]
            if join.segment in joined or first is None or not first.refined_poses:
                continue
            needed = {join.reference, *(r.index for r in later.records)}
            if not later.refined_poses or not needed <= later.refined_poses.keys():
                continue
            if join.frame not in first.refined_poses:
                continue
            H_later_to_first = first.refined_poses[join.frame] @ np.linalg.inv(
                later.refined_poses[join.reference] @ join.H_frame_to_reference
            )
            poses = (H_later_to_first @ later.refined_poses[r.index] for r in later.records)
            joined[later.index] = {
                r.index: H / H[2, 2] for r, H in zip(later.records, poses, strict=True)
            }
        return joined

    def join(self, joined: dict[int, dict[int, np.ndarray]]) -> None:
        """Put the frames of the `joined` later segments into the first at their poses there
        (`joined_poses`), once the first has been rendered with them; the segments left are
        numbered again in order."""
        first = self.all[0]
        assert first.refined_poses is not None
        for k, poses in joined.items():
            later = self.all[k]
            log.info("segment %d joins the first", k)
            first.refined_poses.update(poses)
            first.records = sorted(first.records + later.records, key=lambda r: r.index)
            self.joined_stats.append(later.tracker.stats())
        self.all = [s for s in self.all if s.index not in joined]
        for number, segment in enumerate(self.all):
            segment.index = number
            for record in segment.records:
                record.segment = number


def note_registration(record: FrameRecord, track: Track) -> None:
    """The record's registration figures from a track (none for a segment's first frame)."""
    registration = track.registration
    if registration is None:
        record.n_matches = record.n_inliers = 0
        record.reproj_error_px = record.coverage = record.aligned_px = float("nan")
        record.model = record.reference = None
        return
    record.n_matches = registration.n_matches
    record.n_inliers = registration.n_inliers
    record.reproj_error_px = registration.reproj_error_px
    record.model = registration.model
    record.coverage = registration.coverage
    record.aligned_px = registration.aligned_px
    record.reference = track.reference_index
    record.by_flow = track.by_flow
