"""Synthetic retinal videos with exact ground-truth homographies.

A virtual camera viewport moves over a still fundus image along a smooth random trajectory
(translation, rotation, zoom and a mild perspective tilt). Each frame is
`warpPerspective(source, inv(H_frame_to_source))`, so `H_frame_to_source` is the exact ground
truth. Optional nuisances (illumination drift, vignetting, blur, noise) and a dark elliptical
aperture make frames look like slit-lamp / fundus video; they are photometric only and never
move a pixel, so the ground truth stays exact.

Used by the tests and benchmarks to measure registration error against the truth, and by users
(`write_synthetic_video`) to check the tool on a video whose answer is known.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mosaic.errors import ConfigError, InputError, OutputError
from mosaic.io import read_image, to_bgr8, write_json

log = logging.getLogger(__name__)

_FOV_THRESHOLD = 15  # grey level separating a fundus image's black border from the retina
_APERTURE_LEVEL = 2.0  # grey level of the dark border outside the simulated aperture
_VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG"}


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
    fast_motion_prob: float = 0.0  # chance per frame of a burst of 3-5 steps at 4x speed
    blur_burst_prob: float = 0.0  # chance per frame that a burst of 3-6 strongly blurred starts
    glare_prob: float = 0.0  # chance per frame of a bright specular reflection

    @classmethod
    def hard(cls, **overrides: Any) -> SynthParams:
        """A video hard the way real ones are: loops, fast motion, blur bursts, glare."""
        defaults = dict(revisit=True, fast_motion_prob=0.03, blur_burst_prob=0.02, glare_prob=0.1)
        return cls(**{**defaults, **overrides})

    def __post_init__(self) -> None:
        w, h = self.size
        checks = [
            (self.n_frames >= 1, f"n_frames must be >= 1, got {self.n_frames}"),
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
            (self.fps > 0, f"fps must be > 0, got {self.fps}"),
            *(
                (0 <= p <= 1, f"{name} must be in [0, 1], got {p}")
                for name, p in (
                    ("fast_motion_prob", self.fast_motion_prob),
                    ("blur_burst_prob", self.blur_burst_prob),
                    ("glare_prob", self.glare_prob),
                )
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)


# --------------------------------------------------------------------------------------------
# Source field of view and trajectory
# --------------------------------------------------------------------------------------------


def estimate_fov_disc(source: np.ndarray) -> tuple[float, float, float]:
    """Largest disc (cx, cy, r) inside the illuminated field of view of a fundus image.

    The black border is found by thresholding; holes (dark lesions, vessels) are filled, and the
    maximum of the distance transform gives the largest inscribed disc — also correct for fundus
    images whose circular view is clipped at the top and bottom.
    """
    gray = source if source.ndim == 2 else cv2.cvtColor(source, cv2.COLOR_BGR2GRAY)
    mask = (cv2.GaussianBlur(gray, (0, 0), 2.0) > _FOV_THRESHOLD).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(1 - mask, connectivity=4)
    h, w = mask.shape
    x0, y0 = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    x1, y1 = x0 + stats[:, cv2.CC_STAT_WIDTH], y0 + stats[:, cv2.CC_STAT_HEIGHT]
    is_hole = (x0 > 0) & (y0 > 0) & (x1 < w) & (y1 < h)
    is_hole[0] = False  # label 0: the bright region itself
    mask[is_hole[labels]] = 1
    # Zero padding so the image border also counts as outside the view.
    dist = cv2.distanceTransform(np.pad(mask, 1), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    iy, ix = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return float(ix - 1), float(iy - 1), float(dist[iy, ix])


def _smooth_signal(rng: np.random.Generator, t: np.ndarray, n_terms: int = 3) -> np.ndarray:
    """Random sum of low-frequency sinusoids of t in [0, 1], rescaled to span exactly [-1, 1]."""
    if t.size < 2:
        return np.zeros_like(t)
    freqs = rng.uniform(0.3, 1.6, n_terms) * np.arange(1, n_terms + 1)
    amps = rng.uniform(0.5, 1.0, n_terms) / np.arange(1, n_terms + 1)
    phases = rng.uniform(0, 2 * np.pi, n_terms)
    sig = (amps * np.sin(2 * np.pi * t[:, None] * freqs + phases)).sum(axis=1)
    lo, hi = sig.min(), sig.max()
    return (2 * sig - (lo + hi)) / max(hi - lo, 1e-12)


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1]], dtype=np.float64)


def _centre_path(rng: np.random.Generator, steps: np.ndarray, radius: float) -> np.ndarray:
    """Smooth curve inside a disc of `radius`, sampled at arc lengths cumsum(steps): (N, 2).

    The curve is a random quasi-periodic sum of sinusoids normalised into the disc, then
    re-parametrised by arc length so the per-frame displacement follows `steps` exactly.
    """
    targets = np.concatenate([[0.0], np.cumsum(steps)])
    if radius <= 0 or targets[-1] <= 0:
        return np.zeros((targets.size, 2))
    n_terms = 3
    freqs = rng.uniform(0.4, 1.2, (2, n_terms)) * np.arange(1, n_terms + 1)
    amps = rng.uniform(0.5, 1.0, (2, n_terms)) / np.arange(1, n_terms + 1)
    phases = rng.uniform(0, 2 * np.pi, (2, n_terms))
    span = 1.0
    for _ in range(60):
        n_dense = int(4096 * span) + 1
        t = np.linspace(0.0, span, n_dense)
        waves = np.sin(2 * np.pi * t[None, :, None] * freqs[:, None, :] + phases[:, None, :])
        xy = (amps[:, None, :] * waves).sum(axis=2).T  # (n_dense, 2)
        xy -= xy.mean(axis=0)
        xy *= radius / np.linalg.norm(xy, axis=1).max()
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        if arc[-1] >= targets[-1]:
            break
        span *= 1.5 * targets[-1] / max(arc[-1], 1e-9)
    else:  # pragma: no cover - the curve length grows with its span
        raise RuntimeError("could not build a long enough camera path")
    return np.stack([np.interp(targets, arc, xy[:, 0]), np.interp(targets, arc, xy[:, 1])], 1)


def plan_trajectory(source: np.ndarray, params: SynthParams) -> np.ndarray:
    """Ground truth `H_frame_to_source` (N, 3, 3) of a smooth path inside the source's view.

    H = T(centre) @ R(angle) @ S(scale) @ P(tilt) @ T(-frame centre). Every frame corner lies in
    the inscribed disc of the source's field of view (minus a margin), so no frame shows the
    source's black border. If the viewport is too large for the source, the whole video is
    zoomed in uniformly (logged).
    """
    n = params.n_frames
    w, h = params.size
    cx, cy, r_fov = estimate_fov_disc(source)
    margin = max(4.0, 0.02 * r_fov)
    rng = np.random.default_rng(np.random.SeedSequence(params.seed).spawn(2)[0])
    t = np.linspace(0.0, 1.0, n)
    angle = np.deg2rad(params.rotation_deg) / 2 * _smooth_signal(rng, t)
    lo, hi = np.log(params.scale_range[0]), np.log(params.scale_range[1])
    zoom = np.exp((lo + hi) / 2 + (hi - lo) / 2 * _smooth_signal(rng, t))
    tilt = params.perspective * np.stack([_smooth_signal(rng, t), _smooth_signal(rng, t)], 1)
    speed = 1.0 + 0.3 * _smooth_signal(rng, t[:-1]) if n > 2 else np.ones(max(n - 1, 0))

    # Frame-to-source map without the final translation: A = R S P T(-frame centre).
    c, s = np.cos(angle), np.sin(angle)
    A = np.zeros((n, 3, 3))
    A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1] = c, -s, s, c
    A[:, :2, :2] /= zoom[:, None, None]
    A[:, 2, 2] = 1.0
    P = np.tile(np.eye(3), (n, 1, 1))
    P[:, 2, :2] = tilt
    A = A @ P @ _translation(-(w - 1) / 2, -(h - 1) / 2)
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
    mapped = corners @ A.transpose(0, 2, 1)
    reach = float(np.linalg.norm(mapped[..., :2] / mapped[..., 2:], axis=-1).max())

    base = 1.0  # source px per frame px at zoom 1; < 1 zooms in when the source is too small
    usable = 0.65 * (r_fov - margin)  # at most this much of the radius for the viewport
    if usable <= 1.0:
        raise InputError(f"source image field of view too small (radius {r_fov:.0f} px)")
    if reach > usable:
        base = usable / reach
        log.info("viewport %dx%d too large for the source's view: zooming in x%.2f", w, h, 1 / base)
    A[:, :2, :] *= base  # scales the mapped x, y (not w) of every point by `base`
    reach *= base

    # Centre motion in source px: frame-px speed times the frame's source-px-per-frame-px.
    steps = params.max_step_px * speed / speed.mean() if n > 1 else np.zeros(0)
    hard_rng = np.random.default_rng(np.random.SeedSequence(params.seed).spawn(3)[2])
    if params.fast_motion_prob > 0 and n > 1:
        starts = np.flatnonzero(hard_rng.random(n - 1) < params.fast_motion_prob)
        for start in starts:
            steps[start : start + int(hard_rng.integers(3, 6))] *= 4.0
    steps = steps * base / np.sqrt(zoom[:-1] * zoom[1:]) if n > 1 else steps
    radius = r_fov - margin - reach
    if params.revisit and n > 3:
        # Out along the first half of the path, back along it shifted sideways by a third of
        # the frame height: the way back overlaps the way out only partly.
        half = (n + 1) // 2
        out_path = _centre_path(rng, steps[: half - 1], radius)
        direction = np.gradient(out_path, axis=0)
        normal = np.stack([-direction[:, 1], direction[:, 0]], 1)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
        offset = normal * (h / 3) * base
        back = (out_path + offset)[::-1][: n - half]
        path = np.concatenate([out_path, back])
        path *= min(1.0, radius / max(np.linalg.norm(path, axis=1).max(), 1e-9))
    else:
        path = _centre_path(rng, steps, radius)
    H = _translation(cx, cy)[None] @ np.tile(np.eye(3), (n, 1, 1))
    H[:, :2, 2] += path
    H = H @ A
    return H / H[:, 2:3, 2:3]


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


def _add_glare(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A bright, saturating specular reflection (soft ellipse) somewhere in the frame."""
    h, w = img.shape[:2]
    cx, cy = rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.8) * h
    ax, ay = rng.uniform(0.05, 0.15) * w, rng.uniform(0.05, 0.2) * h
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    blob = np.exp(-(((xx - cx) / ax) ** 2 + ((yy - cy) / ay) ** 2))
    return img + float(rng.uniform(120, 255)) * blob[..., None]


