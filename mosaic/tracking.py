"""Where does the current frame go? Registration strategies that place frames on the mosaic.

- `ChainTracker`: the paper's frame-to-frame chaining, `H_frame_to_ref = H_prev_to_ref @
  H_moving_to_fixed`; errors accumulate with every step.
- `KeyframeTracker`: each frame registers to the keyframe it overlaps most and to its
  predecessor; a frame becomes a keyframe when its registration to the current one decays
  (inliers, coverage) or their overlap drops, before registration fails. A frame that fails
  every keyframe but matches its predecessor keeps its place (so does one whose keyframe
  registration the predecessor's, with as many inliers, contradicts); one that fails both is
  relocalised against nearby and, while lost, all keyframes; new keyframes are matched against
  older overlapping ones (loop closure); at the end a pose graph over every placed frame is
  refined. Keyframes keep their features (bounded count), never their pixels.

A tracker proposes a placement (`track`); the pipeline `commit`s it once the frame is on the
canvas, so a frame the canvas refuses leaves the tracker unchanged.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np

from mosaic.config import Config
from mosaic.features import Features
from mosaic.geometry import apply_homography, corner_error, frame_corners
from mosaic.matching import Matches, match_descriptors
from mosaic.pixel_refine import align_similarity, flow_points, texture_agreement, track_points
from mosaic.posegraph import Constraint, Refinement, refine_poses, refine_tilted_poses
from mosaic.registration import Registration, estimate_motion, perspective_needed

log = logging.getLogger(__name__)

Timed = Callable[..., Any]  # timer.run(stage, fn, *args)
# tracked points a registration is refitted on (fewer: it keeps its keypoints). Below the 20
# keypoint inliers a registration needs: on noisy magnified video tracking keeps fewer than
# 20 in a quarter of the registrations, and 10 tracked points place a link better than 20-40
# keypoints (fast45's links: zoom and roll 1.43 -> 1.29 % rms a link)
TRACK_MIN_POINTS = 10
TRACK_MAX_POINTS = 100  # inliers re-localised per registration (more add cost, not precision)
FLOW_MAX_POINTS = 300  # the predecessor's keypoints followed by flow where matching failed
FLOW_MIN_AGREEMENT = 0.4  # NCC of the two band-passed frames at the flow's placement: at the
# true placement 0.5-0.98 on textured realistic video, ~0.2 where noise dominates (there flow
# stays near its prior both ways, and a wrong placement scores as well as the right one)
FLOW_PEAK_PX = 3.0  # ... and higher there than with the placement shifted this far each way


@dataclass(frozen=True)
class Track:
    """A proposed placement of one frame (or why there is none)."""

    H_frame_to_ref: np.ndarray | None
    registration: Registration | None = None
    matches: Matches | None = None
    reference: Features | None = None  # the features the frame was matched against
    keyframe: int | None = None  # keyframe id (keyframe strategy)
    relocalised: bool = False
    attempts: int = 0
    reference_index: int | None = None  # input frame index of the reference
    by_flow: bool = False  # placed by optical flow from the predecessor (`_by_flow`)
    leaf: bool = False  # committed as a leaf: placed and linked, but no later frame's reference
    previous: Registration | None = None  # the frame against its predecessor (keyframes)
    previous_matches: Matches | None = None
    # registrations to other keyframes than the chosen one: (keyframe's frame index, it)
    links: tuple[tuple[int, Registration], ...] = ()

    @property
    def reason(self) -> str | None:
        if self.H_frame_to_ref is not None:
            return None
        if self.registration is not None and self.registration.reason:
            return self.registration.reason
        return "no reference to register against"


class Tracker(Protocol):
    """What the pipeline needs of a registration strategy."""

    name: str

    def track(
        self, index: int, features: Features, shape: tuple[int, int], timer: Any, leaf: bool = False
    ) -> Track:
        """Propose where the frame goes (the first frame of a segment: identity); `leaf`: the
        frame is to be committed as a leaf (`Track.leaf`), and leaves the video's state as is."""
        ...

    def commit(self, index: int, features: Features, shape: tuple[int, int], track: Track) -> None:
        """The frame is on the canvas: update the tracker's state."""
        ...

    def refine(self) -> Refinement | None:
        """Global refinement at the end of a segment (None when the strategy has none)."""
        ...

    def pose(self, index: int) -> np.ndarray | None:
        """Current best `H_frame_to_ref` of a committed frame."""
        ...

    def stats(self) -> dict[str, Any]:
        """Counters for the report."""
        ...


