"""Video evaluation's results (`VideoResult`) and what is made of them: the mean over
videos, the paired comparison of methods and of runs (`mosaic evaluate --against`: mean
differences with bootstrap intervals over videos), and the tables, CSV / JSON and plots.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mosaic.errors import InputError
from mosaic.eval.common import format_cell, format_table, json_safe, nanmean, pyplot, write_csv
from mosaic.io import atomic_path, make_folder, write_json
from mosaic.registration import MODELS as MOTION_MODELS

log = logging.getLogger(__name__)

ACCURATE_CORNER_ERROR_PX = 10.0  # a video frame further than this from the truth is a failure


@dataclass(frozen=True)
class VideoResult:
    """One detector on one video (one row of videos.csv)."""

    detector: str  # "name/strategy", e.g. "sift/keyframes"
    video: str
    has_ground_truth: bool
    frames: int  # frames read (including skipped ones)
    registered: int
    failed: int
    skipped: int
    registered_fraction: float  # registered / decoded frames
    frames_until_failure: int  # registered (and, with ground truth, accurate) from the start
    frames_until_failure_pipeline: int  # the pipeline's own count (registration failures only)
    accurate_fraction: float  # registered within 10 px of the truth / decoded frames
    mean_error_px: float  # corner error of registered frames (frame -> first frame)
    median_error_px: float
    max_error_px: float
    drift_px_per_frame: float  # slope of the corner error against the frame index
    mean_inliers: float
    fps: float
    # the corner error taken apart (`geometry.view_error`), means over the same frames: the
    # shift at the frame centre, the zoom and the roll of each frame against the truth
    shift_error_px: float = math.nan
    zoom_error_pct: float = math.nan
    roll_error_deg: float = math.nan
    step_median_px: float = math.nan  # corner error of each frame relative to its reference
    step_p90_px: float = math.nan
    quality_rho: float = math.nan  # Spearman of quality and corner error (negative: it works)
    bad_frames: float = math.nan  # frames more than 10 px off the truth (nan: no truth)
    bad_caught: float = math.nan  # fraction of them flagged by the quality score
    good_flagged: float = math.nan  # fraction of the frames within 10 px flagged
    fidelity: float = math.nan  # mean local NCC of the main mosaic and the source (issue 16)
    good_area: float = math.nan  # share of the scanned retina with local NCC > 0.5
    oracle_fidelity: float = math.nan  # the same for the mean of frames placed by the truth
    oracle_good_area: float = math.nan
    model_counts: dict[str, int] = field(default_factory=dict)  # registered frames per model
    # mosaic segments (several: the camera left the mapped area; `registered` counts them all,
    # `accurate` and the errors are of the first placed frame's segment)
    segments: int = 1
    precision: str | None = None  # GLAMpoints' network as it ran (None: no network, older run)
    errors: list[tuple[int, float]] = field(default_factory=list, repr=False)  # (index, px)
    step_errors: list[tuple[int, float]] = field(default_factory=list, repr=False)


VIDEO_MEAN_KEYS = (
    "frames",
    "registered_fraction",
    "frames_until_failure",
    "frames_until_failure_pipeline",
    "accurate_fraction",
    "mean_error_px",
    "max_error_px",
    "drift_px_per_frame",
    "shift_error_px",
    "zoom_error_pct",
    "roll_error_deg",
    "step_median_px",
    "step_p90_px",
    "quality_rho",
    "bad_frames",
    "bad_caught",
    "good_flagged",
    "fidelity",
    "good_area",
    "oracle_fidelity",
    "oracle_good_area",
    "mean_inliers",
    "fps",
    "segments",
)
VIDEO_COLUMNS = (
    ("detector", "detector", ""),
    ("videos", "videos", "d"),
    ("frames", "frames", ".1f"),
    ("registered_fraction", "registered", ".3f"),
    ("frames_until_failure", "until fail", ".2f"),
    ("frames_until_failure_pipeline", "until fail (pipe)", ".2f"),
    ("accurate_fraction", "accurate", ".3f"),
    ("mean_error_px", "error px", ".2f"),
    ("max_error_px", "max px", ".2f"),
    ("drift_px_per_frame", "drift px/fr", ".3f"),
    ("shift_error_px", "centre px", ".2f"),
    ("zoom_error_pct", "zoom %", ".2f"),
    ("roll_error_deg", "roll deg", ".2f"),
    ("step_median_px", "step med px", ".2f"),
    ("step_p90_px", "step p90 px", ".2f"),
    ("quality_rho", "quality rho", ".2f"),
    ("bad_frames", "bad >10px", ".1f"),
    ("bad_caught", "bad caught", ".2f"),
    ("good_flagged", "good flagged", ".2f"),
    ("fidelity", "fidelity", ".3f"),
    ("good_area", "good area", ".3f"),
    ("oracle_fidelity", "oracle fid", ".3f"),
    ("oracle_good_area", "oracle good", ".3f"),
    ("models", "models", ""),
    ("fps", "fps", ".1f"),
)


# paired differences between methods (`compare_methods`): (key, header, format spec)
DIFFERENCE_KEYS = (
    ("accurate_fraction", "accurate", ".3f"),
    ("registered_fraction", "registered", ".3f"),
    ("until_failure_share", "until failure", ".3f"),  # frames_until_failure / frames
    ("mean_error_px", "error px", ".2f"),
)
BOOTSTRAP_SAMPLES = 2000


def _video_value(result: VideoResult, key: str) -> float:
    if key == "until_failure_share":
        return result.frames_until_failure / result.frames if result.frames else math.nan
    return float(getattr(result, key))


def _paired(
    pairs: Sequence[tuple[VideoResult, VideoResult]],
    method: str,
    against: str,
    rng: np.random.Generator,
    samples: int,
) -> dict[str, Any]:
    """The mean difference (first of each pair minus second) per measure, and its 95 %
    bootstrap interval over the pairs (videos resampled)."""
    row: dict[str, Any] = {"method": method, "against": against, "videos": len(pairs)}
    for key, _, _ in DIFFERENCE_KEYS:
        d = np.array([_video_value(a, key) - _video_value(b, key) for a, b in pairs])
        d = d[np.isfinite(d)]
        # rounded below float noise: equal runs print +0.000, not -0.000
        row[key] = round(float(d.mean()), 12) + 0.0 if len(d) else math.nan
        low = high = math.nan
        if len(d) >= 2:
            means = d[rng.integers(0, len(d), (samples, len(d)))].mean(axis=1)
            low, high = (float(x) for x in np.percentile(means, [2.5, 97.5]))
        row[f"{key}_low"], row[f"{key}_high"] = low, high
    return row


def compare_methods(
    results: Sequence[VideoResult],
    previous: Sequence[VideoResult] = (),
    samples: int = BOOTSTRAP_SAMPLES,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Each method (detector/strategy) against the run's first, and against itself in a
    `previous` run (`load_video_results`), paired over the videos both ran: the mean
    difference and its 95 % bootstrap interval (videos resampled). Single drifting videos
    swing by tenths with small changes, so on a few videos a difference whose interval holds
    0 is no difference; pairing removes what the videos themselves vary by."""
    rng = np.random.default_rng(seed)
    methods = list(dict.fromkeys(r.detector for r in results))
    by_run = {(r.detector, r.video): r for r in results}
    rows = []
    base = methods[0] if methods else ""
    for method in methods[1:]:
        videos = [v for m, v in by_run if m == method and (base, v) in by_run]
        pairs = [(by_run[method, v], by_run[base, v]) for v in videos]
        rows.append(_paired(pairs, method, base, rng, samples))
    key_before, key_now = _video_keys(previous), _video_keys(results)
    before = {(r.detector, key_before[r.video]): r for r in previous}
    for method in methods if previous else []:
        runs = [r for r in results if r.detector == method]
        keys = [(method, key_now[r.video]) for r in runs]
        pairs = [(r, before[k]) for r, k in zip(runs, keys, strict=True) if k in before]
        rows.append(_paired(pairs, method, f"{method} (previous run)", rng, samples))
    return rows


