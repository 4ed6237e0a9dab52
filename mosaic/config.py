"""Run configuration: one frozen dataclass per TOML table, strict loading.

`sample_config.toml` at the repository root equals these defaults (a test checks it).
Unknown tables or keys, wrong types, values outside their choices and numbers outside their
range (`RANGES`: one place for every numeric key; NaN and infinity are never valid) raise
`ConfigError` naming the offending key and what it allows, so a typo never silently falls back
to a default and a bad value never reaches OpenCV as a traceback.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, get_type_hints

from mosaic.errors import ConfigError


@dataclass(frozen=True)
class PreprocessConfig:
    """The paper's fundus pre-processing, each step switchable, plus the field-of-view mask."""

    deinterlace: bool = False  # video from an interlaced camera: each frame is replaced by its
    # first field, line-doubled (`preprocess.Deinterlacer`); the report says when a video looks so
    green_channel: bool = True  # use the green channel (best vessel contrast) instead of luma
    clahe: bool = True  # contrast-limited adaptive histogram equalisation
    clahe_clip_limit: float = 2.0
    clahe_tile_grid: int = 8  # tiles per side
    bilateral: bool = True  # edge-preserving denoising
    bilateral_diameter_px: int = 5
    bilateral_sigma_color: float = 25.0
    bilateral_sigma_space: float = 5.0
    fov_mask: bool = True  # keep keypoints off the dark border of fundus / slit-lamp frames
    fov_threshold: int = 12  # grey level under which a border pixel counts as outside the view
    fov_erode_px: int = 6  # margin kept away from the field-of-view edge
    overlay_mask: bool = True  # no keypoints on burned-in overlays (pixels that never change)
    overlay_max_range: int = 2  # grey levels a pixel may vary over the video and count as static
    overlay_margin_px: int = 6  # margin kept away from a static overlay
    surround_mask: bool = True  # the camera's dark surround kept out where haze lifts it
    reflex_mask: bool = True  # no keypoints on lens reflexes: bright spots that stay in one
    # place of the frame while the retina moves (their edges would match where the camera was)
    reflex_brightness: int = 50  # grey levels above its surroundings a reflex keeps in every
    # recent frame
    lens_rim_mask: bool = True  # video through a handheld lens: no keypoints, tracking or
    # blending outside the lens's rim, a disc that moves about the frame (the face around it)
    max_side_px: int = 800  # larger frames are registered (and composed: [compose] resolution)
    # downscaled to this longer side (0: off)
    fov_diameter_px: int = 512  # `mosaic register`: a photograph showing the whole retina is
    # registered with the retina's diameter at this (the detector's training images: 460-640
    # px, median 590), instead of by max_side_px; `mosaic build`: a video whose first readable
    # frame shows a whole retina is also scaled so that it is at most this across (0: off)
    vessel_polarity: bool = True  # `mosaic register`: an angiogram (bright vessels) paired with a
    # colour or red-free photograph (dark vessels) is also registered inverted in its view


@dataclass(frozen=True)
class FeaturesConfig:
    """Keypoint detector and descriptor."""

    detector: str = "glampoints"  # a key of mosaic.features.DETECTORS
    descriptor: str = (
        "rootsift"  # "rootsift": upright root-SIFT (the paper's); "native": detector's own
    )
    max_keypoints: int = 1000  # strongest kept per frame
    nms_window_px: int = 10  # GLAMpoints non-maximum suppression window (paper: 10)
    score_threshold: float = 0.0  # GLAMpoints minimum score of a keypoint
    descriptor_size_px: float = 9.0  # keypoint diameter given to the SIFT descriptor on video
    # frames: 9 px holds on blurred, compressed, magnified frames
    photo_descriptor_size_px: float = 6.0  # the same for photographs (`mosaic register`, the
    # pair benchmarks): on sharp pairs 6 px registers more than 9 px (53.6 % vs 50.5 %)
    detect_scale: float = 1.0  # detect on the frame resized by this (<= 1: faster, coarser)
    weights: str = ""  # GLAMpoints weights file; empty: the weights shipped in the package
    device: str = "cpu"  # where GLAMpoints runs its network: cpu | cuda (a CUDA GPU if present)
    extra_scale: float = 0.0  # GLAMpoints: also detect on the frame resized by this (0: off)
    precision: str = "auto"  # GLAMpoints network on CPU: float32 | bfloat16 | auto
    border_margin_px: float = 12.0  # keypoints this far inside the view's mask and the frame's
    # edge: a descriptor that sees the border (fixed to the camera) matches the camera's place


