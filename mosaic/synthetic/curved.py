"""Fundus photograph pairs of a curved retina with exact ground truth.

A source fundus image is taken as the view of a spherical eye (radius 1) from a camera at the
pupil; it is painted onto the sphere, and two new photographs are taken from cameras that look
at the sphere's centre from two other places near the pupil (the eye turned, the camera moved
and rolled). No homography relates the two views: the retina is curved. Every pixel of one view
has an exact position in the other (the ray through it meets the sphere at one point, seen by
the other camera), so a pair carries FIRE-style control points and a dense ground truth.

`write_fire_folder` writes pairs in the FIRE layout (`Images/XNN_1.jpg`, `XNN_2.jpg`, `Ground
Truth/control_points_XNN_1_2.txt`, `pairs.csv`): `glampoints evaluate --format fire` and
`mosaic register --pairs` run on them as on FIRE. Image 1 is the fixed, image 2 the moving one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mosaic.errors import InputError
from mosaic.preprocess import estimate_fov_disc

HALF_FIELD_DEG = 22.5  # a 45 degree fundus camera: the source shows this half-angle of view
APERTURE = 0.94  # the photographs' circular field of view, in half image sides


@dataclass(frozen=True)
class Camera:
    """A pinhole looking at the eye's centre: position `centre` (eye radius 1), rotation
    `R_world_to_cam` (rows: the camera's x, y and optical axes), focal `f_px` and `size` px."""

    centre: np.ndarray
    R_world_to_cam: np.ndarray
    f_px: float
    size: int

    def rays(self, xy: np.ndarray) -> np.ndarray:
        """World directions (N, 3) of the rays through pixels (N, 2)."""
        c = (self.size - 1) / 2
        d = np.column_stack(
            [(xy[:, 0] - c) / self.f_px, (xy[:, 1] - c) / self.f_px, np.ones(len(xy))]
        )
        return d @ self.R_world_to_cam  # R^T d for each row

    def project(self, X: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of world points (N, 3); nan behind the camera."""
        p = (X - self.centre) @ self.R_world_to_cam.T
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(p[:, 2] > 1e-9, p[:, 2], np.nan)
        c = (self.size - 1) / 2
        return np.column_stack([p[:, 0] / z * self.f_px + c, p[:, 1] / z * self.f_px + c])


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation (radians) about x, then y, then z."""
    cx, sx, cy, sy, cz, sz = (
        math.cos(rx),
        math.sin(rx),
        math.cos(ry),
        math.sin(ry),
        math.cos(rz),
        math.sin(rz),
    )
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _camera(
    turn: np.ndarray, roll: float, distance: float, size: int, half_field_deg: float
) -> Camera:
    """A camera `distance` from the eye's centre, on the optical axis of the eye turned by
    `turn` (rx, ry radians), rolled by `roll`, looking at the centre."""
    R_eye = _rotation(turn[0], turn[1], 0.0)
    R_cam_to_world = R_eye @ _rotation(0.0, 0.0, roll)
    centre = R_eye @ np.array([0.0, 0.0, -distance])
    f = (size - 1) / 2 / math.tan(math.radians(half_field_deg))
    return Camera(centre, R_cam_to_world.T, f, size)


def hit_sphere(centre: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """The far intersection (N, 3) of rays from `centre` (inside the unit sphere) with it: the
    retina seen from the pupil."""
    d = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    b = d @ centre
    c = centre @ centre - 1.0
    t = -b + np.sqrt(np.maximum(b * b - c, 0.0))
    return centre + t[:, None] * d


@dataclass(frozen=True)
class CurvedPair:
    """Two photographs of a curved retina and the exact mapping between them."""

    fixed: np.ndarray  # BGR uint8 (size, size, 3)
    moving: np.ndarray
    camera_fixed: Camera
    camera_moving: Camera
    control_points: np.ndarray  # (N, 4) x1 y1 x2 y2: fixed (1) and moving (2) pixels, FIRE's order

    def moving_to_fixed(self, xy: np.ndarray) -> np.ndarray:
        """Exact positions in the fixed image (N, 2) of moving-image pixels (N, 2)."""
        X = hit_sphere(self.camera_moving.centre, self.camera_moving.rays(xy))
        return self.camera_fixed.project(X)


def _render(
    source: np.ndarray,
    disc: tuple[float, float, float],
    camera: Camera,
    src_cam: Camera,
    rng: np.random.Generator,
    filled: bool = False,
) -> np.ndarray:
    """The photograph `camera` takes of the sphere painted with `source`, with a circular
    aperture, vignetting, a gain and noise. Beyond the source's disc the sphere is black, or
    with `filled` painted with the source's reflection in its rim (a real retina goes on)."""
    n = camera.size
    step = 4  # the map is computed on a coarse grid and interpolated (smooth, exact to ~1e-3 px)
    g = np.arange(0, n + step, step, dtype=np.float64)
    gx, gy = np.meshgrid(g, g)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    src = src_cam.project(hit_sphere(camera.centre, camera.rays(xy)))
    cx, cy, r = disc
    half = (src_cam.size - 1) / 2
    scale = r / half  # the source camera's image is the disc, resized
    coarse_x = ((src[:, 0] - half) * scale + cx).reshape(gx.shape).astype(np.float32)
    coarse_y = ((src[:, 1] - half) * scale + cy).reshape(gx.shape).astype(np.float32)
    u = np.arange(n, dtype=np.float32) / step  # fine pixels on the coarse grid
    ux, uy = np.meshgrid(u, u)
    map_x = cv2.remap(coarse_x, ux, uy, cv2.INTER_LINEAR)
    map_y = cv2.remap(coarse_y, ux, uy, cv2.INTER_LINEAR)
    if filled:
        map_x, map_y = _reflect_beyond(map_x, map_y, (cx, cy, 0.97 * r))
    img = cv2.remap(source, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT)
    inside_src = np.hypot(map_x - cx, map_y - cy) < r * 0.99
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    c = (n - 1) / 2
    rho = np.hypot(xx - c, yy - c) / (APERTURE * c)
    shade = rng.uniform(0.85, 1.15) * (1 - rng.uniform(0.15, 0.35) * rho**2)
    out = img.astype(np.float32) * shade[..., None] * inside_src[..., None]
    out += rng.normal(0, 2.0, out.shape).astype(np.float32)
    out[rho > 1] = 0
    return np.clip(out, 0, 255).astype(np.uint8)


def _reflect_beyond(
    map_x: np.ndarray, map_y: np.ndarray, disc: tuple[float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Source positions beyond the disc (cx, cy, r) moved to their reflection in its rim
    (radius 2 r - rho, same direction), so the sphere is painted everywhere."""
    cx, cy, r = disc
    dx, dy = map_x - cx, map_y - cy
    rho = np.hypot(dx, dy)
    k = np.where(rho > r, np.maximum(2 * r - rho, 0.0) / np.maximum(rho, 1e-6), 1.0)
    return (cx + dx * k).astype(np.float32), (cy + dy * k).astype(np.float32)


def _visit(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """`image` as another visit would show it: defocus, an off-centre illumination, gamma and
    colour balance, a few lesions come or gone, more sensor noise. A photograph of the same
    eye months later differs in all of these; the geometry is untouched."""
    n = image.shape[0]
    px = n / 2912  # sizes below are for a 2912 px photograph
    out = image.astype(np.float32)
    aperture = image.max(axis=2) > 0
    sigma = rng.uniform(0.0, 2.5) * px
    if sigma > 0.3:
        out = cv2.GaussianBlur(out, (0, 0), sigma)
    for _ in range(int(rng.integers(0, 7))):  # lesions: dark red haemorrhages, yellow exudates
        centre = rng.uniform(0.25, 0.75, 2) * n
        radius = rng.uniform(8, 40) * px
        colour = np.array([20.0, 25.0, 90.0]) if rng.random() < 0.5 else np.array([120, 230, 240.0])
        half = int(2 * radius) + 2
        x0, y0 = (int(c) - half for c in centre)
        box = out[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1]
        yy, xx = np.mgrid[y0 : y0 + box.shape[0], x0 : x0 + box.shape[1]]
        spot = 1 / (1 + np.exp((np.hypot(xx - centre[0], yy - centre[1]) - radius) / (radius / 6)))
        spot = 0.8 * spot[..., None].astype(np.float32)
        box[:] = box * (1 - spot) + colour * spot
    yy, xx = (np.mgrid[0:n, 0:n].astype(np.float32) + 0.5) / n
    cx, cy = rng.uniform(0.2, 0.8, 2)
    width = rng.uniform(0.25, 0.6)
    light = 1 + rng.uniform(-0.35, 0.5) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / width**2)
    balance = rng.uniform(0.85, 1.15, 3).astype(np.float32)
    gamma = rng.uniform(0.75, 1.35)
    out = 255 * (np.clip(out * light[..., None] * balance, 0, 255) / 255) ** gamma
    out += rng.normal(0, rng.uniform(1.0, 5.0), out.shape).astype(np.float32)
    out[~aperture] = 0
    return np.clip(out, 0, 255).astype(np.uint8)


def curved_pair(
    source: np.ndarray,
    seed: int = 0,
    size: int = 2048,
    turn_deg: float = 16.0,
    n_points: int = 10,
    pupil_distance: float = 1.0,
    realistic: bool = False,
) -> CurvedPair:
    """A pair of `size` px photographs of the retina of `source` (a fundus image) taken from two
    camera poses `seed` draws: eye turns of up to `turn_deg` each way (overlap shrinks as it
    grows), rolls of up to 10 degrees, distances from the eye's centre around `pupil_distance`
    (1: at the pupil). `n_points` control points lie where both views see the retina.
    `realistic`: as a real camera's follow-up pair: the aperture always filled (the retina
    continues beyond the source's rim as its reflection, `_render`), each photograph as from
    its own visit (`_visit`: focus, illumination, gamma, colour, lesions, noise)."""
    rng = np.random.default_rng(seed)
    disc = estimate_fov_disc(source)
    src_cam = _camera(np.zeros(2), 0.0, pupil_distance, 2 * int(disc[2]) + 1, HALF_FIELD_DEG)
    cams = []
    for _ in range(2):
        turn = np.radians(rng.uniform(-turn_deg / 2, turn_deg / 2, 2))
        roll = math.radians(rng.uniform(-10, 10))
        distance = pupil_distance * rng.uniform(0.97, 1.03)
        cams.append(_camera(turn, roll, distance, size, HALF_FIELD_DEG))
    fixed = _render(source, disc, cams[0], src_cam, rng, realistic)
    moving = _render(source, disc, cams[1], src_cam, rng, realistic)
    if realistic:  # its own generator: the geometry and the plain pairs stay as they were
        visit_rng = np.random.default_rng([seed, 1])
        fixed, moving = _visit(fixed, visit_rng), _visit(moving, visit_rng)
    pair = CurvedPair(fixed, moving, cams[0], cams[1], np.zeros((0, 4)))
    return CurvedPair(
        fixed, moving, cams[0], cams[1], _control_points(pair, src_cam, disc, rng, n_points)
    )


def _control_points(
    pair: CurvedPair,
    src_cam: Camera,
    disc: tuple[float, float, float],
    rng: np.random.Generator,
    n: int,
) -> np.ndarray:
    """`n` points of the moving image seen by both views and the source, and their truth."""
    size = pair.camera_moving.size
    c = (size - 1) / 2
    rows = []
    for _ in range(200):
        xy2 = rng.uniform(0, size - 1, (4 * n, 2))
        xy1 = pair.moving_to_fixed(xy2)
        X = hit_sphere(pair.camera_moving.centre, pair.camera_moving.rays(xy2))
        s = src_cam.project(X)
        in_src = (
            np.hypot(s[:, 0] - (src_cam.size - 1) / 2, s[:, 1] - (src_cam.size - 1) / 2)
            < 0.9 * (src_cam.size - 1) / 2
        )
        ok = (
            (np.hypot(xy2[:, 0] - c, xy2[:, 1] - c) < 0.9 * APERTURE * c)
            & (np.hypot(xy1[:, 0] - c, xy1[:, 1] - c) < 0.9 * APERTURE * c)
            & in_src
        )
        rows.extend(np.column_stack([xy1[ok], xy2[ok]]))
        if len(rows) >= n:
            return np.array(rows[:n])
    raise InputError("the two views of a curved pair do not overlap: lower turn_deg")


def write_fire_folder(
    sources: list[Path],
    out: Path,
    n_pairs: int,
    seed: int = 0,
    size: int = 2048,
    turn_deg: float = 16.0,
    realistic: bool = False,
) -> Path:
    """Write `n_pairs` curved pairs (sources taken in turn) in the FIRE layout under `out`, and
    `pairs.csv` (fixed,moving) for `mosaic register --pairs`; returns `out`. `realistic`: as
    in `curved_pair`, and JPEG quality 70-95 instead of 95."""
    images, truth = out / "Images", out / "Ground Truth"
    images.mkdir(parents=True, exist_ok=True)
    truth.mkdir(parents=True, exist_ok=True)
    lines = ["fixed,moving"]
    for i in range(n_pairs):
        source = cv2.imread(str(sources[i % len(sources)]), cv2.IMREAD_COLOR)
        if source is None:
            raise InputError(f"cannot read {sources[i % len(sources)]}")
        pair = curved_pair(source, seed=seed + i, size=size, turn_deg=turn_deg, realistic=realistic)
        quality = (
            np.random.default_rng([seed + i, 2]).integers(70, 96, 2) if realistic else (95, 95)
        )
        name = f"C{i + 1:02d}"
        for k, image in enumerate((pair.fixed, pair.moving)):
            path = images / f"{name}_{k + 1}.jpg"
            cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, int(quality[k])])
        np.savetxt(truth / f"control_points_{name}_1_2.txt", pair.control_points, fmt="%.3f")
        lines.append(f"Images/{name}_1.jpg,Images/{name}_2.jpg")
    (out / "pairs.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return out
