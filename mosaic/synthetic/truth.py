"""The ground truth of a synthetic video: its file's name beside the video
(`<video without suffix>.gt.json`) and the per-frame `H_frame_to_source` read back from it.
`synth` writes the file; the evaluation, the pictures and the tests read it.
"""

from __future__ import annotations

import json
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
