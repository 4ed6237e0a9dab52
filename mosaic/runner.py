"""One video, end to end: the single code path of `mosaic build`, `batch`, `evaluate` and `bench`.

`run_video` opens the input, streams its frames through `MosaicBuilder`, finishes (pose-graph
refinement, then the re-render from a second read of the input), and writes the outputs it is
given: the mosaic segment(s) and a thumbnail first, the report last, each atomically (temporary
file, then `os.replace`). The report's `summary.complete` is true only for a run that ended
normally, so a report saying so means every output beside it is whole (`mosaic batch --resume`
relies on it).

Every `[pipeline] checkpoint_every_s` while streaming (and once more when streaming ends, if a
checkpoint was written), the live canvas and the report so far are written the same way, with
`summary.complete = false` and `summary.checkpoint = true`: a run killed outright (SIGKILL, out
of memory, power loss) leaves its last checkpoint; the final write replaces it.

Ctrl-C while streaming or while refining / re-rendering, or an exception in either, does not lose
the run (`salvage`): the live canvas and the unrefined poses of the frames processed so far are
written instead, with `summary.interrupted` (and `summary.error` after an exception) and
`summary.complete = false`; the caller reads `VideoRun.interrupted` / `VideoRun.error` for its
message and exit code (the traceback is logged at INFO level: `-v`, or a batch video's log).

Also here, as the one home of "what is a video": the video suffixes and what makes a folder a
video (a folder of frames).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from mosaic.allocator import keep_freed_memory
from mosaic.config import Config
from mosaic.errors import MosaicError, OutputError
from mosaic.features import FeatureExtractor
from mosaic.io import (
    IMAGE_READ_SUFFIXES,
    Frame,
    FrameSource,
    VideoInfo,
    check_output_path,
    expected_frames,
    open_frames,
    write_image,
    write_json,
)
from mosaic.pipeline import FrameRecord, MosaicBuilder, MosaicResult, Reread
from mosaic.report import BuildReport, Summary
from mosaic.viz import Viewer

log = logging.getLogger(__name__)

#: Suffixes (lower case) of the files taken for videos when searching folders.
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".wmv")
#: Longer side of the thumbnail of the main mosaic (pixels).
THUMBNAIL_SIDE_PX = 320
#: Frames with a shorter side than this give the detectors too few keypoints to register.
MIN_FRAME_SIDE_PX = 64

Opener = Callable[[Path, int, int], FrameSource]


def is_frame_folder(path: Path) -> bool:
    """Whether `path` is a folder holding image files: a video given as its frames."""
    return path.is_dir() and any(
        f.suffix.lower() in IMAGE_READ_SUFFIXES and f.is_file() for f in path.iterdir()
    )


def reread_frames(
    video: Path, step: int, max_frames: int, progress: bool = False, opener: Opener = open_frames
) -> Callable[[], Iterator[tuple[int, np.ndarray | None]]]:
    """A second (third, ...) pass over the input: `(index, image)` of every frame, for the
    re-render from refined poses (and the evaluation's oracle); `progress`: a "render" bar."""

    def frames() -> Iterator[tuple[int, np.ndarray | None]]:
        with opener(video, step, max_frames) as source:
            total = expected_frames(source.info, step, max_frames)
            bar = tqdm(
                source, total=total, unit="frame", desc="render", leave=False, disable=not progress
            )
            for frame in bar:
                yield frame.index, frame.image

    return frames


def segment_path(output: Path, index: int) -> Path:
    """Where segment `index` of a run with several segments is written, beside `output`."""
    return output.with_name(f"{output.stem}_seg{index:03d}{output.suffix}")


@dataclass(frozen=True)
class Outputs:
    """The files a run writes; None: not written. Segments go beside the mosaic when several."""

    mosaic: Path | None = None
    report: Path | None = None
    thumbnail: Path | None = None

    def checked(self) -> Outputs:
        """The same paths, each checked writable before the run (folder exists, format known,
        the file can be created or replaced: `io.check_output_path`)."""
        return Outputs(*(None if p is None else check_output_path(p) for p in self.paths()))

    def paths(self) -> tuple[Path | None, Path | None, Path | None]:
        return self.mosaic, self.report, self.thumbnail


@dataclass(frozen=True)
class VideoRun:
    """What one run of a video gave: the input, the result, and the report as written."""

    info: VideoInfo
    result: MosaicResult
    report: BuildReport  # `result.report` with the input, the output paths, completeness
    interrupted: bool = False  # Ctrl-C: the frames so far, live canvas, unrefined poses
    error: str | None = None  # an exception after which the same was written instead

    @property
    def complete(self) -> bool:
        return not self.interrupted and self.error is None

    @property
    def summary(self) -> Summary:
        return self.report.summary


def one_line(exc: BaseException) -> str:
    """An exception as `Type: first line of its text`, for a one-line message (a run's
    error, a pair's failure, the command line's internal error)."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


class _Checkpoints:
    """Writes the live mosaic and the report so far every `every_s` seconds (0: never)."""

    def __init__(
        self,
        builder: MosaicBuilder,
        outputs: Outputs,
        info: VideoInfo,
        started: float,
        every_s: float,
    ) -> None:
        self.builder, self.outputs, self.info, self.started = builder, outputs, info, started
        self.every_s = every_s if outputs.mosaic is not None or outputs.report is not None else 0
        self.last = time.perf_counter()
        self.written = 0
        self._warned = False

    def due(self) -> None:
        """Write one if `every_s` has passed since the start or the last one."""
        if self.every_s > 0 and time.perf_counter() - self.last >= self.every_s:
            self.write()

    def write(self) -> None:
        """Write the checkpoint now; a failure is warned (once) and the run goes on."""
        try:
            result = self.builder.snapshot()
            _write_outputs(result, self.outputs, self.info, self.started, checkpoint=True)
        except OutputError as exc:
            if not self._warned:
                log.warning("checkpoint not written: %s", exc)
                self._warned = True
        else:
            self.written += 1
            log.info("checkpoint %d: %d frames", self.written, len(self.builder.records))
        self.last = time.perf_counter()


def _stream(
    builder: MosaicBuilder,
    frames: Iterable[Frame],
    total: int | None,
    progress: str | None,
    on_record: Callable[[FrameRecord], None] | None,
    checkpoints: _Checkpoints | None = None,
) -> None:
    with ExitStack() as stack:
        bar = None
        if progress is not None:
            stack.enter_context(logging_redirect_tqdm())
            bar = stack.enter_context(
                tqdm(total=total, unit="frame", desc=progress, dynamic_ncols=True)
            )
        registered = 0
        for record in builder.stream(frames):
            if on_record is not None:
                on_record(record)
            if bar is not None:
                registered += record.status == "registered"
                bar.set_postfix(registered=registered, refresh=False)
                bar.update()
            if checkpoints is not None:
                checkpoints.due()
            if builder.stopped:
                break


def run_video(
    video: str | Path,
    config: Config,
    outputs: Outputs = Outputs(),
    *,
    extractor: FeatureExtractor | None = None,
    viewer: Viewer | Callable[[VideoInfo], Viewer] | None = None,
    progress: str | None = None,
    on_record: Callable[[FrameRecord], None] | None = None,
    wrap_frames: Callable[[FrameSource], Iterable[Frame]] | None = None,
    rerender: bool = True,
    salvage: bool = True,
    opener: Opener = open_frames,
) -> VideoRun:
    """Build the mosaic of one video and write `outputs` (the report last); see the module doc.

    `viewer`: a viewer, or a factory called with the opened input's `VideoInfo`. `progress`:
    the label of a frame progress bar (None: no bar). `on_record` sees each `FrameRecord` as it
    is registered; `wrap_frames` wraps the opened frame source (e.g. to time decoding).
    `rerender` False keeps the live canvas (no second read). `salvage` False lets Ctrl-C and
    exceptions propagate with nothing written (and writes no checkpoints). `opener` opens the
    input (`io.open_frames`).

    Raises `MosaicError` for an unusable input or output, and (after writing the report) when
    no frame could be placed on a mosaic that `outputs` asks for.
    """
    keep_freed_memory()
    video = Path(video)
    started = time.perf_counter()
    outputs = outputs.checked()
    step, max_frames = config.pipeline.step, config.pipeline.max_frames
    interrupted, error = False, None
    with opener(video, step, max_frames) as source:
        info = source.info
        if min(info.width, info.height) < MIN_FRAME_SIDE_PX:
            log.warning(
                "frames of %dx%d px are too small to register (the detectors need at least %d "
                "px a side): expect few registered frames",
                info.width, info.height, MIN_FRAME_SIDE_PX,
            )  # fmt: skip
        made = viewer(info) if callable(viewer) else viewer
        builder = MosaicBuilder(config, extractor=extractor, viewer=made)
        frames = source if wrap_frames is None else wrap_frames(source)
        every_s = config.pipeline.checkpoint_every_s if salvage else 0.0
        checkpoints = _Checkpoints(builder, outputs, info, started, every_s)
        total = expected_frames(info, step, max_frames)
        try:
            _stream(builder, frames, total, progress, on_record, checkpoints)
            if checkpoints.written:  # a long run: keep what streaming gave while it finishes
                checkpoints.write()
        except KeyboardInterrupt:
            if not salvage:
                raise
            interrupted = True  # the caller says so; the log keeps it
            log.info("interrupted: writing the partial mosaic and report")
        except Exception as exc:
            if not salvage:
                raise
            error = f"failed while registering: {one_line(exc)}"
            log.info("%s; writing the mosaic so far", error, exc_info=True)
    if interrupted or error is not None:
        result = builder.finish(interrupted=True)
    else:
        reread = reread_frames(video, step, max_frames, progress is not None, opener)
        result = _finish(builder, reread if rerender else None, salvage)
        if isinstance(result, str | KeyboardInterrupt):
            interrupted = isinstance(result, KeyboardInterrupt)
            error = None if interrupted else result
            result = builder.finish(interrupted=True)
    report = _write_outputs(result, outputs, info, started, interrupted, error)
    return VideoRun(info, result, report, interrupted, error)


def _finish(
    builder: MosaicBuilder, reread: Reread | None, salvage: bool
) -> MosaicResult | str | KeyboardInterrupt:
    """Refine and re-render; with `salvage`, a Ctrl-C or the error message instead of raising."""
    try:
        return builder.finish(reread=reread)
    except KeyboardInterrupt as exc:
        if not salvage:
            raise
        log.info("interrupted while refining / rendering: writing the live mosaic")
        return exc
    except Exception as exc:
        if not salvage:
            raise
        error = f"failed while refining / rendering: {one_line(exc)}"
        log.info("%s; writing the live mosaic and unrefined poses", error, exc_info=True)
        return error


def thumbnail(image: np.ndarray, side_px: int = THUMBNAIL_SIDE_PX) -> np.ndarray:
    """`image` shrunk so that its longer side is at most `side_px` (area interpolation)."""
    h, w = image.shape[:2]
    scale = side_px / max(h, w)
    if scale >= 1.0:
        return image
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _write_outputs(
    result: MosaicResult,
    outputs: Outputs,
    info: VideoInfo,
    started: float,
    interrupted: bool = False,
    error: str | None = None,
    checkpoint: bool = False,
) -> BuildReport:
    """Segments, mosaic, thumbnail, then the report (its `summary.complete` marks them whole).

    `checkpoint`: the live state of a run still going (`summary.checkpoint`, never complete)."""
    report = dataclasses.replace(
        result.report, input=dataclasses.replace(info, path=str(info.path))
    )
    main = result.main
    if outputs.mosaic is not None and main is not None:
        output = outputs.mosaic
        paths = [output]
        if len(result.segments) > 1:
            paths = [segment_path(output, segment.index) for segment in result.segments]
            for segment, path in zip(result.segments, paths, strict=True):
                write_image(path, segment.image)
        segments = [
            dataclasses.replace(entry, mosaic=str(path))
            for entry, path in zip(report.segments, paths, strict=True)
        ]
        write_image(output, main.image)
        thumbnail_path = None
        if outputs.thumbnail is not None:
            write_image(outputs.thumbnail, thumbnail(main.image))
            thumbnail_path = str(outputs.thumbnail)
        report = dataclasses.replace(
            report,
            segments=segments,
            mosaic=str(output),
            main_segment=main.index,
            thumbnail=thumbnail_path,
        )
    report = dataclasses.replace(
        report, summary=_written_summary(report.summary, started, interrupted, error, checkpoint)
    )
    if outputs.report is not None:
        write_json(outputs.report, report.to_dict())
    if outputs.mosaic is not None and main is None and not checkpoint:
        written = f" (report: {outputs.report})" if outputs.report is not None else ""
        raise MosaicError(f"no frame could be placed on the mosaic{written}")
    return report


def _written_summary(
    summary: Summary, started: float, interrupted: bool, error: str | None, checkpoint: bool
) -> Summary:
    """The summary as written: complete only for a run that ended normally (else the live
    canvas and poses were kept: not re-rendered), the error, the wall time."""
    complete = not interrupted and error is None and not checkpoint
    if not complete:
        tracking = dataclasses.replace(summary.tracking, rerendered=False)
        summary = dataclasses.replace(summary, interrupted=interrupted, tracking=tracking)
    return dataclasses.replace(
        summary,
        complete=complete,
        checkpoint=checkpoint,
        error=error if error is not None else summary.error,
        wall_time_s=round(time.perf_counter() - started, 3),
    )
