"""Video evaluation (`mosaic evaluate`): each video run as `mosaic build` runs it, scored
against its synthetic ground truth.

`runner.run_video` (the code path of `mosaic build`) runs the video with `on_failure = "skip"`;
frames are checked against the synthetic ground truth (`*.gt.json`) when there is one: each
frame's placement against the first frame (corner error, drift) and against the frame it was
registered to (step error); the report's motion models are counted per video, and its
per-frame quality score is compared with the corner error (rank correlation, bad frames
flagged, good frames flagged). Each run's full report is kept under `reports/`. With a
readable source photograph, the mosaic itself is scored against it (`mosaic.eval.fidelity`,
issue 16: fidelity and good area), next to the oracle (the plain mean of the frames placed by
the true transforms, computed once per video). The results' tables, plots and the comparison
of runs are `video_tables`'.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mosaic.config import Config, with_overrides
from mosaic.errors import InputError
from mosaic.eval.common import make_extractors
from mosaic.eval.fidelity import (
    FidelityScores,
    SourceTruth,
    mosaic_fidelity,
    oracle_fidelity,
    prepare_source,
)
from mosaic.eval.video_tables import (
    ACCURATE_CORNER_ERROR_PX,
    VideoResult,
    summarize_videos,
    warn_of_precisions,
    write_video_outputs,
)
from mosaic.features import FeatureExtractor
from mosaic.geometry import corner_error, relative_homographies, view_error
from mosaic.io import UNDECODABLE, make_folder, read_image
from mosaic.pipeline import MosaicResult
from mosaic.preprocess import field_of_view_mask, to_gray
from mosaic.quality import spearman
from mosaic.registration import MODELS as MOTION_MODELS
from mosaic.report import FAILED, REGISTERED, SKIPPED, FrameEntry
from mosaic.runner import VIDEO_SUFFIXES, Outputs, is_frame_folder, run_video
from mosaic.runner import reread_frames as _reread
from mosaic.synthetic.truth import gt_path_for, load_ground_truth, source_path

log = logging.getLogger(__name__)


def find_videos(paths: Sequence[str | Path]) -> list[Path]:
    """Videos named on the command line: files, frame folders, or folders holding videos.

    A folder with image files is one video (its frames); otherwise its video files and its
    sub-folders that have a `<name>.gt.json` beside them are the videos.
    """
    found: list[Path] = []
    for raw in paths:
        p = Path(raw).expanduser()
        if not p.exists():
            raise InputError(f"input not found: {p}")
        if p.is_file():
            found.append(p)
            continue
        if is_frame_folder(p):
            found.append(p)
            continue
        inner = sorted(
            f
            for f in p.iterdir()
            if (f.is_file() and f.suffix.lower() in VIDEO_SUFFIXES)
            or (f.is_dir() and gt_path_for(f).is_file())
        )
        if not inner:
            raise InputError(f"no videos or frames in {p}")
        found += inner
    return found


def _placed_against_truth(
    frames: list[FrameEntry], gt: list[np.ndarray]
) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """(index, estimated H_frame_to_first, true H_frame_to_first) of each registered frame of
    the first placed frame's segment."""
    placed = [f for f in frames if f.status == REGISTERED and f.H_to_canvas is not None]
    if not placed or placed[0].index >= len(gt):
        return
    ref = placed[0]
    H_ref_to_canvas = np.asarray(ref.H_to_canvas, np.float64)
    rel = relative_homographies(gt, ref=ref.index)
    for f in placed:
        if f.segment != ref.segment:
            continue
        if f.index >= len(gt):
            log.warning("frame %d has no ground truth (%d frames in it)", f.index, len(gt))
            continue
        H_i_to_ref = np.linalg.solve(H_ref_to_canvas, np.asarray(f.H_to_canvas, np.float64))
        yield f.index, H_i_to_ref, rel[f.index]


Placed = list[tuple[int, np.ndarray, np.ndarray]]  # `_placed_against_truth`, as a list


def _corner_errors(placed: Placed, size: tuple[int, int]) -> dict[int, float]:
    """Corner error (px) of each placed frame against the truth."""
    return {i: corner_error(H, H_gt, size) for i, H, H_gt in placed}


def _view_parts(placed: Placed, size: tuple[int, int]) -> dict[str, float]:
    """The corner error taken apart, means over the frames: the shift at the frame centre
    (px), the zoom (%) and the roll (degrees) of each frame's error (`geometry.view_error`);
    empty without frames (the results' nan)."""
    parts = np.array([view_error(H, H_gt, size) for _, H, H_gt in placed])
    if not len(parts):
        return {}
    return {
        "shift_error_px": float(parts[:, 0].mean()),
        "zoom_error_pct": float(100 * np.abs(np.expm1(parts[:, 1])).mean()),
        "roll_error_deg": float(np.degrees(np.abs(parts[:, 2])).mean()),
    }


