"""Keypoint detectors (a registry chosen by name) and descriptors; the adapter between
`mosaic` and `glampoints`.

Every detector returns `glampoints.Keypoints` (x, y float32 + scores) restricted to the frame's
field-of-view mask. The descriptor is upright root-SIFT (orientation fixed to 0, the paper's
choice for fundus images) unless `descriptor = "native"` asks for the detector's own.

This module is the one place the application meets the model package (besides the
`glampoints` command line): glampoints' `WeightsError` becomes `DetectorWeightsError`, and the
rest of `mosaic` takes from here what it needs of glampoints: the paper's metrics and failure
rules (`paper_metrics`, `failure_reason`), its synthetic pairs (`HomographyRanges`,
`fixed_pairs`) and the CPU's bfloat16 support (`cpu_has_native_bfloat16`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import cv2
import numpy as np

from glampoints import metrics as paper_metrics  # noqa: F401 (re-exported: see above)
from glampoints.descriptors import upright_rootsift
from glampoints.detector import Keypoints, WeightsError
from glampoints.detector import cpu_has_native_bfloat16 as cpu_has_native_bfloat16
from glampoints.metrics import failure_reason as failure_reason
from glampoints.synthetic import HomographyRanges as HomographyRanges
from glampoints.synthetic import fixed_pairs as fixed_pairs
from mosaic.config import FeaturesConfig
from mosaic.errors import ConfigError, DetectorWeightsError
from mosaic.geometry import rescaled
from mosaic.preprocess import Prepared, erode_by_disc

if TYPE_CHECKING:
    from mosaic.pixel_refine import CoarseTexture

log = logging.getLogger(__name__)

# Largest keypoint diameter a detector's own scale may give the descriptor: wider patches are
# smooth on retina and match ambiguously.
MAX_DETECTOR_SIZE_PX = 20.0


@dataclass(frozen=True)
class Features:
    """Keypoints of one frame with one descriptor row per point."""

    xy: np.ndarray  # (N, 2) float32, (x, y)
    scores: np.ndarray  # (N,) float32
    sizes: np.ndarray  # (N,) float32 keypoint diameter in px, for the SIFT descriptor
    descriptors: np.ndarray  # (N, D) float32 (L2 distance) or uint8 (binary, Hamming distance)
    texture: np.ndarray | None = None  # (H, W) uint8 band-passed frame (`pixel_refine.lk_texture`)
    coarse: CoarseTexture | None = None  # (`pixel_refine.coarse_texture`)

    def __len__(self) -> int:
        return len(self.xy)


class Detector(Protocol):
    """What the pipeline needs of a detector."""

    name: str
    # runs on several cores at once: registering meanwhile would compete (`scheduling.Turns`)
    takes_every_core: bool

    def detect(self, gray: np.ndarray, mask: np.ndarray) -> tuple[Keypoints, np.ndarray]:
        """Keypoints inside `mask` (uint8, nonzero = allowed) and their diameters in px."""
        ...

    def native(self, gray: np.ndarray, mask: np.ndarray) -> Features:
        """Keypoints with the detector's own descriptor."""
        ...


def _strongest(n: int, scores: np.ndarray, limit: int) -> np.ndarray:
    """Indices of the `limit` highest scores, strongest first."""
    order = np.argsort(-scores, kind="stable")
    return order[: min(n, limit)]


