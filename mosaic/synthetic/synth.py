"""Synthetic retinal videos with exact ground-truth homographies.

A virtual camera viewport moves over a still fundus image along a smooth random trajectory
(translation, rotation, zoom and a mild perspective tilt). Each frame is
`warpPerspective(source, inv(H_frame_to_source))`, so `H_frame_to_source` is the exact ground
truth. Optional nuisances (illumination drift, vignetting, blur, noise) and a dark elliptical
aperture make frames look like slit-lamp / fundus video; they are photometric only and never
move a pixel (every blur kernel is centred), so the ground truth stays exact.

Profiles: the defaults are a kind video; `SynthParams.hard()` adds loops, fast motion, blur
bursts and glare; `SynthParams.realistic()` imitates magnified slit-lamp / fundus video: the
frame spans a quarter to a half of the source's field of view (soft, upsampled texture where
vessels are the only structure), the path reaches the rim of the source's view, strong
vignetting, per-frame gain / gamma changes, noise, optics blur on every frame, motion blur
along the motion, bursts of blur, defocus and glare, 4-25 px of motion per frame.

Compression: `.mp4` is written by OpenCV's FFmpeg writer with the `mp4v` codec (MPEG-4 Part 2)
at its default bit rate. The OpenCV wheel has no software H.264 encoder (`avc1` / `H264` only
reach the absent V4L2 hardware encoder), so real videos' H.264 is not reproduced bit for bit;
what matters to registration is the loss, and on the realistic profile `mp4v` gives 32-33 dB
PSNR (rendered vs decoded frame, recorded in the ground truth as `psnr_db`; 31.1 dB the worst
frame seen). libx264 (PyAV 18.1, tried outside the project) gives 31.7-32.6 dB at CRF 18-28 on
frames with noise sigma 6, where `mp4v` gives 32.2 dB: at noise sigma 5-7 the loss is mostly
the noise the codec drops (4:2:0 chroma alone costs 32 dB), not the codec's own artefacts.

Used by the tests and benchmarks to measure registration error against the truth, and by users
(`write_synthetic_video`) to check the tool on a video whose answer is known.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mosaic.errors import ConfigError, InputError, OutputError
from mosaic.io import (
    IMAGE_READ_SUFFIXES,
    atomic_path,
    natural_key,
    open_frames,
    read_image,
    to_bgr8,
    write_image,
    write_json,
)
from mosaic.preprocess import estimate_fov_disc
from mosaic.synthetic.streams import (
    DUST,
    HARD_NUISANCE,
    NUISANCE,
    REAL_NUISANCE,
    REFLEX,
    RIM,
    smooth_signal,
    stream,
)
from mosaic.synthetic.trajectory import plan_trajectory
from mosaic.synthetic.truth import VIDEO_CODECS, gt_path_for, recorded_source

log = logging.getLogger(__name__)

_SOURCE_ORDER_SEED = 13  # fixed shuffle of a source folder (`pick_source`)

_APERTURE_LEVEL = 2.0  # grey level of the dark border outside the simulated aperture
_PSNR_MAX_FRAMES = 250  # frames kept in memory to measure the compression loss of a video file


@dataclass(frozen=True)
class SynthParams:
    """Parameters of a synthetic video. Geometry and nuisances use independent random streams,
    so switching `nuisances`/`aperture` off leaves the trajectory (the ground truth) unchanged."""

    n_frames: int = 60
    size: tuple[int, int] = (660, 350)  # (width, height) of a frame
    seed: int = 0
    max_step_px: float = 12.0  # mean motion of the viewport centre per frame, in frame pixels
    rotation_deg: float = 10.0  # range (max - min) of the in-plane rotation over the video
    scale_range: tuple[float, float] = (0.9, 1.1)  # range of the zoom (frame px per source px)
    perspective: float = 2e-5  # largest |h31|, |h32| in frame-centred coordinates (tilt)
    nuisances: bool = True  # illumination drift, vignetting, occasional blur, noise
    aperture: bool = True  # dark elliptical field-of-view border in every frame
    blur_prob: float = 0.05  # probability that a frame is motion- or defocus-blurred
    noise_sigma: float = 3.0  # std of the additive gaussian noise, grey levels
    fps: float = 25.0
    # Hard cases of real video (off by default; `hard()` turns them on):
    revisit: bool = False  # the second half of the path runs back beside the first (loops)
    fast_motion_prob: float = 0.0  # chance per frame of a burst of 3-5 faster steps
    blur_burst_prob: float = 0.0  # chance per frame that a burst of 3-6 strongly blurred starts
    glare_prob: float = 0.0  # chance per frame of a bright specular reflection
    fast_motion_factor: float = 4.0  # speed-up during such a burst
    # Realistic video (the defaults reproduce the videos above; `realistic()` sets them):
    fov_fraction: tuple[float, float] | None = None  # frame width / source FOV diameter, drawn
    #   per video in this range (None: frame px = source px, zoomed in only if the view is small)
    rim_overlap: float = 0.0  # how deep the source's FOV border comes into the frame, at one
    #   place of the path: share of the frame's half-height (0: never)
    speed_variation: float = 0.3  # relative amplitude of the smooth change of speed
    step_jitter: float = 0.0  # per-frame factor of the step length in 1 ± this (hand tremor)
    step_range_px: tuple[float, float] | None = None  # clip each frame's motion to this range
    gain_drift: float = 0.12  # amplitude of the smooth illumination change
    gain_jitter: float = 0.0  # per-frame independent gain factor in 1 ± this
    gamma_jitter: float = 0.0  # per-frame independent gamma in 1 ± this
    vignette: float = 0.18  # mean darkening at the frame corners (share of the light)
    vignette_variation: float = 0.12  # smooth change of the darkening along the video, ±
    optics_blur_px: float = 0.0  # gaussian sigma of the optics' blur, every frame
    noise_jitter: float = 0.0  # per-frame noise sigma in noise_sigma ± this
    motion_blur: float = 0.0  # exposure / frame interval: streak = this x motion at the centre
    defocus_burst_prob: float = 0.0  # chance per frame that a 3-8 frame defocus burst starts
    glare_burst_prob: float = 0.0  # chance per frame that a 3-8 frame drifting glare starts
    interlaced: bool = False  # odd rows from half a frame interval later (an analogue camera's
    #   second field); the ground truth is the even rows' pose
    lens_reflexes: int = 0  # bright, sharp-edged reflections of the fundus lens: they stay
    #   near one place of the frame (a few px of wander) while the retina moves under them
    dust_spots: int = 0  # out-of-focus dust on the sensor or lens: soft dark blobs fixed in the
    #   frame, which darken the light by 20-60 %
    lens_rim: bool = False  # a handheld fundus lens: the retina is seen only inside its rim, a
    #   disc that moves about the frame; outside, the face and lid, out of focus and lit
    haze_frames: int = 0  # the last N frames seen through haze (a veil of scattered light:
    #   contrast down to 25-55 %, lifted towards a bright grey, slightly blurred)

    @classmethod
    def hard(cls, **overrides: Any) -> SynthParams:
        """A video hard the way real ones are: loops, fast motion, blur bursts, glare."""
        defaults = dict(revisit=True, fast_motion_prob=0.03, blur_burst_prob=0.02, glare_prob=0.1)
        return cls(**{**defaults, **overrides})

    @classmethod
    def realistic(cls, **overrides: Any) -> SynthParams:
        """Looks like real magnified slit-lamp / fundus video (see the module docstring).

        The frame spans 25-45 % of the source's field of view, so a 500-1300 px fundus photo is
        upsampled 1.5-5x; the path touches the rim of the view (part of some frames black);
        4-25 px of motion per frame, varying, with faster stretches, a few degrees of rotation,
        ±5 % zoom; vignetting up to ~40 %, per-frame gain and gamma ±20 %, noise sigma 5-7,
        optics blur sigma 1 px, motion blur, bursts of blur, defocus and glare.
        """
        defaults = dict(
            fov_fraction=(0.25, 0.45),
            rim_overlap=0.4,
            max_step_px=10.0,
            speed_variation=0.6,
            step_jitter=0.3,
            fast_motion_prob=0.02,
            fast_motion_factor=2.2,
            step_range_px=(4.5, 24.0),
            rotation_deg=6.0,
            scale_range=(0.95, 1.05),
            perspective=3e-5,
            gain_drift=0.1,
            gain_jitter=0.1,
            gamma_jitter=0.2,
            vignette=0.32,
            vignette_variation=0.1,
            optics_blur_px=1.0,
            noise_sigma=6.0,
            noise_jitter=1.0,
            motion_blur=0.3,
            blur_prob=0.05,
            blur_burst_prob=0.015,
            defocus_burst_prob=0.02,
            glare_burst_prob=0.02,
            glare_prob=0.03,
        )
        return cls(**{**defaults, **overrides})

    @classmethod
    def realistic_fast(cls, **overrides: Any) -> SynthParams:
        """`realistic`, faster and more magnified: 4-45 px of motion a frame (16 px on average
        before the speed changes), the frame 20-40 % of the source's view (`mosaic synth
        --realistic --fast`; the set `fast45` of docs/evaluation.md)."""
        defaults = dict(max_step_px=16.0, step_range_px=(4.0, 45.0), fov_fraction=(0.2, 0.4))
        return cls.realistic(**{**defaults, **overrides})

    def __post_init__(self) -> None:
        w, h = self.size
        checks = [
            (self.n_frames >= 1, f"n_frames must be >= 1, got {self.n_frames}"),
            (self.haze_frames >= 0, f"haze_frames must be >= 0, got {self.haze_frames}"),
            (w >= 16 and h >= 16, f"size must be at least 16x16, got {w}x{h}"),
            (self.max_step_px >= 0, f"max_step_px must be >= 0, got {self.max_step_px}"),
            (self.rotation_deg >= 0, f"rotation_deg must be >= 0, got {self.rotation_deg}"),
            (
                0 < self.scale_range[0] <= self.scale_range[1],
                f"scale_range must satisfy 0 < low <= high, got {self.scale_range}",
            ),
            (self.perspective >= 0, f"perspective must be >= 0, got {self.perspective}"),
            (0 <= self.blur_prob <= 1, f"blur_prob must be in [0, 1], got {self.blur_prob}"),
            (self.noise_sigma >= 0, f"noise_sigma must be >= 0, got {self.noise_sigma}"),
            (self.lens_reflexes >= 0, f"lens_reflexes must be >= 0, got {self.lens_reflexes}"),
            (self.dust_spots >= 0, f"dust_spots must be >= 0, got {self.dust_spots}"),
            (self.fps > 0, f"fps must be > 0, got {self.fps}"),
            *(
                (0 <= p <= 1, f"{name} must be in [0, 1], got {p}")
                for name, p in (
                    ("fast_motion_prob", self.fast_motion_prob),
                    ("blur_burst_prob", self.blur_burst_prob),
                    ("glare_prob", self.glare_prob),
                    ("defocus_burst_prob", self.defocus_burst_prob),
                    ("glare_burst_prob", self.glare_burst_prob),
                    ("rim_overlap", self.rim_overlap),
                    ("gain_jitter", self.gain_jitter),
                    ("gamma_jitter", self.gamma_jitter),
                    ("vignette", self.vignette),
                )
            ),
            *(
                (v >= 0, f"{name} must be >= 0, got {v}")
                for name, v in (
                    ("fast_motion_factor", self.fast_motion_factor),
                    ("speed_variation", self.speed_variation),
                    ("step_jitter", self.step_jitter),
                    ("gain_drift", self.gain_drift),
                    ("vignette_variation", self.vignette_variation),
                    ("optics_blur_px", self.optics_blur_px),
                    ("noise_jitter", self.noise_jitter),
                    ("motion_blur", self.motion_blur),
                )
            ),
            *(
                (rng is None or 0 < rng[0] <= rng[1], f"{name} must satisfy 0 < low <= high")
                for name, rng in (
                    ("fov_fraction", self.fov_fraction),
                    ("step_range_px", self.step_range_px),
                )
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


def _aperture_mask(w: int, h: int) -> np.ndarray:
    """Soft elliptical field of view (1 inside, 0 outside), clipped at the top and bottom."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    a, b = 0.495 * w, 0.62 * h
    rho = np.sqrt(((xx - (w - 1) / 2) / a) ** 2 + ((yy - (h - 1) / 2) / b) ** 2)
    edge = 6.0 / min(a, b)  # soft edge about 6 px wide
    return np.clip((1.0 - rho) / edge + 0.5, 0.0, 1.0)


def _blur_kernel(rng: np.random.Generator) -> np.ndarray:
    """A centred motion (line) or defocus (disc) kernel: blurs without shifting the image."""
    size = int(rng.integers(2, 6)) * 2 + 1  # 5..11 px, odd so it is centred
    kernel = np.zeros((size, size), np.float32)
    mid = size // 2
    if rng.random() < 0.5:
        angle = rng.uniform(0, 180)
        kernel[mid, :] = 1.0
        rot = cv2.getRotationMatrix2D((float(mid), float(mid)), angle, 1.0)
        kernel = cv2.warpAffine(kernel, rot, (size, size))
    else:
        cv2.circle(kernel, (mid, mid), mid, 1.0, -1)
    return kernel / kernel.sum()


def _line_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """Motion-blur kernel: a line `length_px` long, centred (its centroid is the kernel centre)."""
    mid = int(np.ceil(length_px / 2)) + 1
    t = np.linspace(-length_px / 2, length_px / 2, int(np.ceil(4 * length_px)) + 2)
    x, y = mid + t * np.cos(angle_rad), mid + t * np.sin(angle_rad)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    kernel = np.zeros((2 * mid + 1, 2 * mid + 1))
    for dx, dy, weight in (
        (0, 0, (1 - fx) * (1 - fy)),
        (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy),
    ):  # bilinear splat of points placed symmetrically about the centre
        np.add.at(kernel, (y0 + dy, x0 + dx), weight)
    return (kernel / kernel.sum()).astype(np.float32)


def _disc_kernel(radius_px: float) -> np.ndarray:
    """Defocus kernel: a disc of `radius_px` (anti-aliased, 4x4 samples per pixel), centred."""
    mid, sub = int(np.ceil(radius_px)) + 1, 4
    size = 2 * mid + 1
    c = (np.arange(size * sub) + 0.5) / sub - 0.5 - mid  # sample offsets from the centre
    inside = (c[None, :] ** 2 + c[:, None] ** 2 <= radius_px**2).astype(np.float64)
    kernel = inside.reshape(size, sub, size, sub).mean(axis=(1, 3))
    return (kernel / kernel.sum()).astype(np.float32)


def _glare_blob(w: int, h: int, cx: float, cy: float, ax: float, ay: float) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.exp(-(((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2))


HAZE_VEIL = (0.6, 0.15)  # share of scattered light: mean, and amplitude of its frame-to-frame swing
HAZE_COLOUR = (170.0, 180.0, 200.0)  # BGR of the veil: bright, bluish grey
HAZE_BLUR_PX = 1.5


def _hazed(img: np.ndarray, i: int) -> np.ndarray:
    """The frame through haze: a veil of scattered light over a slightly blurred view."""
    veil = HAZE_VEIL[0] + HAZE_VEIL[1] * np.sin(i)
    blurred = cv2.GaussianBlur(img, (0, 0), HAZE_BLUR_PX)
    return blurred * (1.0 - veil) + veil * np.array(HAZE_COLOUR, np.float32)


def _add_glare(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A bright, saturating specular reflection (soft ellipse) somewhere in the frame."""
    h, w = img.shape[:2]
    cx, cy = rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.8) * h
    ax, ay = rng.uniform(0.05, 0.15) * w, rng.uniform(0.05, 0.2) * h
    blob = _glare_blob(w, h, cx, cy, ax, ay)
    return img + float(rng.uniform(120, 255)) * blob[..., None]


def _bursts(rng: np.random.Generator, n: int, prob: float) -> Iterator[tuple[int, np.ndarray]]:
    """(start, strength per frame) of each burst: 3-8 frames, strength a sine ramp up to 1."""
    i = 0
    while i < n:
        if rng.random() < prob:
            length = int(rng.integers(3, 9))
            yield i, np.sin(np.pi * (np.arange(length) + 0.5) / length)[: n - i]
            i += length
        else:
            i += 1


@dataclass(frozen=True)
class _LensReflexes:
    """Reflections of the fundus lens (own random stream): each an ellipse of 4-16 px semi-axes
    with a flat top and a steep edge (a super-Gaussian, the lens surface's mirror image of the
    lamp), 100-220 grey levels bright with a flicker of ±15 %, wandering smoothly by up to 6 px:
    the lens moves a little, the retina much more."""

    centres: np.ndarray  # (n, k, 2) frame px
    axes: np.ndarray  # (k, 2) semi-axes, px
    brightness: np.ndarray  # (n, k) grey levels

    @classmethod
    def draw(cls, params: SynthParams) -> _LensReflexes | None:
        k, n, (w, h) = params.lens_reflexes, params.n_frames, params.size
        if k <= 0:
            return None
        rng = stream(params.seed, REFLEX)
        t = np.linspace(0.0, 1.0, n)
        home = rng.uniform(0.25, 0.75, (k, 2)) * [w, h]
        axes = rng.uniform(4.0, 16.0, (k, 2))
        peak = rng.uniform(100.0, 220.0, k)
        wander = 6.0 * np.array([[smooth_signal(rng, t) for _ in range(2)] for _ in range(k)])
        flicker = 1.0 + rng.uniform(-0.15, 0.15, (n, k))
        return cls(home[None] + wander.transpose(2, 0, 1), axes, peak * flicker)

    def image(self, i: int, w: int, h: int) -> np.ndarray:
        """Grey levels the reflexes add to frame i, (h, w) float32."""
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        total = np.zeros((h, w), np.float32)
        for (cx, cy), (ax, ay), peak in zip(
            self.centres[i], self.axes, self.brightness[i], strict=True
        ):
            r2 = ((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2
            total += np.float32(peak) * np.exp(-(r2**2))
        return total


def _dust(params: SynthParams) -> np.ndarray | None:
    """(h, w, 1) share of the light that passes the dust (own random stream), or None: each
    spot a Gaussian of 4-14 px sd that takes 20-60 % of the light at its centre."""
    if params.dust_spots <= 0:
        return None
    (w, h), k = params.size, params.dust_spots
    rng = stream(params.seed, DUST)
    centres = rng.uniform(0.15, 0.85, (k, 2)) * [w, h]
    sd, depth = rng.uniform(4.0, 14.0, k), rng.uniform(0.2, 0.6, k)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    passed = np.ones((h, w), np.float32)
    for (cx, cy), s, d in zip(centres, sd, depth, strict=True):
        passed *= 1.0 - d * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    return passed[..., None]


@dataclass(frozen=True)
class _LensRim:
    """A handheld lens's rim (own random stream): the retina shows inside a disc of 0.45-0.6 of
    the frame's height in radius whose centre wanders smoothly over ±15 % of the frame; outside
    it the face and lid, out of focus (a smooth random field of 60-160 grey levels) that drifts
    a little."""

    centres: np.ndarray  # (n, 2) frame px
    radius: float
    surround: np.ndarray  # (h + 2 * pad, w + 2 * pad, 3) float32
    drift: np.ndarray  # (n, 2) px the surround has moved
    PAD = 16

    @classmethod
    def draw(cls, params: SynthParams) -> _LensRim | None:
        if not params.lens_rim:
            return None
        n, (w, h) = params.n_frames, params.size
        rng = stream(params.seed, RIM)
        t = np.linspace(0.0, 1.0, n)
        wander = np.stack([smooth_signal(rng, t) * 0.15 * w, smooth_signal(rng, t) * 0.15 * h], 1)
        centres = np.array([(w - 1) / 2, (h - 1) / 2]) + wander
        radius = float(rng.uniform(0.45, 0.6) * h)
        p = cls.PAD
        field = rng.uniform(0.0, 1.0, (h + 2 * p, w + 2 * p)).astype(np.float32)
        field = cv2.GaussianBlur(field, (0, 0), 25.0)
        field = (field - field.min()) / max(float(np.ptp(field)), 1e-6)
        skin = np.array([0.55, 0.7, 1.0], np.float32)  # B, G, R: a lit face is reddish
        surround = (60.0 + 100.0 * field)[..., None] * skin
        drift = np.stack([smooth_signal(rng, t) * 0.5 * p, smooth_signal(rng, t) * 0.5 * p], 1)
        return cls(centres, radius, surround, drift)

    def apply(self, img: np.ndarray, i: int) -> np.ndarray:
        """Frame i's retina inside the rim, the surround outside (a soft 4 px edge)."""
        h, w = img.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        (cx, cy), (dx, dy), p = self.centres[i], self.drift[i], self.PAD
        rho = np.hypot(xx - cx, yy - cy)
        inside = np.clip((self.radius - rho) / 4.0 + 0.5, 0.0, 1.0)[..., None]
        x0, y0 = round(p + dx), round(p + dy)
        return img * inside + self.surround[y0 : y0 + h, x0 : x0 + w] * (1.0 - inside)


def lens_rim_truth(params: SynthParams) -> tuple[np.ndarray, float] | None:
    """Where `lens_rim` puts the lens's rim: its centre in each frame ((n, 2) frame px) and its
    radius (px); None for a video without it. For checking a rim finder against the truth."""
    rim = _LensRim.draw(params)
    return None if rim is None else (rim.centres.copy(), rim.radius)


@dataclass(frozen=True)
class _RealisticNuisances:
    """Per-frame draws of the realistic profile's nuisances (independent stream)."""

    gain: np.ndarray  # (n,) per-frame gain factor
    gamma: np.ndarray  # (n,)
    noise_sigma: np.ndarray  # (n,) grey levels
    streak: np.ndarray  # (n, 2) motion-blur length (px) and angle (rad)
    defocus_px: np.ndarray  # (n,) disc radius, 0 = sharp
    glare: list[tuple[float, float, float, float, float] | None]  # cx, cy, ax, ay, amplitude

    @classmethod
    def draw(cls, params: SynthParams, H_all: np.ndarray) -> _RealisticNuisances:
        n, (w, h) = params.n_frames, params.size
        rng = stream(params.seed, REAL_NUISANCE)
        gain = 1.0 + rng.uniform(-params.gain_jitter, params.gain_jitter, n)
        gamma = 1.0 + rng.uniform(-params.gamma_jitter, params.gamma_jitter, n)
        noise = params.noise_sigma + rng.uniform(-params.noise_jitter, params.noise_jitter, n)
        defocus = np.zeros(n)
        for start, ramp in _bursts(rng, n, params.defocus_burst_prob):
            defocus[start : start + ramp.size] = rng.uniform(2.5, 6.0) * ramp
        glare: list[tuple[float, float, float, float, float] | None] = [None] * n
        for start, ramp in _bursts(rng, n, params.glare_burst_prob):
            (x0, x1), (y0, y1) = rng.uniform(0.15, 0.85, (2, 2)) * [[w], [h]]
            ax, ay = rng.uniform(0.08, 0.25) * w, rng.uniform(0.1, 0.3) * h
            peak = rng.uniform(80, 200)
            for k, strength in enumerate(ramp):  # drifts across the frame, brightest mid-burst
                f = k / max(ramp.size - 1, 1)
                x, y = x0 + f * (x1 - x0), y0 + f * (y1 - y0)
                glare[start + k] = (float(x), float(y), ax, ay, float(peak * strength))
        # Image motion at the frame centre (frame px per frame), from the neighbours' centres.
        centre = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
        velocity = np.zeros((n, 2))
        if n > 1:
            in_source = H_all @ centre
            nxt = np.einsum("nij,nj->ni", np.linalg.inv(H_all[:-1]), in_source[1:])
            step = nxt[:, :2] / nxt[:, 2:] - centre[:2]  # frame i+1's centre seen in frame i
            velocity[:-1] += step / 2
            velocity[1:] += step / 2
            velocity[[0, -1]] *= 2
        length = params.motion_blur * np.linalg.norm(velocity, axis=1)
        streak = np.stack([length, np.arctan2(velocity[:, 1], velocity[:, 0])], 1)
        return cls(gain, gamma, np.maximum(noise, 0.0), streak, defocus, glare)


@dataclass(frozen=True)
class _Illumination:
    """The light a frame gets: a drifting gain, a colour tint and a vignette whose strength
    and centre wander (smooth signals over the video)."""

    gain: np.ndarray  # (n,)
    tint: np.ndarray  # (n, 3)
    vignette: np.ndarray  # (n,) darkening at the frame's corners
    centre: np.ndarray  # (n, 2) the vignette's centre, px from the frame centre
    xx: np.ndarray  # (h, w) float32 px from the frame centre
    yy: np.ndarray
    r2_scale: float  # 1 / the squared half-diagonal

    @classmethod
    def draw(cls, rng: np.random.Generator, t: np.ndarray, params: SynthParams) -> _Illumination:
        w, h = params.size
        gain = 1.0 + params.gain_drift * smooth_signal(rng, t)
        tint = 1.0 + 0.04 * np.stack([smooth_signal(rng, t) for _ in range(3)], 1)
        vignette = params.vignette + params.vignette_variation * smooth_signal(rng, t)
        centre = np.stack([smooth_signal(rng, t) * 0.15 * w, smooth_signal(rng, t) * 0.15 * h], 1)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        xx -= (w - 1) / 2
        yy -= (h - 1) / 2
        return cls(gain, tint, vignette, centre, xx, yy, 1.0 / ((w / 2) ** 2 + (h / 2) ** 2))

    def factor(self, i: int, real_gain: float) -> np.ndarray:
        """(h, w, 3) factor of frame i's light (`real_gain`: the realistic video's own gain)."""
        r2 = (self.xx - self.centre[i, 0]) ** 2 + (self.yy - self.centre[i, 1]) ** 2
        light = self.gain[i] * real_gain * (1.0 - self.vignette[i] * (r2 * self.r2_scale))
        return light[..., None] * self.tint[i].astype(np.float32)


def _optical_blur(
    frame: np.ndarray, optics_px: float, streak: np.ndarray, defocus_px: float
) -> np.ndarray:
    """Optics, motion (a `streak` of (length, angle)) and defocus blur the scene before the
    sensor (float32)."""
    img = frame.astype(np.float32)
    if optics_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), optics_px)
    length, angle = streak
    if length >= 1.0:
        img = cv2.filter2D(img, -1, _line_kernel(length, angle))
    if defocus_px >= 0.5:
        img = cv2.filter2D(img, -1, _disc_kernel(defocus_px))
    return img


def render_frames(
    source: np.ndarray, params: SynthParams
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield (frame BGR uint8 (h, w, 3), H_frame_to_source 3x3) for each frame of the video."""
    source = to_bgr8(source)
    w, h = params.size
    H_all = plan_trajectory(source, params)
    rng = stream(params.seed, NUISANCE)
    t = np.linspace(0.0, 1.0, params.n_frames)
    aperture = _aperture_mask(w, h)[..., None] if params.aperture else None
    hard_rng = stream(params.seed, HARD_NUISANCE)
    real = _RealisticNuisances.draw(params, H_all)
    reflexes = _LensReflexes.draw(params)
    dust = _dust(params)
    rim = _LensRim.draw(params)
    burst_left = 0
    light = _Illumination.draw(rng, t, params) if params.nuisances else None

    def view(H_frame_to_source: np.ndarray) -> np.ndarray:
        return cv2.warpPerspective(
            source,
            np.linalg.inv(H_frame_to_source),
            (w, h),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(0, 0, 0),
        )

    def blurred(frame: np.ndarray, i: int) -> np.ndarray:
        return _optical_blur(frame, params.optics_blur_px, real.streak[i], real.defocus_px[i])

    for i, H_frame_to_source in enumerate(H_all):
        frame = view(H_frame_to_source)
        second = None  # the second field's view, half a frame interval later
        if params.interlaced and i + 1 < len(H_all):
            second = view((H_frame_to_source + H_all[i + 1]) / 2)
        if not params.nuisances and aperture is None:
            if second is not None:
                frame[1::2] = second[1::2]
            yield frame, H_frame_to_source
            continue
        img = blurred(frame, i) if params.nuisances else frame.astype(np.float32)
        if second is not None:  # the sensor reads the odd rows from the second field
            img[1::2] = (blurred(second, i) if params.nuisances else second)[1::2]
        if light is not None:
            img *= light.factor(i, real.gain[i])
        if rim is not None:
            img = rim.apply(img, i)
        if dust is not None:
            img *= dust
        if aperture is not None:
            img = img * aperture + _APERTURE_LEVEL * (1.0 - aperture)
        if params.nuisances:
            if burst_left == 0 and hard_rng.random() < params.blur_burst_prob:
                burst_left = int(hard_rng.integers(3, 7))
            if burst_left > 0:
                burst_left -= 1
                sigma = float(hard_rng.uniform(3.0, 6.0))
                img = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
            elif rng.random() < params.blur_prob:
                img = cv2.filter2D(img, -1, _blur_kernel(rng), borderType=cv2.BORDER_REFLECT)
            if hard_rng.random() < params.glare_prob:
                img = _add_glare(img, hard_rng)
            if real.glare[i] is not None:
                *blob, amplitude = real.glare[i]
                img = img + amplitude * _glare_blob(w, h, *blob)[..., None]
            if reflexes is not None:
                img = img + reflexes.image(i, w, h)[..., None]
            if params.gamma_jitter > 0:
                img = 255.0 * (np.clip(img, 0.0, 255.0) / 255.0) ** float(real.gamma[i])
            if i >= params.n_frames - params.haze_frames:
                img = _hazed(img, i)
            if real.noise_sigma[i] > 0:
                img += rng.normal(0.0, real.noise_sigma[i], img.shape).astype(np.float32)
        yield np.clip(img + 0.5, 0, 255).astype(np.uint8), H_frame_to_source


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def pick_source(path: str | Path, seed: int) -> Path:
    """The source image of a video: `path` itself, or, for a folder of fundus images, the one
    the seed picks: the images in natural order, shuffled by a fixed permutation, taken at
    `seed mod count`, so the same seed gives the same image and consecutive seeds different
    ones (a loop over seeds renders a set from as many photographs as it has videos)."""
    p = Path(path).expanduser()
    if not p.is_dir():
        return p
    images = sorted(
        (f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_READ_SUFFIXES),
        key=lambda f: natural_key(f.name),
    )
    if not images:
        kinds = ", ".join(sorted(s.lstrip(".") for s in IMAGE_READ_SUFFIXES))
        raise InputError(f"folder has no source images ({kinds}): {p}")
    order = np.random.default_rng(_SOURCE_ORDER_SEED).permutation(len(images))
    return images[int(order[seed % len(images)])]


def _psnr_db(rendered: list[np.ndarray], video: Path) -> dict[str, Any]:
    """PSNR (dB) of each decoded frame of `video` against the frame as rendered."""
    values = []
    with open_frames(video, max_frames=len(rendered)) as frames:
        for frame, original in zip(frames, rendered, strict=False):
            if frame.image is None:
                continue
            mse = np.mean((frame.image.astype(np.float64) - original) ** 2)
            values.append(float(10 * np.log10(255.0**2 / max(mse, 1e-10))))
    if not values:
        raise OutputError(f"cannot decode the video just written: {video}")
    return {"mean": float(np.mean(values)), "min": float(np.min(values)), "frames": len(values)}


def _frame_folder(out: Path) -> None:
    """Create the frame folder `out`, or accept an existing one without images: synth never
    deletes or overwrites files it did not write (a folder of frames is a video to `build`)."""
    try:
        out.mkdir(exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create folder {out}: {exc.strerror or exc}") from exc
    images = sorted(f.name for f in out.iterdir() if f.suffix.lower() in IMAGE_READ_SUFFIXES)
    if images:
        raise OutputError(
            f"output folder {out} already holds images ({images[0]}, ...): "
            "choose a new or empty folder"
        )


def write_synthetic_video(
    source_path: str | Path,
    out_path: str | Path,
    params: SynthParams,
    edit_source: Callable[[np.ndarray, SynthParams], tuple[np.ndarray, dict[str, Any]]]
    | None = None,
) -> Path:
    """Render a synthetic video from a fundus image and write it with its ground truth.

    `source_path` is an image, or a folder of them: then `pick_source` chooses one by the seed,
    and the ground truth's `source` names the image used. `out_path` ending in .mp4 (codec
    mp4v) or .avi (MJPG) gives a video file, whose compression loss against the rendered frames
    is measured (`psnr_db`: mean, min over the first 250 frames); a path without suffix gives a
    folder of PNG frames `frame_0000.png`, ... (lossless; a new folder or one without images).
    Every file is written atomically. Returns the ground-truth path. `edit_source` changes the
    source before rendering (a follow-up visit's planted changes, `mosaic.synthetic.followup`)
    and gives entries added to the ground truth.
    """
    source_path = pick_source(source_path, params.seed)
    source = read_image(source_path)
    edits: dict[str, Any] = {}
    if edit_source is not None:
        source, edits = edit_source(source, params)
    out = Path(out_path).expanduser()
    if not out.parent.is_dir():
        raise OutputError(f"output folder does not exist: {out.parent}")
    suffix = out.suffix.lower()
    as_folder = out.is_dir() or suffix == ""
    if not as_folder and suffix not in VIDEO_CODECS:
        raise OutputError(
            f"unsupported video format '{out.suffix}' (use .mp4, .avi or a folder): {out}"
        )
    w, h = params.size
    with ExitStack() as stack:
        writer = None
        if as_folder:
            _frame_folder(out)
        else:  # written beside it, renamed when whole: never half a video under its name
            tmp = stack.enter_context(atomic_path(out))
            fourcc = cv2.VideoWriter.fourcc(*VIDEO_CODECS[suffix])
            writer = cv2.VideoWriter(str(tmp), fourcc, params.fps, (w, h))
            if not writer.isOpened():
                raise OutputError(f"cannot open video writer for {out}")
        frames_gt = []
        rendered: list[np.ndarray] = []  # kept to measure the compression loss
        try:
            for i, (frame, H) in enumerate(render_frames(source, params)):
                if writer is not None:
                    writer.write(frame)
                    if i < _PSNR_MAX_FRAMES:
                        rendered.append(frame)
                else:
                    write_image(out / f"frame_{i:04d}.png", frame)
                frames_gt.append({"index": i, "H_frame_to_source": H})
        finally:
            if writer is not None:
                writer.release()
        if writer is not None and (not tmp.is_file() or tmp.stat().st_size == 0):
            raise OutputError(f"video writer produced no file: {out}")
        compression = (
            {"codec": VIDEO_CODECS[suffix], "psnr_db": _psnr_db(rendered, tmp)}
            if writer is not None
            else {"codec": "png"}
        )

    gt = {
        **recorded_source(source_path, gt_path_for(out)),
        "video": out.name,
        "size": [w, h],
        "fps": params.fps,
        "seed": params.seed,
        "params": dataclasses.asdict(params),
        **compression,
        **edits,
        "frames": frames_gt,
    }
    gt_path = write_json(gt_path_for(out), gt)
    log.info("wrote synthetic video %s (%d frames) and %s", out, len(frames_gt), gt_path)
    return gt_path


__all__ = [
    "SynthParams",
    "estimate_fov_disc",
    "lens_rim_truth",
    "pick_source",
    "render_frames",
    "write_synthetic_video",
]