def warn_of_precisions(results: Sequence[VideoResult], previous: Sequence[VideoResult]) -> None:
    """Say where a method's GLAMpoints ran in another precision in the earlier run: single
    videos swing by tenths between float32 and bfloat16, so the differences include that."""
    before = {r.detector: r.precision for r in previous}
    mixed = {
        (r.detector, r.precision, before[r.detector])
        for r in results
        if r.detector in before and r.precision != before[r.detector]
    }
    for method, now, then in sorted(mixed, key=str):
        log.warning(
            "%s ran in %s here and in %s in the earlier run: the differences include the "
            "precision's (single videos swing by tenths between the two)",
            method, now or "an unrecorded precision", then or "an unrecorded precision",
        )  # fmt: skip


def _video_keys(run: Sequence[VideoResult]) -> dict[str, str]:
    """How each video of a run is matched across runs: by its file name where the run holds
    no other video of that name (runs started from other folders name the same video by other
    paths), else by its path."""
    videos = {r.video for r in run}
    names = Counter(Path(v).name for v in videos)
    return {v: Path(v).name if names[Path(v).name] == 1 else v for v in videos}


def load_video_results(path: Path) -> list[VideoResult]:
    """The per-video results of an earlier `mosaic evaluate` (its `--out` folder or its
    video_evaluation.json), for `compare_methods`."""
    file = path / "video_evaluation.json" if path.is_dir() else path
    try:
        videos = json.loads(file.read_text())["videos"]
        fields = {f.name for f in dataclasses.fields(VideoResult)}
        # JSON wrote nan as null (precision's null is None)
        entries = [
            {k: math.nan if v is None and k != "precision" else v for k, v in e.items()}
            for e in videos
        ]
        return [VideoResult(**{k: v for k, v in e.items() if k in fields}) for e in entries]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"not the output of `mosaic evaluate` on videos: {path} ({exc})") from exc