@dataclass(frozen=True)
class MatchingConfig:
    """Brute-force matching of descriptors."""

    cross_check: bool = True  # keep mutual nearest neighbours only (the paper's)
    ratio: float = 1.0  # Lowe ratio test threshold; 1.0 turns it off


@dataclass(frozen=True)
class RegistrationConfig:
    """Robust homography estimation and the rules that declare it failed."""

    method: str = "ransac"  # ransac | usac_default | usac_magsac | usac_accurate | usac_fast
    reproj_threshold_px: float = 3.0
    max_iters: int = 2000
    confidence: float = 0.995
    min_inliers: int = 20  # fewer RANSAC inliers than this is a failure (a wrong placement
    # smears the mosaic; a skipped frame costs nothing)
    model: str = "similarity"  # similarity | auto (least expected corner error) | translation |
    # affine | homography. Video frames: similarity, measured best on realistic video (richer
    # models fit the matches' errors); `mosaic register` selects (auto) unless --model says
    refine: bool = True  # re-weighted least squares of the model on all matches within threshold
    perspective_prior: float = 0.01  # with refine, relax a model below the homography into
    # one whose departure from it has this prior sd (frame half-diagonal = 1; 0.01 is ~2 px at
    # the corners): the matches set the perspective where they span the frame; 0 = pure model
    track_window_px: int = 31  # video: re-localise each registration's inliers by pyramidal
    # Lucas-Kanade in windows of this side on the band-passed frames, then refit (0: off)
    align_windows: bool = True  # with tracking: before it, one similarity aligned over all the
    # windows together on the smoothed band-passed frames (the points start from it)
    flow_fallback: bool = True  # video, keyframes: a frame no descriptors register is placed by
    # optical flow from its predecessor (motion prior, forward-backward check, same rules)
    refine_levels: int = 3  # `mosaic register`: coarse-to-fine levels from the working size up to
    # the photographs' pixels (template matching around each inlier, robust refit; 0: off)


@dataclass(frozen=True)
class ComposeConfig:
    """Mosaic canvas, blending and the frames' photometric correction."""

    blend: str = "multiband"  # multiband | feather | average | last | best (mosaic.compose)
    resolution: str = "working"  # working: frames are composed at the size they are registered
    # at ([preprocess] max_side_px; 1920x1080 video: ~2x the frame rate) | full: as decoded
    max_canvas_px: int = 8000  # cap on either side of the canvas
    feather_px: int = 40  # distance from the frame edge over which feather weights ramp up
    exposure: bool = True  # per-frame gain compensation (live: running; re-render: global)
    flatfield: bool = True  # divide out the vignetting profile estimated from the frames
    sharpness_weighting: bool = True  # weight frames by local sharpness, glare, border distance
    side_bands: bool = True  # leave frame-fixed side bands without retina out of the mosaic
    denoise: bool = True  # shrink the mosaic's finest band where it is near the noise level
    # (local Wiener): the frames' noise that blending left, not the vessels' edges
    quality_threshold: float = 0.4  # a frame agreeing less with the mosaic under it (NCC of
    # band-passed green, mosaic.quality) is flagged in the report as likely misregistered


@dataclass(frozen=True)
class PipelineConfig:
    """Frame streaming, registration strategy and what to do when a frame does not register."""

    strategy: str = "keyframes"  # keyframes (accurate over long videos) | chain (the paper's)
    on_failure: str = "skip"  # stop (paper's protocol) | skip | restart (new mosaic segment)
    reanchor_after: int = 5  # skip: this many failures in a row against a mosaic of one frame
    # start it again from two later frames that register to each other (0: never)
    new_segment_after: int = 10  # skip: after this many failures in a row against a mosaic of
    # several frames, two later frames that register to each other start a new segment; the
    # first segment is still tried first, so the camera coming back continues it, and the
    # re-render joins the two where the frame that comes back registers to both (0: never)
    step: int = 1  # process every step-th frame
    max_frames: int = 0  # stop after this many processed frames; 0: whole video
    overlap: str = "auto"  # extract frame i+1 in a background thread while frame i registers:
    # on | off | auto (each way timed on the first frames and every 500, the fastest kept: serial,
    # and for a network on every core with or without turns (scheduling.OverlapTrial); same results)
    checkpoint_every_s: float = 30.0  # write the live mosaic and the report so far (summary.
    # complete = false) this often while streaming, so a killed run leaves them; 0: off