def _frame_references(frames: list[FrameEntry]) -> dict[int, int]:
    """{frame index: index of the frame it was registered against} for registered frames.

    The report's `"reference"` is used when it names a placed frame of the same segment. When it
    is missing or None (reports written before it existed) for a frame that is not its
    segment's first, the previous registered frame of that segment stands in: exact for the
    chain strategy, an approximation for keyframes. A segment's first frame has no reference.
    """
    placed = [f for f in frames if f.status == REGISTERED and f.H_to_canvas is not None]
    segment_of = {f.index: f.segment for f in placed}
    previous: dict[Any, int] = {}  # segment -> last registered frame index
    references = {}
    for f in placed:
        ref = f.reference
        if ref is None:
            ref = previous.get(f.segment)
        elif segment_of.get(ref, object()) != f.segment or ref == f.index:
            log.warning("frame %d: reference %s is not a registered frame", f.index, ref)
            ref = None
        if ref is not None:
            references[f.index] = int(ref)
        previous[f.segment] = f.index
    return references


def _step_errors(
    frames: list[FrameEntry], gt: list[np.ndarray], size: tuple[int, int]
) -> dict[int, float]:
    """Corner error (px) of each registered frame's placement relative to its reference.

    Estimate inv(P_ref) @ P_i (P = the report's H_to_canvas), truth inv(G_ref) @ G_i (G =
    H_frame_to_source), both in full-size frame pixels; references from `_frame_references`.
    """
    poses = {
        f.index: np.asarray(f.H_to_canvas, np.float64)
        for f in frames
        if f.status == REGISTERED and f.H_to_canvas is not None
    }
    errors = {}
    for index, ref in _frame_references(frames).items():
        if max(index, ref) >= len(gt):
            log.warning("frame %d or %d has no ground truth (%d frames)", index, ref, len(gt))
            continue
        H_est = np.linalg.solve(poses[ref], poses[index])
        H_gt = np.linalg.solve(gt[ref], gt[index])
        errors[index] = corner_error(H_est, H_gt, size)
    return errors


def _quality_vs_error(
    frames: list[FrameEntry], errors: dict[int, float] | None
) -> dict[str, float]:
    """How the report's per-frame `quality` and `flagged` predict the corner error (`errors`).

    Over the frames with an error but the reference frame (error 0 by construction, never
    scored): `quality_rho`, the Spearman correlation of score and error over the scored ones
    (negative: lower score, larger error); `bad_frames`, those more than
    ACCURATE_CORNER_ERROR_PX off; `bad_caught`, the fraction of them flagged (a frame without a
    score is never flagged: a miss); `good_flagged`, the fraction of the others flagged. NaN
    without errors, or (but `bad_frames`) when no frame has a score (older reports).
    """
    nan = math.nan
    if errors is None:
        return {"quality_rho": nan, "bad_frames": nan, "bad_caught": nan, "good_flagged": nan}
    entries = {f.index: f for f in frames}
    judged = sorted(errors)[1:]  # the first is the reference frame
    error = np.array([errors[i] for i in judged], np.float64)
    score = np.array([entries[i].quality for i in judged], np.float64)  # None -> nan
    flagged = np.array([entries[i].flagged for i in judged], bool)
    bad = error > ACCURATE_CORNER_ERROR_PX
    scored = bool(np.isfinite(score).any())

    def flagged_share(group: np.ndarray) -> float:
        return float(flagged[group].mean()) if scored and group.any() else nan

    return {
        "quality_rho": spearman(score, error),
        "bad_frames": float(bad.sum()),
        "bad_caught": flagged_share(bad),
        "good_flagged": flagged_share(~bad),
    }


def _leading_accurate(frames: list[FrameEntry], errors: dict[int, float] | None) -> int:
    """Registered (and accurate, when errors are given) frames from the start until a failure."""
    count = 0
    for f in frames:
        if f.status == SKIPPED:
            continue
        if f.status == FAILED:
            break
        if errors is not None and not errors.get(f.index, math.inf) <= ACCURATE_CORNER_ERROR_PX:
            break
        count += 1
    return count


def _unique_stems(videos: Sequence[Path]) -> list[str]:
    """Each video's file stem (a frame folder's name), made unique with "-2", "-3", ..."""
    stems: list[str] = []
    for video in videos:
        stem = base = video.name if video.is_dir() else video.stem
        k = 1
        while stem in stems:
            k += 1
            stem = f"{base}-{k}"
        stems.append(stem)
    return stems