class PerspectiveEvidence:
    """Whether this video's views need the perspective terms between them: the median, over
    its last WINDOW tracked registrations of frames at least MIN_BASELINE apart, of
    `registration.perspective_evidence`. Perspective comes from the camera and the eye, so it
    is a property of the video; one registration's test is weak (its points' errors are not
    independent), many agree; frames close together show too little of it to tell (evidence
    1.3-1.6 between consecutive tilted frames). Measured on the realistic tuning videos: a
    median of 1.3-1.7 without perspective, 3.7-6 with the mild tilt of `mosaic synth
    --realistic` (frames 8-20 apart); relaxing without need costs precision (corner error 0.24
    -> 0.62 px), not relaxing with it costs ~0.8 px."""

    WINDOW = 31
    THRESHOLD = 2.5
    MIN_VALUES = 5  # before this many, each registration's own test decides
    MIN_BASELINE = 0.1  # only registrations whose frames are this far apart (of the diagonal) vote

    def __init__(self) -> None:
        self._values: deque[float] = deque(maxlen=self.WINDOW)
        self.tracked = 0  # registrations refitted on tracked points (for the report)
        self.aligned = 0  # of which tracked from the windows' alignment
        self.relaxed = 0  # of which relaxed by the perspective prior

    def add(self, value: float) -> None:
        if np.isfinite(value):
            self._values.append(value)

    def copy(self) -> PerspectiveEvidence:
        """The evidence so far, to vote on without changing this one."""
        other = PerspectiveEvidence()
        other._values.extend(self._values)
        return other

    def needed(self, value: float, model: str) -> bool:
        """Relax this registration (its own evidence `value`, already added)?"""
        if len(self._values) < self.MIN_VALUES:
            return np.isfinite(value) and perspective_needed(value, model)
        return float(np.median(self._values)) > self.THRESHOLD


def _register(
    reference: Features,
    features: Features,
    config: Config,
    timer: Any,
    shape: tuple[int, int],
    model: str | None = None,
    perspective: PerspectiveEvidence | None = None,
) -> tuple[Matches, Registration]:
    matches = timer.run(
        "match", match_descriptors, reference.descriptors, features.descriptors, config.matching
    )
    registration = timer.run(
        "estimate",
        estimate_motion,
        features.xy[matches.idx_b],
        reference.xy[matches.idx_a],
        config.registration,
        shape,
        model,
    )
    window = config.registration.track_window_px
    if (
        registration.ok
        and window > 0
        and config.registration.refine
        and reference.texture is not None
        and features.texture is not None
    ):
        registration = timer.run(
            "estimate",
            _tracked,
            registration,
            reference,
            features,
            config,
            shape,
            model,
            perspective or PerspectiveEvidence(),
        )
    return matches, registration


def _tracked(
    registration: Registration,
    reference: Features,
    features: Features,
    config: Config,
    shape: tuple[int, int],
    model: str | None,
    perspective: PerspectiveEvidence,
) -> Registration:
    """The registration refitted on its inliers re-localised by tracking
    (`pixel_refine.track_points`); it keeps its matches and inlier counts (what keyframe
    promotion reads). Unchanged where fewer than TRACK_MIN_POINTS (or `min_inliers`) points
    track or the refit fails. The refit is relaxed by the perspective prior only where the
    video's views need it (`PerspectiveEvidence`): on tracked points, which are placed twice
    as precisely, the relaxation would otherwise fit their errors."""
    assert registration.points is not None and registration.H_moving_to_fixed is not None
    xy_cur = registration.points[0]
    if len(xy_cur) > TRACK_MAX_POINTS:  # evenly through the list: spread over the frame
        xy_cur = xy_cur[np.linspace(0, len(xy_cur) - 1, TRACK_MAX_POINTS).round().astype(int)]
    H_start, aligned_px = registration.H_moving_to_fixed, float("nan")
    if features.coarse is not None and reference.coarse is not None:
        aligned = align_similarity(features.coarse, reference.coarse, xy_cur, H_start)
        if aligned is not None:
            aligned_px = corner_error(aligned, H_start, (shape[1], shape[0]))
            H_start = aligned
    pred = apply_homography(H_start, xy_cur.astype(np.float64))
    found, ok = track_points(
        features.texture, reference.texture, xy_cur, pred, config.registration.track_window_px
    )
    refit_config = dataclasses.replace(
        config.registration, min_inliers=min(TRACK_MIN_POINTS, config.registration.min_inliers)
    )
    if ok.sum() < refit_config.min_inliers:
        return registration
    h, w = shape
    centre = np.array([[w / 2, h / 2]])
    relaxed = False

    def relax(evidence: float, H_pure: np.ndarray, fitted: str) -> bool:
        nonlocal relaxed
        baseline = float(np.linalg.norm(apply_homography(H_pure, centre) - centre) / np.hypot(w, h))
        if baseline >= perspective.MIN_BASELINE:
            perspective.add(evidence)
        relaxed = perspective.needed(evidence, fitted)
        return relaxed

    refit = estimate_motion(xy_cur[ok], found[ok], refit_config, shape, model, relax)
    if not refit.ok:
        return registration
    perspective.relaxed += relaxed
    perspective.tracked += 1
    perspective.aligned += int(np.isfinite(aligned_px))
    return dataclasses.replace(
        registration,
        aligned_px=aligned_px,
        H_moving_to_fixed=refit.H_moving_to_fixed,
        reproj_error_px=refit.reproj_error_px,
        model=refit.model,
        corner_sd_px=refit.corner_sd_px,
        points=refit.points,
    )