def resized_for_detection(
    gray: np.ndarray, mask: np.ndarray, scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame and mask resized by `scale`, and the (x, y) factor from their pixels to the frame's."""
    h, w = gray.shape
    size = (max(round(w * scale), 16), max(round(h * scale), 16))
    small = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    small_mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
    return small, small_mask, np.array([w / size[0], h / size[1]], np.float32)


def to_frame_pixels(xy: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """Points of a resized frame in the frame's pixels (pixel centres: (x + 0.5) * f - 0.5)."""
    return rescaled(xy, factor).astype(np.float32)


class OpenCVDetector:
    """A classical OpenCV detector (SIFT, ORB, AKAZE, KAZE, BRISK)."""

    takes_every_core = False  # detects on about one core (measured: overlapping gains 40-60 %)

    def __init__(self, name: str, factory: Callable[[], cv2.Feature2D], max_keypoints: int):
        self.name = name
        self._cv = factory()
        self._max = max_keypoints

    def _select(self, kps: tuple[cv2.KeyPoint, ...]) -> tuple[list[cv2.KeyPoint], np.ndarray]:
        if not kps:
            return [], np.zeros(0, np.intp)
        xy = cv2.KeyPoint_convert(kps).astype(np.float32)
        scores = np.fromiter((k.response for k in kps), np.float32, len(kps))
        # Several orientations at one location are one point for an upright descriptor.
        _, first = np.unique(np.round(xy, 2), axis=0, return_index=True)
        keep = first[_strongest(len(first), scores[first], self._max)]
        return [kps[i] for i in keep], keep

    def detect(self, gray: np.ndarray, mask: np.ndarray) -> tuple[Keypoints, np.ndarray]:
        kps, _ = self._select(self._cv.detect(gray, mask))
        return _from_cv(kps)

    def native(self, gray: np.ndarray, mask: np.ndarray) -> Features:
        kps, desc = self._cv.detectAndCompute(gray, mask)
        if desc is None or not kps:
            return _empty(self._cv.descriptorSize(), np.uint8 if _binary(self._cv) else np.float32)
        chosen, keep = self._select(tuple(kps))
        keypoints, sizes = _from_cv(chosen)
        return Features(keypoints.xy, keypoints.scores, sizes, desc[keep])


def _binary(cv: cv2.Feature2D) -> bool:
    return cv.defaultNorm() in (cv2.NORM_HAMMING, cv2.NORM_HAMMING2)


def _from_cv(kps: list[cv2.KeyPoint]) -> tuple[Keypoints, np.ndarray]:
    if not kps:
        return Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.float32)), np.zeros(
            0, np.float32
        )
    xy = cv2.KeyPoint_convert(kps).astype(np.float32).reshape(-1, 2)
    scores = np.fromiter((k.response for k in kps), np.float32, len(kps))
    sizes = np.fromiter((k.size for k in kps), np.float32, len(kps))
    return Keypoints(xy, scores), sizes


def _empty(dim: int, dtype: type) -> Features:
    return Features(
        np.zeros((0, 2), np.float32),
        np.zeros(0, np.float32),
        np.zeros(0, np.float32),
        np.zeros((0, dim), dtype),
    )


class RandomGrid:
    """The paper's baseline: points on a uniform grid with a random offset and jitter."""

    name = "random-grid"
    takes_every_core = False

    def __init__(self, max_keypoints: int, seed: int = 0):
        self._max = max_keypoints
        self._rng = np.random.default_rng(seed)

    def detect(self, gray: np.ndarray, mask: np.ndarray) -> tuple[Keypoints, np.ndarray]:
        h, w = gray.shape
        area = max(int(np.count_nonzero(mask)), 1)
        spacing = max(np.sqrt(area / self._max), 2.0)
        ox, oy = self._rng.uniform(0, spacing, 2)
        gx, gy = np.meshgrid(np.arange(ox, w, spacing), np.arange(oy, h, spacing))
        xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
        xy += self._rng.uniform(-spacing / 4, spacing / 4, xy.shape)
        xy = np.clip(xy, 0, [w - 1, h - 1]).astype(np.float32)
        inside = mask[xy[:, 1].astype(int), xy[:, 0].astype(int)] > 0
        xy = xy[inside][: self._max]
        return Keypoints(xy, np.ones(len(xy), np.float32)), np.full(len(xy), 0.0, np.float32)

    def native(self, gray: np.ndarray, mask: np.ndarray) -> Features:
        raise ConfigError("detector random-grid has no descriptor of its own; use rootsift")


def resolve_precision(config: FeaturesConfig, native_bfloat16: bool) -> str:
    """The network's precision: "auto" is bfloat16 on a CPU that has it in hardware."""
    if config.precision != "auto":
        return config.precision
    return "bfloat16" if config.device == "cpu" and native_bfloat16 else "float32"