@dataclass(frozen=True)
class KeyframesConfig:
    """Keyframe strategy: register to keyframes, relocalise, close loops, refine globally."""

    min_overlap: float = 0.6  # promote a new keyframe when overlap with the active one drops below
    promote_min_inliers: int = 40  # ... or when a frame registers to it with fewer inliers
    promote_inlier_ratio: float = 0.4  # ... or with fewer than this x its best inlier count
    promote_coverage_ratio: float = 0.4  # ... or with an inlier coverage under this x its best
    max_keyframes: int = 200  # keyframes whose features stay in memory (oldest dropped first)
    relocalise_candidates: int = 4  # other keyframes tried before a frame is declared failed
    bridge_frames: int = 3  # the frames right after a promotion also register to ...
    bridge_keyframes: int = 2  # ... this many keyframes before the new one (pose-graph links
    # that tie consecutive keyframes through several frames: less drift; 0: off)
    loop_closure: bool = True  # match new keyframes against older overlapping ones too
    loop_min_overlap: float = 0.3  # predicted overlap that makes an old keyframe a loop candidate
    refine: bool = True  # pose-graph refinement of the keyframes at the end of the video
    tilt_step_px: float = 0.4  # pose graph: each view is a similarity times a tilt whose effect
    # at the frame corner changes about this much per frame, fitted to the links' inlier points
    # (0: free homographies fitted to each link's chosen model)
    rerender: bool = True  # re-read the video to render the mosaic from refined poses


@dataclass(frozen=True)
class GatingConfig:
    """Frames not worth registering: skipped and counted before detection."""

    enabled: bool = True
    min_sharpness_ratio: float = 0.3  # Laplacian variance below this x the recent median: blurred
    blurred: str = "track"  # a blurred frame is registered and keeps the chain, but is left out
    # of the blend (track), or skipped before detection (skip)
    min_fov_fraction: float = 0.15  # fraction of the frame inside the field of view