class ChainTracker:
    """The paper's frame-to-frame chaining.

    Its steps use the pure motion model (no `perspective_prior`): between consecutive frames
    there is no perspective to find, and what the relaxed terms fit of the matches' errors
    adds up along the chain, which no pose graph corrects (measured: realistic tuning set
    0.46 of frames within 10 px with the pure similarity, 0.33 with the prior)."""

    name = "chain"

    def __init__(self, config: Config):
        pure = dataclasses.replace(config.registration, perspective_prior=0.0)
        self._config = dataclasses.replace(config, registration=pure)
        self._prev: Features | None = None
        self._prev_index: int | None = None
        self._H_prev_to_ref = np.eye(3)
        self._poses: dict[int, np.ndarray] = {}

    def track(
        self, index: int, features: Features, shape: tuple[int, int], timer: Any, leaf: bool = False
    ) -> Track:
        if self._prev is None:
            return Track(np.eye(3))
        matches, registration = _register(self._prev, features, self._config, timer, shape)
        H = self._H_prev_to_ref @ registration.H_moving_to_fixed if registration.ok else None
        return Track(
            H, registration, matches, self._prev, attempts=1, reference_index=self._prev_index
        )

    def commit(self, index: int, features: Features, shape: tuple[int, int], track: Track) -> None:
        assert track.H_frame_to_ref is not None
        self._prev, self._H_prev_to_ref = features, track.H_frame_to_ref
        self._prev_index = index
        self._poses[index] = track.H_frame_to_ref

    def refine(self) -> Refinement | None:
        return None

    def pose(self, index: int) -> np.ndarray | None:
        return self._poses.get(index)

    def stats(self) -> dict[str, Any]:
        return {}


def overlap_fraction(poly_a: np.ndarray, poly_b: np.ndarray) -> float:
    """Area of the intersection of two convex quadrilaterals over the area of `poly_a`."""
    area_a = cv2.contourArea(poly_a.astype(np.float32))
    if area_a <= 0 or not np.isfinite(poly_a).all() or not np.isfinite(poly_b).all():
        return 0.0
    inter, _ = cv2.intersectConvexConvex(poly_a.astype(np.float32), poly_b.astype(np.float32))
    return float(inter / area_a)


@dataclass
class Keyframe:
    """A frame kept as a registration anchor: its features, not its pixels."""

    id: int
    frame_index: int
    features: Features | None  # None once dropped from memory (its pose stays in the graph)
    shape: tuple[int, int]
    H_to_ref: np.ndarray
    peak_inliers: int = 0  # most inliers a frame registered to it has had
    peak_coverage: float = 0.0  # largest inlier coverage a frame registered to it has had

    def footprint(self) -> np.ndarray:
        return apply_homography(self.H_to_ref, frame_corners(self.shape))


@dataclass
class _Counters:
    keyframes: int = 0
    relocalised: int = 0
    via_previous: int = 0
    loop_closures: int = 0
    loop_attempts: int = 0
    extra_links: int = 0  # frames' registrations to keyframes besides their reference
    by_flow: int = 0  # frames no descriptors registered, placed by flow from the predecessor
    refinement: dict[str, float] = field(default_factory=dict)