class GlamPointsDetector:
    """Adapter of the learned GLAMpoints detector (the one place mosaic meets glampoints)."""

    name = "glampoints"

    def __init__(self, config: FeaturesConfig):
        import torch

        from glampoints.detector import GlamPoints

        if config.device == "cuda" and not torch.cuda.is_available():
            raise ConfigError(
                '[features] device = "cuda" but this torch build sees no CUDA GPU; use "cpu"'
            )
        try:
            self._model = GlamPoints.from_pretrained(
                config.weights or None,
                nms_window_px=config.nms_window_px,
                score_threshold=config.score_threshold,
                max_keypoints=config.max_keypoints,
                device=config.device,
                precision=resolve_precision(config, cpu_has_native_bfloat16()),
            )
        except WeightsError as exc:  # the app's own error, so callers catch MosaicError only
            raise DetectorWeightsError(str(exc)) from exc
        self._extra_scale = config.extra_scale
        self._extra_size = (
            config.descriptor_size_px / config.extra_scale if config.extra_scale else 0
        )

    @property
    def precision(self) -> str:
        """The precision the network runs in (float32 | bfloat16): "auto" resolved."""
        return str(self._model.precision)

    @property
    def takes_every_core(self) -> bool:
        """The network runs on torch's CPU threads, more than one: registering meanwhile
        would compete with it for the cores (`scheduling.Turns`)."""
        import torch

        return self._model.device.type == "cpu" and torch.get_num_threads() > 1

    def detect(self, gray: np.ndarray, mask: np.ndarray) -> tuple[Keypoints, np.ndarray]:
        """Keypoints of the frame (size 0: the configured descriptor size); with `extra_scale`,
        plus those of a smaller copy, in frame pixels and described on a larger support, so
        that views of different magnification still share points (the network is single-scale).
        """
        keypoints = self._model.detect(gray, mask)
        sizes = np.zeros(len(keypoints), np.float32)
        s = self._extra_scale
        if not s or s >= 1.0:
            return keypoints, sizes
        small_gray, small_mask, factor = resized_for_detection(gray, mask, s)
        small = self._model.detect(small_gray, small_mask)
        return Keypoints(
            np.concatenate([keypoints.xy, to_frame_pixels(small.xy, factor)]),
            np.concatenate([keypoints.scores, small.scores]),
        ), np.concatenate([sizes, np.full(len(small), self._extra_size, np.float32)])

    def native(self, gray: np.ndarray, mask: np.ndarray) -> Features:
        raise ConfigError("detector glampoints has no descriptor of its own; use rootsift")


def _xf(name: str) -> Callable[..., cv2.Feature2D]:
    """An OpenCV 5 contrib factory (AKAZE, KAZE and BRISK moved to xfeatures2d)."""
    return getattr(cv2.xfeatures2d, f"{name}_create")


# Thresholds sit below OpenCV's defaults: low-contrast retina gives the defaults only a few
# dozen points per frame, so each detector over-detects and the strongest `max_keypoints` stay.
DETECTORS: dict[str, Callable[[FeaturesConfig], Detector]] = {
    "glampoints": GlamPointsDetector,
    "sift": lambda c: OpenCVDetector(
        "sift",
        lambda: cv2.SIFT_create(nfeatures=2 * c.max_keypoints, contrastThreshold=0.01),
        c.max_keypoints,
    ),
    "orb": lambda c: OpenCVDetector(
        "orb", lambda: cv2.ORB_create(nfeatures=c.max_keypoints, fastThreshold=5), c.max_keypoints
    ),
    "akaze": lambda c: OpenCVDetector(
        "akaze", lambda: _xf("AKAZE")(threshold=1e-4), c.max_keypoints
    ),
    "kaze": lambda c: OpenCVDetector("kaze", lambda: _xf("KAZE")(threshold=1e-4), c.max_keypoints),
    "brisk": lambda c: OpenCVDetector("brisk", lambda: _xf("BRISK")(thresh=10), c.max_keypoints),
    "random-grid": lambda c: RandomGrid(c.max_keypoints),
}


MIN_LOCAL_CONTRAST = 1.0  # grey levels (sd) a keypoint's neighbourhood needs to be described
CONTRAST_WINDOW_PX = 31


