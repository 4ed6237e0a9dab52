"""The ground truth of a synthetic video: its file's name beside the video
(`<video without suffix>.gt.json`) and the per-frame `H_frame_to_source` read back from it.
`synth` writes the file; the evaluation, the pictures and the tests read it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from mosaic.errors import InputError

# the video files `synth` writes, by suffix: their codec (any other path is a folder of frames)
VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG"}


def gt_path_for(video_path: str | Path) -> Path:
    """Ground-truth file of a synthetic video: `<video without suffix>.gt.json` beside it."""
    p = Path(video_path).expanduser()
    stem = p.name if p.is_dir() or p.suffix.lower() not in VIDEO_CODECS else p.stem
    return p.with_name(stem + ".gt.json")


def recorded_source(source: str | Path, gt_file: Path) -> dict[str, str]:
    """The source photograph's path as a ground truth records it: relative to the file's
    folder (`source`: a set moved together with its photographs, or read from any folder,
    still finds them) and absolute (`source_absolute`: a set moved without them)."""
    absolute = Path(source).expanduser().resolve()
    try:
        relative = os.path.relpath(absolute, gt_file.expanduser().resolve().parent)
    except ValueError:  # another drive (Windows): no relative path
        relative = str(absolute)
    return {"source": relative, "source_absolute": str(absolute)}


def source_path(gt_file: Path) -> Path | None:
    """The source photograph a ground-truth file names (None if it names none).

    `~` is expanded; a relative path is looked up beside the ground truth (as `synth` records
    it), then at `source_absolute`, then from the current folder (files written before:
    relative to where `mosaic synth` was run); the first that exists, else the first.
    """
    try:
        truth = json.loads(gt_file.read_text(encoding="utf-8"))
        source, absolute = truth.get("source"), truth.get("source_absolute")
    except (OSError, ValueError, AttributeError) as exc:
        raise InputError(f"malformed ground truth {gt_file}: {exc}") from exc
    if not isinstance(source, str) or not source:
        return None
    p = Path(source).expanduser()
    if p.is_absolute():
        return p
    candidates = [gt_file.parent / p, *([Path(absolute)] if isinstance(absolute, str) else []), p]
    return next((c for c in candidates if c.is_file()), candidates[0])


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


__all__ = ["VIDEO_CODECS", "gt_path_for", "load_ground_truth"]
