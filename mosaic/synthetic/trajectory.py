"""The camera's path over the source of a synthetic video: each frame's exact
`H_frame_to_source`, a smooth turning, zooming and tilting view whose corners stay inside the
source's field of view.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from mosaic.errors import InputError
from mosaic.geometry import translation
from mosaic.preprocess import estimate_fov_disc
from mosaic.preprocess import fov_distance as _fov_distance
from mosaic.synthetic.streams import GEOMETRY, HARD_GEOMETRY, REAL_GEOMETRY, smooth_signal, stream

if TYPE_CHECKING:
    from mosaic.synthetic.synth import SynthParams

log = logging.getLogger(__name__)


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


def _touch_rim(
    path: np.ndarray, centre: np.ndarray, dist: np.ndarray, min_dist: np.ndarray
) -> np.ndarray:
    """Shift a path (N, 2) outwards until a frame centre comes `min_dist` (N,) from the view's
    border: the largest shift, along the direction of the path's farthest point from `centre`,
    that keeps every `centre + path[i]` at least `min_dist[i]` from it (`dist`: `_fov_distance`).
    A shift keeps every step's length; the path must start feasible."""
    norms = np.linalg.norm(path, axis=1)
    far = int(np.argmax(norms))
    u = path[far] / norms[far] if norms[far] > 1e-9 else np.array([1.0, 0.0])
    shifts = np.arange(0.0, float(max(dist.shape)), 0.5)
    xy = centre + path[None] + shifts[:, None, None] * u  # (shifts, N, 2)
    ix = np.clip(np.rint(xy[..., 0]).astype(int) + 1, 0, dist.shape[1] - 1)
    iy = np.clip(np.rint(xy[..., 1]).astype(int) + 1, 0, dist.shape[0] - 1)
    feasible = (dist[iy, ix] >= min_dist).all(axis=1)
    n_ok = shifts.size if feasible.all() else int(np.argmin(feasible))
    return path + shifts[max(n_ok - 1, 0)] * u