def _textured(gray: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points whose neighbourhood has some contrast. On a flat patch (a black or blank frame)
    every descriptor is the same quantisation noise and all of them match each other, which
    would "register" two blank images with the identity."""
    if len(xy) == 0:
        return np.zeros(0, bool)
    h, w = gray.shape
    ix = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
    iy = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
    # The window sums of g and g^2 in integers (exact), then as cv2.blur of the float image
    # would give them (its float64 sums of integers are exact too): mean = float32(sum / n).
    k = (CONTRAST_WINDOW_PX, CONTRAST_WINDOW_PX)
    sums = cv2.boxFilter(gray, cv2.CV_32S, k, normalize=False)
    squares = cv2.boxFilter(
        cv2.multiply(gray, gray, dtype=cv2.CV_16U), cv2.CV_32S, k, normalize=False
    )
    per_pixel = 1.0 / (CONTRAST_WINDOW_PX * CONTRAST_WINDOW_PX)
    mean = (sums[iy, ix] * per_pixel).astype(np.float32)
    var = (squares[iy, ix] * per_pixel).astype(np.float32) - mean * mean
    return var >= MIN_LOCAL_CONTRAST**2


def make_detector(config: FeaturesConfig) -> Detector:
    """Build the configured detector by name."""
    try:
        factory = DETECTORS[config.detector]
    except KeyError:
        raise ConfigError(
            f"unknown detector {config.detector!r} (choices: {', '.join(DETECTORS)})"
        ) from None
    return factory(config)


def _inside(mask: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Whether each point (N, 2) falls on a nonzero pixel of `mask` (nearest pixel, clipped)."""
    h, w = mask.shape[:2]
    col = np.round(xy[:, 0]).astype(np.intp).clip(0, w - 1)
    row = np.round(xy[:, 1]).astype(np.intp).clip(0, h - 1)
    return mask[row, col] > 0


class FeatureExtractor:
    """Detector + descriptor as configured: `prepared frame -> Features`."""

    def __init__(self, config: FeaturesConfig, detector: Detector | None = None):
        self.config = config
        self.detector = detector if detector is not None else make_detector(config)
        if config.descriptor == "native" and self.detector.name in ("glampoints", "random-grid"):
            raise ConfigError(
                f"detector {self.detector.name} has no descriptor of its own; "
                'set [features] descriptor = "rootsift"'
            )

    def detect(self, prepared: Prepared) -> Features:
        """Keypoints of a frame; with native descriptors they come described already."""
        if self.config.descriptor == "native":
            detected = self.detector.native(prepared.gray, prepared.mask)
        else:
            keypoints, sizes = self._detect_scaled(prepared)
            # Detectors without a scale (GLAMpoints, grid) get the configured descriptor size;
            # large scales (ORB, BRISK pyramid levels) are capped: such wide, smooth patches
            # match ambiguously on retina.
            size = self.config.descriptor_size_px
            capped = np.minimum(sizes, MAX_DETECTOR_SIZE_PX)
            sizes = np.where(sizes > 0, capped, size).astype(np.float32)
            detected = Features(
                keypoints.xy, keypoints.scores, sizes, np.zeros((len(sizes), 0), np.float32)
            )
        return self._off_the_border(detected, prepared.mask)

    def _off_the_border(self, detected: Features, mask: np.ndarray) -> Features:
        """The keypoints at least `border_margin_px` inside the view's mask and the frame's
        edge. The view's border and burned-in overlays are fixed to the camera: a keypoint
        whose descriptor sees them matches where the camera was, not where the retina went.
        On faint, blurred or glared views such matches are a third of the inliers and pull
        the motion towards zero (measured: 7-11 px wrong steps).

        The points are dropped after detection, not masked out before it: a mask would let
        the detector fill its budget with weaker points instead (measured: fewer frames
        within 10 px on the tuning videos)."""
        margin = round(self.config.border_margin_px)
        if margin <= 0 or len(detected) == 0:
            return detected
        allowed = erode_by_disc(mask, margin, edge_counts=True)
        keep = _inside(allowed, detected.xy)
        return Features(
            detected.xy[keep],
            detected.scores[keep],
            detected.sizes[keep],
            detected.descriptors[keep],
            detected.texture,
        )

    def _detect_scaled(self, prepared: Prepared) -> tuple[Keypoints, np.ndarray]:
        """Detect on the frame resized by `detect_scale`; points and sizes in frame pixels.

        Descriptors are still computed on the full-resolution frame: only the detector (for
        GLAMpoints the network, ~s^2 of the cost) sees the smaller image.
        """
        s = self.config.detect_scale
        if s == 1.0:
            return self.detector.detect(prepared.gray, prepared.mask)
        gray, mask, factor = resized_for_detection(prepared.gray, prepared.mask, s)
        keypoints, sizes = self.detector.detect(gray, mask)
        xy = to_frame_pixels(keypoints.xy, factor)
        h, w = prepared.gray.shape
        inside = (xy[:, 0] <= w - 1) & (xy[:, 1] <= h - 1) & (xy >= 0).all(axis=1)
        inside &= _inside(prepared.mask, xy)
        return Keypoints(xy[inside], keypoints.scores[inside]), sizes[inside] * factor[0]

    def describe(self, prepared: Prepared, detected: Features) -> Features:
        """Attach upright root-SIFT descriptors to detected keypoints (no-op when native)."""
        if detected.descriptors.shape[1] > 0 or self.config.descriptor == "native":
            return detected
        keep = _textured(prepared.gray, detected.xy)
        xy, scores, sizes = detected.xy[keep], detected.scores[keep], detected.sizes[keep]
        return Features(xy, scores, sizes, upright_rootsift(prepared.gray, xy, sizes))

    def __call__(self, prepared: Prepared) -> Features:
        return self.describe(prepared, self.detect(prepared))