def render_frames(
    source: np.ndarray, params: SynthParams
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield (frame BGR uint8 (h, w, 3), H_frame_to_source 3x3) for each frame of the video."""
    source = to_bgr8(source)
    w, h = params.size
    H_all = plan_trajectory(source, params)
    rng = np.random.default_rng(np.random.SeedSequence(params.seed).spawn(2)[1])
    t = np.linspace(0.0, 1.0, params.n_frames)
    aperture = _aperture_mask(w, h)[..., None] if params.aperture else None
    hard_rng = np.random.default_rng(np.random.SeedSequence(params.seed).spawn(4)[3])
    burst_left = 0
    if params.nuisances:
        gain = 1.0 + 0.12 * _smooth_signal(rng, t)
        tint = 1.0 + 0.04 * np.stack([_smooth_signal(rng, t) for _ in range(3)], 1)
        vignette = 0.18 + 0.12 * _smooth_signal(rng, t)
        vig_centre = np.stack(
            [_smooth_signal(rng, t) * 0.15 * w, _smooth_signal(rng, t) * 0.15 * h], 1
        )
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        xx -= (w - 1) / 2
        yy -= (h - 1) / 2
        r2_scale = 1.0 / ((w / 2) ** 2 + (h / 2) ** 2)

    for i, H_frame_to_source in enumerate(H_all):
        frame = cv2.warpPerspective(
            source,
            np.linalg.inv(H_frame_to_source),
            (w, h),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(0, 0, 0),
        )
        if not params.nuisances and aperture is None:
            yield frame, H_frame_to_source
            continue
        img = frame.astype(np.float32)
        if params.nuisances:
            r2 = ((xx - vig_centre[i, 0]) ** 2 + (yy - vig_centre[i, 1]) ** 2) * r2_scale
            light = gain[i] * (1.0 - vignette[i] * r2)
            img *= light[..., None] * tint[i].astype(np.float32)
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
            if params.noise_sigma > 0:
                img += rng.normal(0.0, params.noise_sigma, img.shape).astype(np.float32)
        yield np.clip(img + 0.5, 0, 255).astype(np.uint8), H_frame_to_source


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def gt_path_for(video_path: str | Path) -> Path:
    """Ground-truth file of a synthetic video: `<video without suffix>.gt.json` beside it."""
    p = Path(video_path).expanduser()
    stem = p.name if p.is_dir() or p.suffix.lower() not in _VIDEO_CODECS else p.stem
    return p.with_name(stem + ".gt.json")


def write_synthetic_video(
    source_path: str | Path, out_path: str | Path, params: SynthParams
) -> Path:
    """Render a synthetic video from a fundus image and write it with its ground truth.

    `out_path` ending in .mp4 (codec mp4v) or .avi (MJPG) gives a video file; a path without
    suffix gives a folder of PNG frames `frame_0000.png`, ... Returns the ground-truth path.
    """
    source = read_image(source_path)
    out = Path(out_path).expanduser()
    if not out.parent.is_dir():
        raise OutputError(f"output folder does not exist: {out.parent}")
    suffix = out.suffix.lower()
    as_folder = out.is_dir() or suffix == ""
    if not as_folder and suffix not in _VIDEO_CODECS:
        raise OutputError(
            f"unsupported video format '{out.suffix}' (use .mp4, .avi or a folder): {out}"
        )
    w, h = params.size
    writer = None
    if as_folder:
        try:
            out.mkdir(exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create folder {out}: {exc.strerror or exc}") from exc
        for old in out.glob("frame_*.png"):
            old.unlink()
    else:
        fourcc = cv2.VideoWriter.fourcc(*_VIDEO_CODECS[suffix])
        writer = cv2.VideoWriter(str(out), fourcc, params.fps, (w, h))
        if not writer.isOpened():
            raise OutputError(f"cannot open video writer for {out}")

    frames_gt = []
    try:
        for i, (frame, H) in enumerate(render_frames(source, params)):
            if writer is not None:
                writer.write(frame)
            elif not cv2.imwrite(str(out / f"frame_{i:04d}.png"), frame):
                raise OutputError(f"cannot write frame {i} to {out}")
            frames_gt.append({"index": i, "H_frame_to_source": H})
    finally:
        if writer is not None:
            writer.release()
    if writer is not None and (not out.is_file() or out.stat().st_size == 0):
        raise OutputError(f"video writer produced no file: {out}")

    gt = {
        "source": str(source_path),
        "video": out.name,
        "size": [w, h],
        "fps": params.fps,
        "seed": params.seed,
        "params": dataclasses.asdict(params),
        "frames": frames_gt,
    }
    gt_path = write_json(gt_path_for(out), gt)
    log.info("wrote synthetic video %s (%d frames) and %s", out, len(frames_gt), gt_path)
    return gt_path


def load_ground_truth(path: str | Path) -> list[np.ndarray]:
    """`H_frame_to_source` per frame index from a `.gt.json` (or the video it belongs to)."""
    p = Path(path).expanduser()
    if p.suffix.lower() != ".json":
        p = gt_path_for(p)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
        frames = data["frames"]
        by_index = {int(f["index"]): np.asarray(f["H_frame_to_source"], np.float64) for f in frames}
    except FileNotFoundError as exc:
        raise InputError(f"ground truth not found: {p}") from exc
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"malformed ground truth {p}: {exc}") from exc
    if sorted(by_index) != list(range(len(by_index))) or not by_index:
        raise InputError(f"malformed ground truth {p}: frame indices are not 0..N-1")
    Hs = [by_index[i] for i in range(len(by_index))]
    if any(H.shape != (3, 3) or not np.isfinite(H).all() for H in Hs):
        raise InputError(f"malformed ground truth {p}: a homography is not a finite 3x3 matrix")
    return Hs


def relative_homographies(gt: list[np.ndarray] | np.ndarray, ref: int = 0) -> list[np.ndarray]:
    """H_i_to_ref = inv(H_ref_to_source) @ H_i_to_source for every frame i (normalised)."""
    G = np.asarray(gt, np.float64)
    rel = np.linalg.inv(G[ref])[None] @ G
    rel /= rel[:, 2:3, 2:3]
    return list(rel)


def corner_error(H_est_i_to_0: np.ndarray, H_gt_i_to_0: np.ndarray, size: tuple[int, int]) -> float:
    """Mean distance (px) between the four frame corners mapped by the estimate and the truth."""
    w, h = size
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
    Hs = np.stack([np.asarray(H_est_i_to_0, float), np.asarray(H_gt_i_to_0, float)])
    mapped = corners[None] @ Hs.transpose(0, 2, 1)
    xy = mapped[..., :2] / mapped[..., 2:]
    return float(np.linalg.norm(xy[0] - xy[1], axis=1).mean())


__all__ = [
    "SynthParams",
    "corner_error",
    "estimate_fov_disc",
    "gt_path_for",
    "load_ground_truth",
    "plan_trajectory",
    "relative_homographies",
    "render_frames",
    "write_synthetic_video",
]