def _view_maps(
    rng: np.random.Generator, params: SynthParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each frame's map into the source before its centre is placed, A = R S P T(-frame
    centre) (n, 3, 3): a slowly turning, zooming and tilting view; with its zoom (n,) and the
    relative speed of the centre between frames (n - 1,)."""
    n = params.n_frames
    w, h = params.size
    t = np.linspace(0.0, 1.0, n)
    angle = np.deg2rad(params.rotation_deg) / 2 * smooth_signal(rng, t)
    lo, hi = np.log(params.scale_range[0]), np.log(params.scale_range[1])
    zoom = np.exp((lo + hi) / 2 + (hi - lo) / 2 * smooth_signal(rng, t))
    tilt = params.perspective * np.stack([smooth_signal(rng, t), smooth_signal(rng, t)], 1)
    speed_signal = smooth_signal(rng, t[:-1]) if n > 2 else np.zeros(max(n - 1, 0))
    speed = 1.0 + params.speed_variation * speed_signal
    c, s = np.cos(angle), np.sin(angle)
    A = np.zeros((n, 3, 3))
    A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1] = c, -s, s, c
    A[:, :2, :2] /= zoom[:, None, None]
    A[:, 2, 2] = 1.0
    P = np.tile(np.eye(3), (n, 1, 1))
    P[:, 2, :2] = tilt
    return A @ P @ translation(-(w - 1) / 2, -(h - 1) / 2), zoom, speed


def _centre_steps(params: SynthParams, speed: np.ndarray, tremor: np.ndarray) -> np.ndarray:
    """The centre's step between frames (n - 1,) in frame px: the relative `speed` scaled to
    `max_step_px`, with bursts of fast motion, hand `tremor` and the step range applied."""
    n = params.n_frames
    steps = params.max_step_px * speed / speed.mean() if n > 1 else np.zeros(0)
    hard_rng = stream(params.seed, HARD_GEOMETRY)
    if params.fast_motion_prob > 0 and n > 1:
        starts = np.flatnonzero(hard_rng.random(n - 1) < params.fast_motion_prob)
        for start in starts:
            steps[start : start + int(hard_rng.integers(3, 6))] *= params.fast_motion_factor
    if params.step_jitter > 0:
        steps = steps * tremor
    if params.step_range_px is not None:
        steps = np.clip(steps, *params.step_range_px)
    return steps


def _revisiting_path(
    rng: np.random.Generator,
    steps: np.ndarray,
    radius: float,
    n: int,
    side_px: float,
    base: float,
) -> np.ndarray:
    """Out along the first half of the path, back along it shifted sideways by `side_px`
    frame px (`base` source px each): the way back overlaps the way out only partly."""
    half = (n + 1) // 2
    out_path = _centre_path(rng, steps[: half - 1], radius)
    direction = np.gradient(out_path, axis=0)
    normal = np.stack([-direction[:, 1], direction[:, 0]], 1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    back = (out_path + normal * side_px * base)[::-1][: n - half]
    path = np.concatenate([out_path, back])
    return path * min(1.0, radius / max(np.linalg.norm(path, axis=1).max(), 1e-9))


def plan_trajectory(source: np.ndarray, params: SynthParams) -> np.ndarray:
    """Ground truth `H_frame_to_source` (N, 3, 3) of a smooth path inside the source's view.

    H = T(centre) @ R(angle) @ S(scale) @ P(tilt) @ T(-frame centre). Every frame corner lies in
    the inscribed disc of the source's field of view (minus a margin), so no frame shows the
    source's black border. If the viewport is too large for the source, the whole video is
    zoomed in uniformly (logged).

    With `fov_fraction` the frame width spans that share of the view's diameter instead (drawn
    per video). With `rim_overlap` > 0 the path is shifted towards the rim of the view until,
    at one place, the view's black border comes within (1 - rim_overlap) frame half-heights of
    the frame centre: those frames show part of the border, as magnified real video does.
    """
    n = params.n_frames
    w, h = params.size
    cx, cy, r_fov = estimate_fov_disc(source)
    margin = max(4.0, 0.02 * r_fov)
    rng = stream(params.seed, GEOMETRY)
    A, zoom, speed = _view_maps(rng, params)
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
    mapped = corners @ A.transpose(0, 2, 1)
    reach = float(np.linalg.norm(mapped[..., :2] / mapped[..., 2:], axis=-1).max())

    base = 1.0  # source px per frame px at zoom 1; < 1 zooms in when the source is too small
    usable = 0.65 * (r_fov - margin)  # at most this much of the radius for the viewport
    if usable <= 1.0:
        raise InputError(f"source image field of view too small (radius {r_fov:.0f} px)")
    real_rng = stream(params.seed, REAL_GEOMETRY)
    fraction = real_rng.uniform(*(params.fov_fraction or (1.0, 1.0)))
    tremor = 1.0 + real_rng.uniform(-params.step_jitter, params.step_jitter, max(n - 1, 0))
    if params.fov_fraction is not None:
        base = fraction * 2 * r_fov / w
        log.info("frame spans %.0f %% of the source's view (x%.2f)", 100 * fraction, 1 / base)
    elif reach > usable:
        base = usable / reach
        log.info("viewport %dx%d too large for the source's view: zooming in x%.2f", w, h, 1 / base)
    A[:, :2, :] *= base  # scales the mapped x, y (not w) of every point by `base`
    reach *= base

    steps = _centre_steps(params, speed, tremor)
    steps = steps * base / np.sqrt(zoom[:-1] * zoom[1:]) if n > 1 else steps
    radius = r_fov - margin - reach * (1.0 - params.rim_overlap)  # then shifted to the rim
    if radius <= 0:
        raise InputError(
            f"frame {w}x{h} too large for the source's view (radius {r_fov:.0f} px) "
            f"at {1 / base:.2f}x magnification"
        )
    if params.revisit and n > 3:
        path = _revisiting_path(rng, steps, radius, n, h / 3, base)
    else:
        path = _centre_path(rng, steps, radius)
    if params.rim_overlap > 0:
        half_height = (h - 1) / 2 * base / zoom  # in source px
        min_dist = np.maximum((1.0 - params.rim_overlap) * half_height, 1.0)
        path = _touch_rim(path, np.array([cx, cy]), _fov_distance(source), min_dist)
    H = translation(cx, cy)[None] @ np.tile(np.eye(3), (n, 1, 1))
    H[:, :2, 2] += path
    H = H @ A
    return H / H[:, 2:3, 2:3]