@dataclass(frozen=True)
class FidelityReference:
    """A video's truth for the mosaic-fidelity scores, shared by all its runs."""

    truth: list[np.ndarray]  # H_frame_to_source per frame index
    source: SourceTruth
    oracle: FidelityScores  # the mean of the frames placed by the truth


def _fov_masker(config: Config) -> Callable[[np.ndarray], np.ndarray | None]:
    """The frames' field-of-view mask as the pipeline composes them (None: no mask)."""
    pre = config.preprocess

    def mask_of(image: np.ndarray) -> np.ndarray | None:
        if not pre.fov_mask:
            return None
        return field_of_view_mask(
            to_gray(image, pre.green_channel), pre.fov_threshold, pre.fov_erode_px
        )

    return mask_of


def fidelity_reference(path: Path, config: Config) -> FidelityReference | None:
    """Truth, source and oracle scores of a video, or None without ground truth or a readable
    source photograph (then one warning). The oracle reads the video once more, frame by frame.
    """
    gt_file = gt_path_for(path)
    if not gt_file.is_file():
        return None
    source_file = source_path(gt_file)
    try:
        if source_file is None:
            raise InputError(f"{gt_file} names no source image")
        image = read_image(source_file)
    except InputError as exc:
        log.warning("no fidelity scores for %s: %s", path, exc)
        return None
    start = time.perf_counter()
    truth = load_ground_truth(gt_file)
    source = prepare_source(image)
    frames = _reread(path, config.pipeline.step, config.pipeline.max_frames)()
    oracle = oracle_fidelity(
        frames, truth, source, _fov_masker(config), config.compose.max_canvas_px
    )
    log.info(
        "oracle of %s: fidelity %.3f, good area %.3f (%.1f s)",
        path.name,
        oracle.fidelity,
        oracle.good_area,
        time.perf_counter() - start,
    )
    return FidelityReference(truth, source, oracle)


def _fidelity_scores(
    result: MosaicResult, reference: FidelityReference, size: tuple[int, int]
) -> dict[str, float]:
    """The main mosaic's fidelity and good area (its frames' reported poses map into its
    image), and the video's oracle, as VideoResult fields."""
    start = time.perf_counter()
    frames = result.report.frames
    main = result.main
    scores = FidelityScores()
    if main is not None:
        poses = {
            f.index: np.asarray(f.H_to_canvas, np.float64)
            for f in frames
            if f.status == REGISTERED and f.segment == main.index and f.H_to_canvas is not None
        }
        image = main.image
        content = image.any(axis=2) if image.ndim == 3 else image > 0
        scanned = [f.index for f in frames]
        scores = mosaic_fidelity(
            image, content, poses, reference.truth, reference.source, size, scanned
        )
    log.info(
        "fidelity %.3f, good area %.3f (oracle %.3f, %.3f; %.1f s)",
        scores.fidelity,
        scores.good_area,
        reference.oracle.fidelity,
        reference.oracle.good_area,
        time.perf_counter() - start,
    )
    return {
        "fidelity": scores.fidelity,
        "good_area": scores.good_area,
        "oracle_fidelity": reference.oracle.fidelity,
        "oracle_good_area": reference.oracle.good_area,
    }


