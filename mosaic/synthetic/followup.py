"""Synthetic follow-up visits: the same eye with planted changes, and their truth.

A follow-up of a synthetic video is rendered from the baseline's own source photograph with
three changes planted in it (`plant_changes`), each at least `MIN_CHANGE_PX` a side in source
pixels and inside the part of the retina both visits' frames see:

- a new haemorrhage: a soft dark-red blob (green and blue take most of the loss, as blood's
  absorption does);
- a narrowed vessel segment: where a large vessel runs, its dark profile is eroded from both
  sides (a grey dilation of the image), so the segment is about half as wide;
- a laser-scar pattern: a grid of small spots, each a pale centre ringed with pigment.

The truth (`changes`, in source pixels) goes into the follow-up's `gt.json` under `followup`;
the frames' `H_frame_to_source` there are in the same source coordinates as the baseline's, so
the follow-up's transform relative to the baseline is exact: both videos map into one source.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mosaic.errors import InputError
from mosaic.preprocess import estimate_fov_disc
from mosaic.synthetic.truth import gt_path_for, source_path

log = logging.getLogger(__name__)

MIN_CHANGE_PX = 10  # the smallest change a side, in source pixels
KINDS = ("haemorrhage", "narrowed_vessel", "laser_scars")


@dataclass(frozen=True)
class Change:
    """One planted change: its kind and bounding box (x0, y0, x1, y1) in source pixels."""

    kind: str
    bbox: tuple[float, float, float, float]

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "bbox_source": [round(v, 2) for v in self.bbox]}


def coverage_mask(H_frames_to_source: np.ndarray, frame_size: tuple[int, int],
                  shape: tuple[int, int], inset: float = 0.2) -> np.ndarray:  # fmt: skip
    """Pixels (bool, `shape`) of the source that at least one frame (w, h) shows well: its
    rectangle without `inset` of each side (a frame's corners are outside its aperture, its
    rim dim, and a mosaic's edge is no place for a change)."""
    w, h = frame_size
    x0, y0, x1, y1 = inset * (w - 1), inset * (h - 1), (1 - inset) * (w - 1), (1 - inset) * (h - 1)
    corners = np.array([[x0, y0, 1], [x1, y0, 1], [x1, y1, 1], [x0, y1, 1]], float)
    mask = np.zeros(shape, np.uint8)
    for H in np.asarray(H_frames_to_source, float):
        p = corners @ H.T
        cv2.fillConvexPoly(mask, np.round(p[:, :2] / p[:, 2:]).astype(np.int32), 1)
    return mask.astype(bool)


def _soft_disc(shape: tuple[int, int], cx: float, cy: float, rx: float, ry: float,
               angle: float = 0.0, edge: float = 0.25) -> np.ndarray:  # fmt: skip
    """A float32 ellipse of 1 inside and a smooth fall to 0 over `edge` of its radius."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    c, s = np.cos(angle), np.sin(angle)
    u, v = (xx - cx) * c + (yy - cy) * s, -(xx - cx) * s + (yy - cy) * c
    r = np.sqrt((u / rx) ** 2 + (v / ry) ** 2)
    return np.clip((1.0 + edge - r) / edge, 0.0, 1.0).astype(np.float32) ** 2


def _pick(score: np.ndarray, allowed: np.ndarray, rng: np.random.Generator,
          top: float = 0.9) -> tuple[int, int]:  # fmt: skip
    """A random (x, y) among the allowed pixels whose score is in its top share."""
    ys, xs = np.nonzero(allowed)
    if xs.size == 0:
        raise InputError(
            "the two visits share too little retina to plant a change in (more frames, or "
            "another seed, give the two videos more in common)"
        )
    values = score[ys, xs]
    keep = np.flatnonzero(values >= np.quantile(values, top))
    k = int(rng.choice(keep))
    return int(xs[k]), int(ys[k])


def _haemorrhage(image: np.ndarray, x: int, y: int, radius: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, Change]:  # fmt: skip
    rx, ry = radius * rng.uniform(0.8, 1.2), radius * rng.uniform(0.6, 0.9)
    blob = _soft_disc(image.shape[:2], x, y, rx, ry, rng.uniform(0, np.pi))[..., None]
    absorb = np.array([0.25, 0.35, 0.7], np.float32)  # B, G, R kept at the blob's core
    out = image * (1.0 - blob * (1.0 - absorb))
    half = 1.25 * max(rx, ry)
    return out, Change("haemorrhage", (x - half, y - half, x + half, y + half))


def _narrowed_vessel(image: np.ndarray, x: int, y: int, half: float,
                     width_px: int) -> tuple[np.ndarray, Change]:  # fmt: skip
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (width_px, width_px))
    eroded = cv2.dilate(image, kernel)  # bright grows: a dark vessel loses width each side
    window = _soft_disc(image.shape[:2], x, y, half, half, edge=0.4)[..., None]
    out = image * (1.0 - window) + eroded * window
    reach = 1.4 * half  # the window's soft edge
    return out, Change("narrowed_vessel", (x - reach, y - reach, x + reach, y + reach))


def _laser_scars(image: np.ndarray, x: int, y: int, spot_r: float, n: int,
                 rng: np.random.Generator) -> tuple[np.ndarray, Change]:  # fmt: skip
    pitch = 2.6 * spot_r
    offsets = (np.arange(n) - (n - 1) / 2) * pitch
    out = image.copy()
    pale = np.array([170, 215, 235], np.float32)  # B, G, R of a pale, atrophic scar
    for oy in offsets:
        for ox in offsets:
            cx, cy = x + ox + rng.normal(0, 0.1 * spot_r), y + oy + rng.normal(0, 0.1 * spot_r)
            ring = _soft_disc(image.shape[:2], cx, cy, 1.25 * spot_r, 1.25 * spot_r, edge=0.3)
            core = _soft_disc(image.shape[:2], cx, cy, 0.8 * spot_r, 0.8 * spot_r, edge=0.3)
            out = out * (1.0 - 0.55 * ring[..., None])  # pigment around the spot
            out = out * (1.0 - core[..., None]) + pale * core[..., None]
    half = -offsets[0] + 2.0 * spot_r  # the rings' soft edge (1.63 r) and the jitter
    return out, Change("laser_scars", (x - half, y - half, x + half, y + half))


def plant_changes(
    source: np.ndarray, allowed: np.ndarray | None, rng: np.random.Generator
) -> tuple[np.ndarray, list[Change]]:
    """The source (BGR uint8) with a haemorrhage, a narrowed vessel segment and a laser-scar
    pattern planted where `allowed` (bool, source shape; None: the retina's disc) holds, each
    clear of the others and of the allowed area's edge; and the changes' truth.

    Sizes follow the retina's radius R (a photograph of any resolution gets the same changes):
    haemorrhage radius 0.035 R, vessel window 0.05 R (narrowed by 0.008 R each side), scar
    spots of 0.012 R on a 3x3 grid; none smaller than `MIN_CHANGE_PX` a side."""
    h, w = source.shape[:2]
    cx, cy, r = estimate_fov_disc(source)
    yy, xx = np.mgrid[0:h, 0:w]
    in_disc = np.hypot(xx - cx, yy - cy) < 0.85 * r
    allowed = in_disc if allowed is None else allowed & in_disc
    sizes = {
        "haemorrhage": max(0.035 * r, MIN_CHANGE_PX / 2 + 1),
        "narrowed_vessel": max(0.05 * r, MIN_CHANGE_PX / 2 + 1),
        "laser_scars": max(0.012 * r, 2.5),
    }
    green = source[..., 1].astype(np.float32)
    vessel_px = max(round(0.03 * r), 5) | 1  # wider than the large vessels
    disc_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (vessel_px, vessel_px))
    vessels = cv2.morphologyEx(green, cv2.MORPH_BLACKHAT, disc_kernel)
    window = int(2 * sizes["narrowed_vessel"]) | 1
    vessel_score = cv2.boxFilter(vessels, -1, (window // 3 | 1, window // 3 | 1))  # a dark one
    calm = -cv2.boxFilter(vessels, -1, (window * 2 + 1, window * 2 + 1))  # scars avoid vessels
    brightness = cv2.GaussianBlur(green, (0, 0), max(r * 0.05, 1.0))
    optic_disc = brightness > np.quantile(brightness[in_disc], 0.97)  # its vessels are a tangle
    optic_disc = cv2.dilate(optic_disc.astype(np.uint8), np.ones((window, window), np.uint8)) > 0
    vessel_score = np.where(optic_disc, 0.0, vessel_score)
    image = source.astype(np.float32)
    changes: list[Change] = []
    free = allowed.astype(np.uint8)
    for kind in KINDS:
        half = {"haemorrhage": 1.5, "narrowed_vessel": 1.4, "laser_scars": 4.6}[kind]
        reach = int(np.ceil(1.2 * half * sizes[kind]))  # the change's box, and a margin
        inner = cv2.erode(free, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)) > 0
        score = {"haemorrhage": -np.abs(brightness - np.median(brightness[in_disc])),
                 "narrowed_vessel": vessel_score, "laser_scars": calm}[kind]  # fmt: skip
        x, y = _pick(score, inner, rng, top=0.8 if kind != "narrowed_vessel" else 0.99)
        if kind == "haemorrhage":
            image, change = _haemorrhage(image, x, y, sizes[kind], rng)
        elif kind == "narrowed_vessel":
            width = max(round(0.016 * r), 3) | 1
            image, change = _narrowed_vessel(image, x, y, sizes[kind], width)
        else:
            image, change = _laser_scars(image, x, y, sizes[kind], 3, rng)
        changes.append(change)
        x0, y0, x1, y1 = (round(v) for v in change.bbox)
        pad = int(sizes[kind] / 2)  # the changes' boxes apart
        free[max(y0 - pad, 0) : y1 + pad, max(x0 - pad, 0) : x1 + pad] = 0
        log.info("planted %s at (%d, %d)", kind, x, y)
    return np.clip(image + 0.5, 0, 255).astype(np.uint8), changes


def followup_hook(
    baseline_gt: dict[str, Any], seed: int
) -> Callable[[np.ndarray, Any], tuple[np.ndarray, dict[str, Any]]]:
    """The `edit_source` hook of `synth.write_synthetic_video` that renders a follow-up of the
    baseline whose ground truth is `baseline_gt`: changes planted where the baseline's frames
    and the follow-up's own frames (its trajectory, planned from the same source) both look."""
    from mosaic.synthetic.trajectory import plan_trajectory

    H_base = np.array([f["H_frame_to_source"] for f in baseline_gt["frames"]], float)
    base_size = tuple(baseline_gt["size"])

    def edit(source: np.ndarray, params: Any) -> tuple[np.ndarray, dict[str, Any]]:
        shape = source.shape[:2]
        both = coverage_mask(H_base, base_size, shape) & coverage_mask(
            plan_trajectory(source, params), params.size, shape
        )
        changed, changes = plant_changes(source, both, np.random.default_rng([seed, 41]))
        return changed, {
            "followup": {
                "baseline_video": baseline_gt.get("video"),
                "baseline_source": baseline_gt.get("source"),
                "frames_in": "source",  # both videos' H_frame_to_source map into one source
                "changes": [c.to_json() for c in changes],
            }
        }

    return edit


def load_baseline_gt(path: str | Path) -> dict[str, Any]:
    """The ground truth of a baseline video (its `.gt.json`, or the video it belongs to)."""
    import json

    p = Path(path).expanduser()
    gt_path = p if p.suffix.lower() == ".json" else gt_path_for(p)
    try:
        gt = json.loads(gt_path.read_text(encoding="utf-8"))
        gt["frames"][0]["H_frame_to_source"], gt["size"], gt["source"]
    except FileNotFoundError:
        raise InputError(f"ground truth of the baseline not found: {gt_path}") from None
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise InputError(f"malformed ground truth {gt_path}: {exc}") from None
    source = source_path(gt_path)  # where it is from here (the file's may be relative to it)
    if source is None:
        raise InputError(f"malformed ground truth {gt_path}: it names no source photograph")
    gt["source"] = str(source)
    return gt


def source_to_mosaic(report: dict[str, Any], gt: dict[str, Any]) -> np.ndarray:
    """`H_source_to_mosaic` of a synthetic video's mosaic: the homography fitted (least squares)
    to a grid of every placed frame, mapped into the source by the truth and into the mosaic by
    the report's `H_to_canvas` (main segment). The truth of a comparison of two such mosaics
    is `H_source_to_baseline @ inv(H_source_to_followup)`."""
    w, h = report["input"]["width"], report["input"]["height"]
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 8), np.linspace(0, h - 1, 5))
    grid = np.column_stack([gx.ravel(), gy.ravel(), np.ones(gx.size)])
    truth = {int(f["index"]): np.asarray(f["H_frame_to_source"], float) for f in gt["frames"]}
    main = report.get("main_segment", 0)
    src, dst = [], []
    for f in report["frames"]:
        if f.get("H_to_canvas") is None or f.get("segment") != main or f["index"] not in truth:
            continue
        for H, out in ((truth[f["index"]], src), (np.asarray(f["H_to_canvas"], float), dst)):
            p = grid @ H.T
            out.append(p[:, :2] / p[:, 2:])
    if not src:
        raise InputError("the report places no frame of the video")
    H, _ = cv2.findHomography(np.vstack(src), np.vstack(dst), 0)
    return H / H[2, 2]