class KeyframeTracker:
    """Keyframes driven by match quality, frame-to-frame links, relocalisation, loop closure
    and a pose graph over every placed frame."""

    name = "keyframes"
    RECENT_KEYFRAMES = 2  # keyframes this close in time are neighbours, not loop closures
    LOOP_CANDIDATES = 3  # older keyframes tried per new keyframe
    GOOD_INLIERS = 100  # a registration this strong is not compared with other keyframes
    GRID = 3  # constraint points per side: the chosen model's prediction on a GRID x GRID grid
    LINK_POINTS = 24  # tilted pose graph: inlier points per link (evenly through the inliers)
    POINT_SD_PX = 1.0  # ... each with this weight's inverse (tracked inliers: ~0.5-1 px)
    LINK_AGREEMENT_PX = 25.0  # an extra link must place the frame this close to its reference
    MIN_SD_PX = 1.0  # constraint weight = 1 / max(expected corner error, this)
    # A keyframe the predicted footprint overlaps less than this is not tried (but the first,
    # and all while lost): none of 236 such registrations held on six realistic videos (those
    # of 0.10-0.20: 4 %); each cost a matching and a RANSAC run to its iteration limit.
    MIN_CANDIDATE_OVERLAP = 0.05

    def __init__(self, config: Config):
        self._config = config
        self._kcfg = config.keyframes
        self._keyframes: OrderedDict[int, Keyframe] = OrderedDict()
        self._active: int | None = None
        self._poses: dict[int, np.ndarray] = {}  # H_frame_to_ref of every committed frame
        self._constraints: list[Constraint] = []
        # leaves (`Track.leaf`): frame index -> (its keyframe's frame index, H_frame_to_keyframe)
        self._leaves: dict[int, tuple[int, np.ndarray]] = {}
        self._prev: tuple[int, Features] | None = None  # the last committed frame
        self._last_pose: np.ndarray | None = None
        self._step: np.ndarray | None = None  # H_prev_to_prevprev of the last two committed
        self._counters = _Counters()
        self._lost = False  # the last frame failed against every candidate
        self._lost_cursor = 0
        self._perspective = PerspectiveEvidence()  # the video's views: with perspective or not
        self._shape: tuple[int, int] | None = None  # (h, w) of the frames

    @property
    def _tilted_graph(self) -> bool:
        """Does the pose graph model tilted views? Only on tracked inliers: the tilt is read
        from the links' point residuals, and keypoints' own errors (untracked links,
        `track_window_px = 0`) are large and systematic enough to pass for it (the ORB loop
        test: 4.3 px at the end of the loop with the tilt, 0.6 px with the former graph)."""
        registration = self._config.registration
        return (
            self._kcfg.tilt_step_px > 0 and registration.refine and registration.track_window_px > 0
        )

    @property
    def _prev_index(self) -> int | None:
        """Input index of the last committed frame (None before the first)."""
        return self._prev[0] if self._prev else None

    # -- proposing a placement -------------------------------------------------------------
    def _overlaps(self, H_frame_to_ref: np.ndarray, shape: tuple[int, int]) -> dict[int, float]:
        """Fraction of the frame (placed by `H_frame_to_ref`) inside each live keyframe."""
        footprint = apply_homography(H_frame_to_ref, frame_corners(shape))
        return {
            kf.id: overlap_fraction(footprint, kf.footprint())
            for kf in self._keyframes.values()
            if kf.features is not None
        }

    def _candidates(self, shape: tuple[int, int]) -> list[Keyframe]:
        """Keyframes to try, in order: those the predicted footprint (the last pose) overlaps
        most, the active one first among equals (after the first, only those it overlaps by
        MIN_CANDIDATE_OVERLAP); then, while lost, a rotating batch of all others, so a camera
        returning anywhere on the map after a blink or a jump is found again within a few
        frames."""
        assert self._last_pose is not None
        overlaps = self._overlaps(self._last_pose, shape)
        ranked = sorted(
            (self._keyframes[k] for k in overlaps),
            key=lambda kf: (overlaps[kf.id], kf.id == self._active, kf.id),
            reverse=True,
        )
        n = 1 + self._kcfg.relocalise_candidates
        nearby, rest = ranked[:n], ranked[n:]
        if not self._lost:
            return nearby[:1] + [
                kf for kf in nearby[1:] if overlaps[kf.id] >= self.MIN_CANDIDATE_OVERLAP
            ]
        if rest:
            start = self._lost_cursor % len(rest)
            self._lost_cursor += n
            return nearby + (rest[start:] + rest[:start])[:n]
        return nearby

    def track(
        self, index: int, features: Features, shape: tuple[int, int], timer: Any, leaf: bool = False
    ) -> Track:
        if not self._keyframes:
            return Track(np.eye(3))
        # a leaf's registrations (blurred, hazy) do not vote on the video's perspective
        perspective = self._perspective.copy() if leaf else self._perspective
        previous = previous_matches = None
        prev_is_keyframe = self._prev is not None and any(
            kf.frame_index == self._prev[0] for kf in self._keyframes.values()
        )
        if self._prev is not None and not prev_is_keyframe:
            previous_matches, previous = _register(
                self._prev[1], features, self._config, timer, shape, perspective=perspective
            )
        candidates = self._candidates(shape)
        first: Track | None = None
        best: Track | None = None
        tried: dict[int, Registration] = {}  # keyframe id -> the frame registered to it
        for kf in candidates:
            assert kf.features is not None
            matches, registration = _register(
                kf.features, features, self._config, timer, shape, perspective=perspective
            )
            tried[kf.id] = registration
            if kf.frame_index == self._prev_index:
                previous, previous_matches = registration, matches
            if not registration.ok:
                if first is None:
                    first = Track(None, registration, matches, kf.features, kf.id)
                continue
            H = kf.H_to_ref @ registration.H_moving_to_fixed
            track = Track(H, registration, matches, kf.features, kf.id)
            if best is None or registration.n_inliers > best.registration.n_inliers:  # type: ignore[union-attr]
                best = track
            # A weak registration (few inliers: small overlap, blur, glare) may be bettered by
            # the next keyframe; a strong one is taken at once.
            if registration.n_inliers >= self.GOOD_INLIERS:
                break
        attempts = len(candidates) + (previous is not None and not prev_is_keyframe)
        extra = dict(attempts=attempts, previous=previous, previous_matches=previous_matches)
        if best is not None and self._contradicted(best, previous, shape):
            log.info(
                "frame %d: keyframe %d's registration contradicts the predecessor's; "
                "placed by the predecessor",
                index,
                best.keyframe,
            )
            best = None
        if best is not None:
            self._lost = False
            assert best.keyframe is not None
            bridged = self._bridge(index, features, shape, timer, tried, perspective, best)
            tried.update(bridged)
            links = self._links(best, tried, shape)
            return dataclasses.replace(
                best,
                relocalised=first is not None,
                reference_index=self._keyframes[best.keyframe].frame_index,
                links=links,
                **extra,
            )
        if previous is not None and previous.ok and self._prev is not None:
            # No keyframe registers, but the predecessor does: the frame keeps its place.
            self._lost = False
            H = self._poses[self._prev[0]] @ previous.H_moving_to_fixed
            return Track(
                H,
                previous,
                previous_matches,
                self._prev[1],
                None,
                reference_index=self._prev[0],
                **extra,
            )
        flowed = self._by_flow(features, shape, timer)
        if flowed is not None:
            self._lost = False
            return dataclasses.replace(flowed, **extra)
        self._lost = True
        assert first is not None
        return dataclasses.replace(first, **extra)

    def _by_flow(self, features: Features, shape: tuple[int, int], timer: Any) -> Track | None:
        """A frame no keyframe nor its predecessor registers by descriptors (motion blur, a
        fast jump, a hazy view) placed by following the predecessor's keypoints into it with
        optical flow (`pixel_refine.flow_points`), from where the last step's motion predicts them;
        the model is fitted to the points that track there and back, under the same failure
        rules. It then becomes a keyframe, so the chain goes on through it."""
        registration_config = self._config.registration
        if not registration_config.flow_fallback or self._prev is None:
            return None
        prev_index, prev = self._prev
        if prev.texture is None or features.texture is None or len(prev.xy) == 0:
            return None
        xy_prev = prev.xy
        if len(xy_prev) > FLOW_MAX_POINTS:  # evenly through the list: spread over the frame
            xy_prev = xy_prev[np.linspace(0, len(xy_prev) - 1, FLOW_MAX_POINTS).round().astype(int)]
        H_moving_to_fixed = np.eye(3) if self._step is None else self._step  # constant velocity
        pred = apply_homography(np.linalg.inv(H_moving_to_fixed), xy_prev.astype(np.float64))
        window = registration_config.track_window_px or 31
        found, ok = timer.run(
            "estimate", flow_points, prev.texture, features.texture, xy_prev, pred, window
        )
        if ok.sum() < registration_config.min_inliers:
            return None
        registration = timer.run(
            "estimate", estimate_motion, found[ok], xy_prev[ok], registration_config, shape
        )
        if not registration.ok:
            return None
        assert registration.H_moving_to_fixed is not None
        H = registration.H_moving_to_fixed
        agreement = texture_agreement(prev.texture, features.texture, H)
        log.info(
            "flow from frame %d: %d inliers, agreement %.3f",
            prev_index, registration.n_inliers, agreement,
        )  # fmt: skip
        if agreement < FLOW_MIN_AGREEMENT or not _peaks(agreement, prev, features, registration):
            return None
        H = self._poses[prev_index] @ registration.H_moving_to_fixed
        return Track(
            H, registration, None, prev, None, reference_index=prev_index, previous=registration,
            by_flow=True,
        )  # fmt: skip

    def _contradicted(
        self, best: Track, previous: Registration | None, shape: tuple[int, int]
    ) -> bool:
        """Does the frame's registration to its predecessor, with at least as many inliers,
        place it elsewhere than the chosen keyframe's (LINK_AGREEMENT_PX at the corners)? A
        wrong registration that passes the failure rules (a few dozen inliers on a repetitive
        or featureless view) would otherwise place the frame and outvote the right link in the
        pose graph."""
        if previous is None or not previous.ok or self._prev is None or best.keyframe is None:
            return False
        if self._keyframes[best.keyframe].frame_index == self._prev[0]:
            return False
        assert best.registration is not None and previous.H_moving_to_fixed is not None
        if previous.n_inliers < best.registration.n_inliers:
            return False
        by_previous = self._poses[self._prev[0]] @ previous.H_moving_to_fixed
        return not self._agree(by_previous, best.H_frame_to_ref, shape)

    def _agree(self, H_a: np.ndarray, H_b: np.ndarray, shape: tuple[int, int]) -> bool:
        """Do two placements of a frame lie within LINK_AGREEMENT_PX (mean over its corners)?"""
        frame = frame_corners(shape)
        gap = np.linalg.norm(
            apply_homography(H_a, frame) - apply_homography(H_b, frame), axis=1
        ).mean()
        return bool(gap <= self.LINK_AGREEMENT_PX)

    def _links(
        self, best: Track, tried: dict[int, Registration], shape: tuple[int, int]
    ) -> tuple[tuple[int, Registration], ...]:
        """Every registration besides the chosen one that holds and places the frame where the
        chosen one does (within LINK_AGREEMENT_PX at the corners: a wrong registration with
        enough inliers would otherwise pull the whole graph); the previous frame's registration
        is a link of its own."""
        assert best.H_frame_to_ref is not None
        links = []
        for k, registration in tried.items():
            kf = self._keyframes[k]
            if k == best.keyframe or not registration.ok or kf.frame_index == self._prev_index:
                continue
            assert registration.H_moving_to_fixed is not None
            H = kf.H_to_ref @ registration.H_moving_to_fixed
            if self._agree(H, best.H_frame_to_ref, shape):
                links.append((kf.frame_index, registration))
        return tuple(links)

    def _bridge(
        self,
        index: int,
        features: Features,
        shape: tuple[int, int],
        timer: Any,
        tried: dict[int, Registration],
        perspective: PerspectiveEvidence,
        best: Track,
    ) -> dict[int, Registration]:
        """For the first `bridge_frames` frames after a promotion, the frame's registrations to
        the `bridge_keyframes` keyframes before the newest one (those not tried already, and
        overlapping the frame where `best` places it by MIN_CANDIDATE_OVERLAP). A new
        keyframe is otherwise tied to its predecessor by one link, whose scale and rotation
        errors every later frame inherits; frames that see both keyframes add independent
        links (measured on the realistic tuning set: mean error 4.0 -> 3.1 px)."""
        k = self._kcfg
        ids = list(self._keyframes)
        newest = self._keyframes[ids[-1]]
        if not k.bridge_keyframes or index - newest.frame_index > k.bridge_frames:
            return {}
        out = {}
        assert best.H_frame_to_ref is not None
        footprint = apply_homography(best.H_frame_to_ref, frame_corners(shape))
        for kid in reversed(ids[-1 - k.bridge_keyframes : -1]):
            kf = self._keyframes[kid]
            if kid in tried or kf.features is None or kf.frame_index == self._prev_index:
                continue  # the previous frame's registration is its own link
            if overlap_fraction(footprint, kf.footprint()) < self.MIN_CANDIDATE_OVERLAP:
                continue
            out[kid] = _register(
                kf.features, features, self._config, timer, shape, perspective=perspective
            )[1]
        return out

    # -- committing ------------------------------------------------------------------------
    def commit(self, index: int, features: Features, shape: tuple[int, int], track: Track) -> None:
        assert track.H_frame_to_ref is not None
        if track.leaf and track.keyframe is not None:
            self._commit_leaf(index, track)
            return
        self._shape = shape
        self._last_pose = track.H_frame_to_ref
        self._poses[index] = track.H_frame_to_ref
        prev = self._prev
        self._prev = (index, features)
        if prev is not None:  # the last step's motion: the prior of the next frame's flow
            self._step = np.linalg.inv(self._poses[prev[0]]) @ self._poses[index]
        if track.by_flow:
            self._counters.by_flow += 1
        if track.registration is None:  # first frame of the segment
            self._promote(index, features, shape, track.H_frame_to_ref)
            return
        if track.relocalised:
            self._counters.relocalised += 1
            log.info("frame %d relocalised on keyframe %d", index, track.keyframe)
        if track.previous is not None and track.previous.ok and prev is not None:
            self._add_constraint(index, prev[0], track.previous, shape)
        if track.keyframe is None:
            self._counters.via_previous += 1
            log.info("frame %d placed by its predecessor only: new keyframe", index)
            self._promote(index, features, shape, track.H_frame_to_ref)
            return
        kf = self._keyframes[track.keyframe]
        registration = track.registration
        assert registration is not None
        if kf.frame_index != (prev[0] if prev else None):  # else added as the previous link
            self._add_constraint(index, kf.frame_index, registration, shape)
        for other, link in track.links:
            self._add_constraint(index, other, link, shape)
            self._counters.extra_links += 1
        weak = self._weak(kf, registration)
        kf.peak_inliers = max(kf.peak_inliers, registration.n_inliers)
        if np.isfinite(registration.coverage):
            kf.peak_coverage = max(kf.peak_coverage, registration.coverage)
        overlaps = self._overlaps(track.H_frame_to_ref, shape)
        best = max(overlaps, key=lambda k: (overlaps[k], k == kf.id))
        if weak is None and overlaps[best] >= self._kcfg.min_overlap:
            self._active = best  # the next frame starts with the keyframe it overlaps most
            return
        log.debug("frame %d becomes a keyframe: %s", index, weak or "overlap")
        new = self._promote(index, features, shape, track.H_frame_to_ref)
        if self._kcfg.loop_closure:
            self._close_loops(new, kf.id, shape)

    def _commit_leaf(self, index: int, track: Track) -> None:
        """A frame placed by its keyframe alone, which moves no other pose: no later frame
        registers to it (neither keyframe nor predecessor), and it stays out of the pose graph
        (its link would pull its neighbours' tilts there); after refinement it follows its
        keyframe. A blurred or hazy frame's registrations are the least precise."""
        assert track.H_frame_to_ref is not None and track.keyframe is not None
        assert track.registration is not None and track.registration.H_moving_to_fixed is not None
        self._poses[index] = track.H_frame_to_ref
        kf = self._keyframes[track.keyframe]
        self._leaves[index] = (kf.frame_index, track.registration.H_moving_to_fixed)

    def _weak(self, kf: Keyframe, registration: Registration) -> str | None:
        """Why the keyframe no longer holds (its registrations decay), or None."""
        k = self._kcfg
        n = registration.n_inliers
        if n < k.promote_min_inliers:
            return f"{n} inliers < {k.promote_min_inliers}"
        if kf.peak_inliers and n < k.promote_inlier_ratio * kf.peak_inliers:
            return f"{n} inliers < {k.promote_inlier_ratio} x {kf.peak_inliers}"
        coverage = registration.coverage
        if kf.peak_coverage and coverage < k.promote_coverage_ratio * kf.peak_coverage:
            return f"coverage {coverage:.2f} < {k.promote_coverage_ratio} x {kf.peak_coverage:.2f}"
        return None

    def _promote(
        self, index: int, features: Features, shape: tuple[int, int], H_to_ref: np.ndarray
    ) -> Keyframe:
        next_id = max(self._keyframes, default=-1) + 1
        kf = Keyframe(next_id, index, features, shape, H_to_ref)
        self._keyframes[kf.id] = kf
        self._active = kf.id
        self._counters.keyframes += 1
        alive = [k for k in self._keyframes.values() if k.features is not None]
        if len(alive) > self._kcfg.max_keyframes:
            alive[0].features = None  # forget the oldest keyframe's features, keep its pose
        return kf

    def _add_constraint(
        self,
        a: int,
        b: int,
        registration: Registration,
        shape: tuple[int, int],
        loop: bool = False,
    ) -> None:
        """Frame a registered onto frame b. For the tilted pose graph, inlier points spread
        through the registration's inliers: they carry what a similarity per link leaves out.
        Otherwise the chosen model's prediction on a grid over a, weighted by how well that
        model is expected to place the frame."""
        assert registration.H_moving_to_fixed is not None
        points = registration.points
        if self._tilted_graph and points is not None and len(points[0]) >= 4:
            pick = np.linspace(0, len(points[0]) - 1, min(len(points[0]), self.LINK_POINTS))
            xy_a, xy_b = (p[pick.round().astype(int)].astype(np.float64) for p in points)
            self._constraints.append(Constraint(a, b, xy_a, xy_b, loop, 1 / self.POINT_SD_PX))
            return
        h, w = shape
        gx, gy = np.meshgrid(np.linspace(0, w, self.GRID), np.linspace(0, h, self.GRID))
        xy_a = np.stack([gx.ravel(), gy.ravel()], 1)
        sd = registration.corner_sd_px
        weight = 1.0 / max(sd if np.isfinite(sd) else self.MIN_SD_PX, self.MIN_SD_PX)
        self._constraints.append(
            Constraint(
                a, b, xy_a, apply_homography(registration.H_moving_to_fixed, xy_a), loop, weight
            )
        )

    def _close_loops(self, new: Keyframe, registered_to: int, shape: tuple[int, int]) -> None:
        """Match a new keyframe against older keyframes its footprint overlaps."""
        recent = set(list(self._keyframes)[-(self.RECENT_KEYFRAMES + 1) :]) | {registered_to}
        footprint = new.footprint()
        scored = [
            (overlap_fraction(footprint, kf.footprint()), kf)
            for kf in self._keyframes.values()
            if kf.id not in recent and kf.features is not None
        ]
        scored = [s for s in scored if s[0] >= self._kcfg.loop_min_overlap]
        scored.sort(key=lambda s: s[0], reverse=True)
        assert new.features is not None
        for _, old in scored[: self.LOOP_CANDIDATES]:
            assert old.features is not None
            self._counters.loop_attempts += 1
            _, registration = _register(
                old.features, new.features, self._config, _NoTimer, shape, None, self._perspective
            )
            if registration.ok:
                self._add_constraint(new.frame_index, old.frame_index, registration, shape, True)
                self._counters.loop_closures += 1
                log.info("loop closure: keyframe %d <-> %d", new.id, old.id)

    # -- refinement ------------------------------------------------------------------------
    def refine(self) -> Refinement | None:
        if not self._kcfg.refine or len(self._poses) < 2:
            return None
        graph = {k: H for k, H in self._poses.items() if k not in self._leaves}
        if len(graph) < 2:
            return None
        fixed = min(graph)
        if self._tilted_graph and self._shape is not None:
            result = refine_tilted_poses(
                graph, self._constraints, fixed, self._shape, self._kcfg.tilt_step_px
            )
        else:
            result = refine_poses(graph, self._constraints, fixed)
        poses = dict(result.poses)
        for index, (keyframe, H_frame_to_keyframe) in self._leaves.items():
            poses[index] = poses[keyframe] @ H_frame_to_keyframe
        result = dataclasses.replace(result, poses=poses)
        self._poses.update(result.poses)
        for kf in self._keyframes.values():
            kf.H_to_ref = self._poses[kf.frame_index]
        self._counters.refinement = {
            "rms_before_px": round(result.rms_before_px, 3),
            "rms_after_px": round(result.rms_after_px, 3),
            "constraints": result.n_constraints,
            "dropped_loop_closures": result.dropped_loops,
            "pose_model": result.pose_model,
            "tilt_gain": round(result.tilt_gain, 4) if np.isfinite(result.tilt_gain) else None,
        }
        return result

    def pose(self, index: int) -> np.ndarray | None:
        return self._poses.get(index)

    def stats(self) -> dict[str, Any]:
        c = self._counters
        return {
            "keyframes": c.keyframes,
            "relocalised": c.relocalised,
            "placed_by_previous": c.via_previous,
            "loop_closures": c.loop_closures,
            "loop_attempts": c.loop_attempts,
            "extra_links": c.extra_links,
            "placed_by_flow": c.by_flow,
            "tracked_registrations": self._perspective.tracked,
            "aligned_registrations": self._perspective.aligned,
            "perspective_relaxed": self._perspective.relaxed,
            "refinement": c.refinement or None,
        }


def _peaks(
    agreement: float, reference: Features, features: Features, registration: Registration
) -> bool:
    """Is the two textures' agreement at the registration higher than with the placement
    moved FLOW_PEAK_PX along either axis (a placement, not a plateau)?"""
    assert reference.texture is not None and features.texture is not None
    assert registration.H_moving_to_fixed is not None
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        shift = np.array([[1.0, 0, dx * FLOW_PEAK_PX], [0, 1.0, dy * FLOW_PEAK_PX], [0, 0, 1.0]])
        H = shift @ registration.H_moving_to_fixed
        if texture_agreement(reference.texture, features.texture, H) >= agreement:
            return False
    return True


class _NoTimer:
    """Loop closures run outside a frame's stage timings."""

    @staticmethod
    def run(stage: str, fn: Callable[..., Any], *args: Any) -> Any:
        return fn(*args)


TRACKERS: dict[str, Callable[[Config], Tracker]] = {
    "chain": ChainTracker,
    "keyframes": KeyframeTracker,
}


def make_tracker(config: Config) -> Tracker:
    """The registration strategy named in `[pipeline] strategy`."""
    return TRACKERS[config.pipeline.strategy](config)