def format_differences(rows: Sequence[dict[str, Any]]) -> str:
    """The table of `compare_methods`: 'mean [low, high]' per measure."""
    cells = []
    for row in rows:
        cell: dict[str, Any] = {k: row[k] for k in ("method", "against", "videos")}
        for key, _, spec in DIFFERENCE_KEYS:
            keys = (key, f"{key}_low", f"{key}_high")
            mean, low, high = (format_cell(row[k], f"+{spec}") for k in keys)
            cell[key] = mean if math.isnan(row[f"{key}_low"]) else f"{mean} [{low}, {high}]"
        cells.append(cell)
    columns = [("method", "method", ""), ("against", "against", ""), ("videos", "videos", "d")]
    columns += [(key, header, "") for key, header, _ in DIFFERENCE_KEYS]
    return format_table(cells, columns)


def _model_columns(counts: dict[str, float]) -> dict[str, float]:
    """{"model_<name>": count} for the CSV, every model of MOTION_MODELS first (0 if absent)."""
    merged = {**dict.fromkeys(MOTION_MODELS, 0), **counts}
    return {f"model_{name}": n for name, n in merged.items()}


def format_models(counts: dict[str, float], spec: str = "d") -> str | None:
    """The models in use, abbreviated, e.g. "sim 80 / aff 10 / hom 9"; None when none was."""
    used = [f"{name[:3]} {format(n, spec)}" for name, n in counts.items() if n]
    return " / ".join(used) or None


def summarize_videos(results: Sequence[VideoResult]) -> list[dict[str, Any]]:
    """Mean over videos per detector (nan entries, e.g. no ground truth, are left out)."""
    rows = []
    for detector in dict.fromkeys(r.detector for r in results):
        rs = [r for r in results if r.detector == detector]
        row: dict[str, Any] = {"detector": detector, "videos": len(rs)}
        row.update({k: nanmean(getattr(r, k) for r in rs) for k in VIDEO_MEAN_KEYS})
        columns = [_model_columns(r.model_counts) for r in rs]
        names = dict.fromkeys(n for c in columns for n in c)
        row.update({n: float(np.mean([c.get(n, 0) for c in columns])) for n in names})
        rows.append(row)
    return rows