def evaluate_video(
    path: Path,
    config: Config,
    extractor: FeatureExtractor,
    progress: bool = False,
    report_path: Path | None = None,
    fidelity: bool = True,
    reference: FidelityReference | None = None,
) -> VideoResult:
    """Run the pipeline over a video (failed frames skipped) and score it against its truth.

    The frames' poses are the ones `mosaic build` reports: after the strategy's refinement
    (keyframes: pose graph) and re-rendering, so the video is read twice. With `report_path`,
    that report (with the input, as `mosaic build` writes it) is saved there as JSON.

    With `fidelity`, the main mosaic is scored against the source photograph (nan without
    one); `reference` is the video's `fidelity_reference`, computed here when None (pass it
    to score several runs of one video with one oracle).
    """
    config = with_overrides(config, pipeline={"on_failure": "skip"})
    run = run_video(  # refined poses, as `mosaic build` reports
        path,
        config,
        Outputs(report=report_path),
        extractor=extractor,
        progress=f"{extractor.detector.name} {path.name}" if progress else None,
        salvage=False,
    )
    result, info = run.result, run.info
    size = (info.width, info.height)
    frames, summary = result.report.frames, result.report.summary
    gt_file = gt_path_for(path)
    errors: dict[int, float] | None = None
    steps: dict[int, float] = {}
    parts: dict[str, float] = {}
    if gt_file.is_file() and size is not None:
        gt = load_ground_truth(gt_file)
        placed = list(_placed_against_truth(frames, gt))  # each frame's warning once
        errors, parts = _corner_errors(placed, size), _view_parts(placed, size)
        steps = _step_errors(frames, gt, size)
    step_values = np.array(list(steps.values()))
    # every frame the video holds counts, those the gate skipped too (a frame skipped as
    # blurred is not placed: counting it out flattered gating); only undecodable ones do not
    undecodable = sum(f.reason == UNDECODABLE for f in frames)
    decoded = max(summary.frames_read - undecodable, 1)
    values = np.array(list(errors.values())) if errors else np.zeros(0)
    drift = math.nan
    if len(values) >= 2:
        idx = np.array(list(errors), dtype=np.float64)  # type: ignore[arg-type]
        drift = float(np.polyfit(idx, values, 1)[0])
    accurate = int((values <= ACCURATE_CORNER_ERROR_PX).sum()) if errors is not None else 0
    if fidelity and reference is None:
        reference = fidelity_reference(path, config)
    scores = _fidelity_scores(result, reference, size) if fidelity and reference else {}
    return VideoResult(
        detector=f"{extractor.detector.name}/{config.pipeline.strategy}",
        video=str(path),
        has_ground_truth=errors is not None,
        frames=summary.frames_read,
        registered=summary.registered,
        failed=summary.failed,
        skipped=summary.skipped,
        registered_fraction=summary.registered / decoded,
        frames_until_failure=_leading_accurate(frames, errors),
        frames_until_failure_pipeline=summary.frames_until_failure,
        accurate_fraction=accurate / decoded if errors is not None else math.nan,
        mean_error_px=float(values.mean()) if values.size else math.nan,
        median_error_px=float(np.median(values)) if values.size else math.nan,
        max_error_px=float(values.max()) if values.size else math.nan,
        drift_px_per_frame=drift,
        **parts,
        mean_inliers=float(summary.mean_inliers),
        fps=float(summary.fps),
        step_median_px=float(np.median(step_values)) if step_values.size else math.nan,
        step_p90_px=float(np.percentile(step_values, 90)) if step_values.size else math.nan,
        **_quality_vs_error(frames, errors),
        **scores,
        model_counts={**dict.fromkeys(MOTION_MODELS, 0), **summary.models},
        segments=summary.segments,
        precision=summary.precision,
        errors=sorted(errors.items()) if errors else [],
        step_errors=sorted(steps.items()),
    )


def run_video_evaluation(
    paths: Sequence[str | Path],
    config: Config,
    detectors: Sequence[str],
    out_dir: str | Path,
    explicit: bool = True,
    progress: bool = False,
    strategies: Sequence[str] = ("keyframes", "chain"),
    fidelity: bool = True,
    previous: Sequence[VideoResult] = (),
) -> tuple[list[VideoResult], list[dict[str, Any]]]:
    """Evaluate every detector with every strategy on every video; write tables and plots
    (with `previous`, an earlier run's results, the differences against it too).

    Each run's report goes to `reports/<video stem>__<detector>__<strategy>.json` in `out_dir`
    (listed in the same order as the results under the JSON's `meta.reports`). With
    `fidelity`, each video's oracle is computed once and shared by its runs.
    """
    videos = find_videos(paths)
    report_dir = make_folder(Path(out_dir).expanduser() / "reports")
    extractors = make_extractors(config, detectors, explicit)
    results, reports = [], []
    for video, stem in zip(videos, _unique_stems(videos), strict=True):
        reference = fidelity_reference(video, config) if fidelity else None
        for name, (cfg, extractor) in extractors.items():
            for strategy in strategies:
                cfg_strategy = with_overrides(cfg, pipeline={"strategy": strategy})
                report = report_dir / f"{stem}__{name}__{strategy}.json"
                results.append(
                    evaluate_video(
                        video,
                        cfg_strategy,
                        extractor,
                        progress,
                        report,
                        fidelity=reference is not None,
                        reference=reference,
                    )
                )
                reports.append(str(report.relative_to(report_dir.parent)))
    summary = summarize_videos(results)
    meta = {
        "videos": [str(v) for v in videos],
        "detectors": list(extractors),
        "config": dataclasses.asdict(config),
        "reports": reports,
        "fidelity": fidelity,
    }
    write_video_outputs(results, summary, out_dir, meta, previous)
    warn_of_precisions(results, previous)
    return results, summary