@dataclass(frozen=True)
class Config:
    """The whole run configuration, one attribute per TOML table."""

    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    compose: ComposeConfig = field(default_factory=ComposeConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    keyframes: KeyframesConfig = field(default_factory=KeyframesConfig)
    gating: GatingConfig = field(default_factory=GatingConfig)


CHOICES: dict[tuple[str, str], tuple[str, ...]] = {
    ("features", "descriptor"): ("rootsift", "native"),
    ("gating", "blurred"): ("track", "skip"),
    ("features", "device"): ("cpu", "cuda"),
    ("features", "precision"): ("float32", "bfloat16", "auto"),
    ("registration", "method"): (
        "ransac",
        "usac_default",
        "usac_magsac",
        "usac_accurate",
        "usac_fast",
    ),
    ("registration", "model"): (
        "auto",
        "translation",
        "similarity",
        "affine",
        "homography",
        "quadratic",
    ),
    ("compose", "blend"): ("feather", "average", "last", "multiband", "best"),
    ("compose", "resolution"): ("working", "full"),
    ("pipeline", "on_failure"): ("stop", "skip", "restart"),
    ("pipeline", "overlap"): ("auto", "on", "off"),
    ("pipeline", "strategy"): ("keyframes", "chain"),
}


@dataclass(frozen=True)
class Range:
    """The numbers a key accepts: between `low` and `high` (each bound included unless open),
    and also 0 when `off` (0 turns the feature off)."""

    low: float = 0.0
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    off: bool = False

    def __contains__(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        if self.off and value == 0:
            return True
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def __str__(self) -> str:
        low, high = _number(self.low), _number(self.high)
        if math.isinf(self.high):
            text = f"{'>' if self.low_open else '>='} {low}"
        else:
            opening, closing = "(" if self.low_open else "[", ")" if self.high_open else "]"
            text = f"in {opening}{low}, {high}{closing}"
        return f"0 (off) or {text}" if self.off else text


def _number(value: float) -> str:
    """A bound as a user writes it: 100000, not 1e+05; 0.0001, 0.1."""
    return str(int(value)) if float(value).is_integer() and abs(value) < 1e15 else f"{value:g}"


# Upper bounds follow from what each key sizes: a bound past which the code cannot run (OpenCV
# takes a C int; a kernel or canvas of that side does not fit in memory) or past which the value
# means nothing more (a window wider than any frame, a count longer than any video).
KEYPOINTS = 100_000  # keypoints of a frame, and so matches and inliers (SIFT gets twice this)
FRAMES = 1_000_000  # frames of a video: nine hours at 30 frames/s
KEYFRAMES = 10_000  # keyframes held (each ~0.5 MB of features at 1000 keypoints)
SIDE_PX = 32_768  # an image side: a canvas of this side takes more than 16 GB of buffers
MARGIN_PX = 100  # a margin grown around a mask (a disc of 201 px: ~0.2 s an 800x600 frame)
DESCRIPTOR_PX = 100  # a keypoint's diameter for the descriptor (detectors' own: 20 at most)

AT_LEAST_0 = Range()
FRACTION = Range(0, 1)  # [0, 1]
GREY_LEVEL = Range(0, 255)
FRAME_COUNT = Range(0, FRAMES)
#: The range of every numeric key (a test checks that each has one, and that the code runs at
#: each bound); a key missing here (a new one) gets `AT_LEAST_0`.
RANGES: dict[tuple[str, str], Range] = {
    # a clip at 256 x the mean histogram bin clips nothing (a bin holds at most 256 x the mean)
    ("preprocess", "clahe_clip_limit"): Range(0, 256, low_open=True),
    ("preprocess", "clahe_tile_grid"): Range(1, 64),
    ("preprocess", "bilateral_diameter_px"): Range(1, 31),
    # wider than the grey scale (or than the 31 px window): the filter is a plain blur
    ("preprocess", "bilateral_sigma_color"): Range(0, 1000, low_open=True),
    ("preprocess", "bilateral_sigma_space"): Range(0, 100, low_open=True),
    ("preprocess", "fov_threshold"): GREY_LEVEL,
    ("preprocess", "fov_erode_px"): Range(0, MARGIN_PX),
    ("preprocess", "overlay_max_range"): GREY_LEVEL,
    ("preprocess", "overlay_margin_px"): Range(0, MARGIN_PX),
    ("preprocess", "reflex_brightness"): Range(1, 255),
    ("preprocess", "max_side_px"): Range(64, SIDE_PX, off=True),
    ("preprocess", "fov_diameter_px"): Range(64, SIDE_PX, off=True),
    ("features", "max_keypoints"): Range(1, KEYPOINTS),
    ("features", "nms_window_px"): Range(1, 100),  # 100 px: ~50 keypoints in an 800x600 frame
    ("features", "score_threshold"): Range(0, 1, high_open=True),  # scores lie in [0, 1]
    ("features", "descriptor_size_px"): Range(1, DESCRIPTOR_PX),
    ("features", "photo_descriptor_size_px"): Range(1, DESCRIPTOR_PX),
    ("features", "detect_scale"): Range(0.1, 1),
    ("features", "extra_scale"): Range(0.1, 1, off=True),
    ("features", "border_margin_px"): Range(0, MARGIN_PX),
    ("matching", "ratio"): Range(0, 1, low_open=True),
    ("registration", "reproj_threshold_px"): Range(0, 100, low_open=True),
    ("registration", "max_iters"): Range(1, KEYPOINTS),  # OpenCV takes a C int
    # a probability: 1 would ask RANSAC for certainty
    ("registration", "confidence"): Range(0, 1, low_open=True, high_open=True),
    ("registration", "min_inliers"): Range(0, KEYPOINTS),
    # an sd in frame half-diagonals: 1 leaves the perspective free, 1e-4 (0.02 px at the
    # corners) holds it as 0 does; far smaller values overflow the prior's weight
    ("registration", "perspective_prior"): Range(1e-4, 1, off=True),
    ("registration", "refine_levels"): Range(0, 6),
    ("registration", "track_window_px"): Range(9, 61, off=True),
    ("compose", "max_canvas_px"): Range(64, SIDE_PX),
    ("compose", "feather_px"): Range(0, 1000),  # longer: every weight scaled alike
    ("compose", "quality_threshold"): FRACTION,
    ("pipeline", "step"): Range(1, FRAMES),
    ("pipeline", "reanchor_after"): FRAME_COUNT,
    ("pipeline", "new_segment_after"): FRAME_COUNT,
    ("pipeline", "max_frames"): FRAME_COUNT,
    ("pipeline", "checkpoint_every_s"): Range(0, 86_400),  # a day
    ("keyframes", "min_overlap"): FRACTION,
    ("keyframes", "promote_min_inliers"): Range(0, KEYPOINTS),
    ("keyframes", "promote_inlier_ratio"): FRACTION,
    ("keyframes", "promote_coverage_ratio"): FRACTION,
    ("keyframes", "max_keyframes"): Range(1, KEYFRAMES),
    ("keyframes", "relocalise_candidates"): Range(0, KEYFRAMES),
    ("keyframes", "bridge_frames"): FRAME_COUNT,
    ("keyframes", "bridge_keyframes"): Range(0, KEYFRAMES),
    ("keyframes", "loop_min_overlap"): FRACTION,
    # px per frame at the frame's corner: 0.01 holds the tilt, 100 leaves it free; far smaller
    # values overflow the smoothness weight
    ("keyframes", "tilt_step_px"): Range(0.01, 100, off=True),
    ("gating", "min_sharpness_ratio"): FRACTION,
    ("gating", "min_fov_fraction"): FRACTION,
}


def value_range(table: str, key: str) -> Range:
    """The range a numeric key accepts (`RANGES`, else >= 0)."""
    return RANGES.get((table, key), AT_LEAST_0)


def _check_value(table: str, key: str, value: Any, expected: type) -> Any:
    where = f"[{table}] {key}"
    numeric = expected in (int, float)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    choices = CHOICES.get((table, key))
    if (expected is not bool and isinstance(value, bool)) or not isinstance(value, expected):
        kind = {int: "an integer", float: "a number"}.get(expected, expected.__name__)
        if choices is not None:
            kind = f"one of {', '.join(choices)}"
        allowed = f" {value_range(table, key)}" if numeric else ""
        raise ConfigError(
            f"config {where} must be {kind}{allowed}, got {type(value).__name__} {value!r}"
        )
    if choices is not None and value not in choices:
        raise ConfigError(f"config {where} must be one of {', '.join(choices)}, got {value!r}")
    if numeric and value not in (allowed := value_range(table, key)):
        finite = "" if math.isfinite(value) else "a finite number "
        raise ConfigError(f"config {where} must be {finite}{allowed}, got {value!r}")
    return value


def _build_table(table: str, cls: type, raw: Any) -> Any:
    if not isinstance(raw, dict):
        raise ConfigError(f"config [{table}] must be a table")
    hints = get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    for key in raw:
        if key not in known:
            raise ConfigError(
                f"unknown config key [{table}] {key} (known: {', '.join(sorted(known))})"
            )
    values = {key: _check_value(table, key, value, hints[key]) for key, value in raw.items()}
    return cls(**values)


def config_from_dict(raw: dict[str, Any]) -> Config:
    """Validate a parsed TOML document into a `Config`; missing keys take their defaults."""
    tables = {f.name: f for f in fields(Config)}
    built = {}
    for table, value in raw.items():
        if table not in tables:
            raise ConfigError(f"unknown config table [{table}] (known: {', '.join(tables)})")
        built[table] = _build_table(table, get_type_hints(Config)[table], value)
    return Config(**built)


def load_config(path: str | Path | None) -> Config:
    """Read a TOML config file; `None` gives the defaults."""
    if path is None:
        return Config()
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read config file {path}: {exc}") from exc
    if not text.strip():
        raise ConfigError(f"config file {path} is empty")
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from exc
    return config_from_dict(raw)


def with_overrides(config: Config, **tables: dict[str, Any]) -> Config:
    """A copy of `config` with some keys replaced, validated like file values."""
    updated = {}
    for table, values in tables.items():
        current = dataclasses.asdict(getattr(config, table))
        current.update(values)
        updated[table] = _build_table(table, get_type_hints(Config)[table], current)
    return dataclasses.replace(config, **updated)


def for_photographs(config: Config) -> Config:
    """The configuration of photograph pairs: their sharp detail is described at
    `photo_descriptor_size_px`, where video frames need the wider `descriptor_size_px`."""
    size = config.features.photo_descriptor_size_px
    return with_overrides(config, features={"descriptor_size_px": size})


def config_to_dict(config: Config) -> dict[str, dict[str, Any]]:
    """Plain dict of the config, for reports and the viewer."""
    return dataclasses.asdict(config)