def format_video_tables(
    results: Sequence[VideoResult],
    summary: Sequence[dict[str, Any]],
    previous: Sequence[VideoResult] = (),
) -> str:
    """Per-video tables (one per detector), the mean over videos, and the paired differences
    (`compare_methods`: against the first method, and against a `previous` run)."""
    per_video = [
        {
            **dataclasses.asdict(r),
            "videos": 1,
            "detector": f"{r.detector} {Path(r.video).name}",
            "models": format_models(r.model_counts),
        }
        for r in results
    ]
    means = [{**row, "models": format_models(_summary_models(row), ".1f")} for row in summary]
    text = (
        "Per video (models: registered frames per motion model)\n"
        + format_table(per_video, VIDEO_COLUMNS)
        + "\n\nMean over videos\n"
        + format_table(means, VIDEO_COLUMNS)
    )
    differences = compare_methods(results, previous)
    if differences:
        text += (
            "\n\nPaired over the same videos: mean difference [95 % bootstrap interval over "
            "videos]\n" + format_differences(differences)
        )
    return text


def _summary_models(row: dict[str, Any]) -> dict[str, float]:
    """{model: mean count} back from a summary row's "model_<name>" entries."""
    return {k[len("model_") :]: v for k, v in row.items() if k.startswith("model_")}


def plot_videos(
    results: Sequence[VideoResult], summary: Sequence[dict[str, Any]], out: Path
) -> list[Path]:
    """video_frames_until_failure.png (bars) and video_error.png (error against frame index)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 0.5 * len(summary) + 1.4))
    names = [row["detector"] for row in summary]
    ax.barh(names, [row["frames_until_failure"] for row in summary], color="#1f77b4")
    ax.set_xlabel("frames until failure (mean over videos)")
    ax.invert_yaxis()
    fig.tight_layout()
    bars = out / "video_frames_until_failure.png"
    with atomic_path(bars) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    colours = {name: f"C{i % 10}" for i, name in enumerate(names)}
    labelled: set[str] = set()
    for r in results:
        if not r.errors:
            continue
        idx, err = zip(*r.errors, strict=True)
        label = r.detector if r.detector not in labelled else None
        labelled.add(r.detector)
        ax.plot(idx, err, color=colours.get(r.detector), alpha=0.8, lw=1, label=label)
    ax.axhline(ACCURATE_CORNER_ERROR_PX, color="k", ls="--", lw=0.8)
    ax.set_xlabel("frame index")
    ax.set_ylabel("corner error vs ground truth [px]")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    if labelled:
        ax.legend(fontsize=8)
    fig.tight_layout()
    curve = out / "video_error.png"
    with atomic_path(curve) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return [bars, curve]


_VIDEO_ROW_EXCLUDED = ("errors", "step_errors", "model_counts")  # per-frame lists; a dict


def write_video_outputs(
    results: Sequence[VideoResult],
    summary: Sequence[dict[str, Any]],
    out_dir: str | Path,
    meta: dict[str, Any] | None = None,
    previous: Sequence[VideoResult] = (),
) -> list[Path]:
    """videos.csv (per video), video_summary.csv, video_differences.csv (`compare_methods`,
    with two methods or more) / video_evaluation.json and the plots."""
    out = make_folder(out_dir)
    rows = [
        {
            **{k: v for k, v in dataclasses.asdict(r).items() if k not in _VIDEO_ROW_EXCLUDED},
            **_model_columns(r.model_counts),
        }
        for r in results
    ]
    written = [write_csv(out / "videos.csv", rows), write_csv(out / "video_summary.csv", summary)]
    differences = compare_methods(results, previous)
    if differences:
        written.append(write_csv(out / "video_differences.csv", differences))
    document = {
        "meta": meta or {},
        "summary": list(summary),
        "differences": differences,
        "videos": [dataclasses.asdict(r) for r in results],
    }
    written.append(write_json(out / "video_evaluation.json", json_safe(document)))
    written += plot_videos(results, summary, out)
    return written
