"""`mosaic bench`: speed of the whole pipeline per detector, measured in one run.

A synthetic video is rendered from the shipped fundus image, then every detector processes it
with the same settings. Per stage we report the median and p90 wall time per frame, end-to-end
frames/s and the ratio to the SIFT pipeline; variants show what detecting on a smaller image
gains, what overlapping the extraction of the next frame with the registration of the current
one (`[pipeline] overlap`) gains, and what the rerun recording costs. A last table times the whole
`mosaic build` of a realistic synthetic video, from the start to the written mosaic and report,
next to the same run's streaming rate: the final passes (pose graph, re-render, blending) show
as the gap between the two. Ratios are what to read: the machines are noisy, so only numbers
from the same run are compared.
"""

from __future__ import annotations

import dataclasses
import logging
import resource
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mosaic.config import Config, with_overrides
from mosaic.errors import ConfigError, DetectorWeightsError, MosaicError
from mosaic.features import FeatureExtractor, cpu_has_native_bfloat16, resolve_precision
from mosaic.io import Frame, sample_image_path
from mosaic.pipeline import FrameRecord
from mosaic.report import STAGES
from mosaic.runner import Outputs, run_video
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from mosaic.viz import Viewer

log = logging.getLogger(__name__)

WARMUP_FRAMES = 3  # first frames pay one-off costs (graph freezing, allocations)
COLUMNS = ("decode", *STAGES)


@dataclass(frozen=True)
class BenchRow:
    """Timings of one pipeline variant over the benchmark video."""

    name: str
    detector: str
    stage_ms: dict[str, tuple[float, float]]  # stage -> (median, p90) per frame
    frame_ms: tuple[float, float]  # whole frame (median, p90), decode included
    fps: float  # frames per second end to end, after warm-up
    registered: int
    frames: int
    peak_rss_mb: float  # process peak so far (monotone over the run)
    overlap: bool | None = None  # next frame extracted meanwhile (auto: as chosen; None: undecided)
    extraction: str | None = None  # ... serial, overlapped, or with turns (`OverlapTrial`)
    notes: dict[str, Any] = field(default_factory=dict)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _median_p90(values: list[float]) -> tuple[float, float]:
    if not values:
        return (float("nan"), float("nan"))
    return float(np.median(values)), float(np.percentile(values, 90))


def cuda_available() -> bool:
    """Whether torch sees a CUDA GPU (then the bench adds a GPU row for GLAMpoints)."""
    import torch

    return bool(torch.cuda.is_available())


def native_bfloat16() -> bool:
    """Whether this CPU has bfloat16 in hardware (the GLAMpoints precision variant is measured)."""
    return cpu_has_native_bfloat16()


def _timed(frames: Iterable[Frame], out: list[float]) -> Iterator[Frame]:
    """Yield the frames, appending each one's decode time (ms) to `out`."""
    it = iter(frames)
    while True:
        t0 = time.perf_counter()
        frame = next(it, None)
        if frame is None:
            return
        out.append((time.perf_counter() - t0) * 1e3)
        yield frame


def run_variant(
    name: str,
    video: Path,
    config: Config,
    viewer: Viewer | None = None,
    extractor: FeatureExtractor | None = None,
) -> BenchRow:
    """Process the whole video once (`runner.run_video`, as `mosaic build` does, without the
    re-render) and collect per-stage timings.

    `frame` is the wall time between two registered frames as the caller sees them: with
    `[pipeline] overlap` on (or chosen) the extraction of the next frame runs meanwhile in
    another thread.
    """
    decode: list[float] = []
    frame_ms: list[float] = []
    stage: dict[str, list[float]] = {s: [] for s in STAGES}
    count = 0
    last = timed_from = time.perf_counter()

    def on_record(record: FrameRecord) -> None:
        nonlocal count, last, timed_from
        t0, last = last, time.perf_counter()
        count += 1
        if count == WARMUP_FRAMES:
            timed_from = last
        if count <= WARMUP_FRAMES:
            return
        frame_ms.append((last - t0) * 1e3)
        for s in STAGES:
            stage[s].append(record.stage_ms.get(s, 0.0))

    run = run_video(
        video,
        config,
        extractor=extractor,
        viewer=viewer,
        on_record=on_record,
        wrap_frames=lambda source: _timed(source, decode),
        rerender=False,
        salvage=False,
    )
    elapsed = last - timed_from
    summary = run.summary
    decode = decode[WARMUP_FRAMES:]
    stage_ms = {"decode": _median_p90(decode)} | {s: _median_p90(v) for s, v in stage.items()}
    timed = max(count - WARMUP_FRAMES, 0)
    return BenchRow(
        name=name,
        detector=config.features.detector,
        stage_ms=stage_ms,
        frame_ms=_median_p90(frame_ms),
        fps=timed / elapsed if elapsed > 0 else float("nan"),
        registered=summary.registered,
        frames=summary.frames_read,
        peak_rss_mb=_peak_rss_mb(),
        overlap=summary.overlap,
        extraction=summary.extraction,
    )


@dataclass(frozen=True)
class BuildRow:
    """The whole `mosaic build` of one video: streaming, then the final passes and writing."""

    name: str
    frames: int
    registered: int
    streaming_s: float  # from the start of the run to the last frame registered
    wall_s: float  # from the start of the run to the mosaic and report written

    @property
    def streaming_fps(self) -> float:
        return self.frames / self.streaming_s if self.streaming_s > 0 else float("nan")

    @property
    def whole_fps(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else float("nan")

    @property
    def final_s(self) -> float:
        """Pose graph, re-render, blending and writing: what streaming does not cover."""
        return self.wall_s - self.streaming_s


def run_build(
    name: str, video: Path, config: Config, extractor: FeatureExtractor | None = None
) -> BuildRow:
    """`mosaic build VIDEO` as the command runs it (re-render, mosaic and report written into
    a temporary folder), timed from the start of the run; the model is loaded before."""
    last = started = time.perf_counter()

    def on_record(record: FrameRecord) -> None:
        nonlocal last
        last = time.perf_counter()

    with tempfile.TemporaryDirectory(prefix="mosaic-bench-build-") as tmp:
        outputs = Outputs(mosaic=Path(tmp) / "mosaic.png", report=Path(tmp) / "mosaic.json")
        started = last = time.perf_counter()
        run = run_video(video, config, outputs, extractor=extractor, on_record=on_record)
        wall = time.perf_counter() - started
    return BuildRow(
        name=name,
        frames=run.summary.frames_read,
        registered=run.summary.registered,
        streaming_s=last - started,
        wall_s=wall,
    )


def run_build_bench(
    detector: str,
    size: tuple[int, int] = (660, 350),
    n_frames: int = 113,
    config: Config | None = None,
    seed: int = 0,
) -> BuildRow:
    """The whole build of a realistic synthetic video (`mosaic synth --realistic`) of
    `n_frames` at `size`, rendered from the shipped image, with `detector`."""
    cfg = with_overrides(config or Config(), features={"detector": detector})
    extractor = FeatureExtractor(cfg.features)
    with tempfile.TemporaryDirectory(prefix="mosaic-bench-") as tmp:
        video = Path(tmp) / f"realistic_{size[0]}x{size[1]}.mp4"
        params = SynthParams.realistic(n_frames=n_frames, size=size, seed=seed)
        write_synthetic_video(sample_image_path(), video, params)
        return run_build(f"{detector} (mosaic build)", video, cfg, extractor)


def format_build_table(rows: list[BuildRow]) -> str:
    """Whole builds: frames, streaming rate, wall clock to the written mosaic, the ratio."""
    header = ["whole build", "frames", "reg", "stream s", "stream fps", "wall s", "fps", "final s"]
    header.append("x stream")
    lines = [
        [
            r.name,
            str(r.frames),
            str(r.registered),
            f"{r.streaming_s:.2f}",
            f"{r.streaming_fps:.1f}",
            f"{r.wall_s:.2f}",
            f"{r.whole_fps:.1f}",
            f"{r.final_s:.2f}",
            f"{r.whole_fps / r.streaming_fps:.2f}",
        ]
        for r in rows
    ]
    return _aligned(header, lines)


def make_video(folder: Path, size: tuple[int, int], n_frames: int, seed: int = 0) -> Path:
    """The benchmark video: synthetic, rendered from the shipped sample image."""
    video = folder / f"bench_{size[0]}x{size[1]}.mp4"
    params = SynthParams(n_frames=n_frames, size=size, seed=seed)
    write_synthetic_video(sample_image_path(), video, params)
    return video


def run_bench(
    detectors: list[str],
    size: tuple[int, int] = (660, 350),
    n_frames: int = 100,
    config: Config | None = None,
    viewer_factory: Callable[[Path], Viewer] | None = None,
    progress: Callable[[str], None] = lambda _: None,
    scales: Sequence[float] = (),
    explicit: bool = True,
) -> list[BenchRow]:
    """Every detector on one synthetic video, then variants of the first one: GLAMpoints on the
    GPU (where CUDA is available) and in the other precision (where the CPU has bfloat16 in
    hardware), each detection scale in `scales`, with `[pipeline] overlap` on and off (those the
    config does not fix), and with the rerun recording.

    A detector that cannot be built (GLAMpoints without its weights, a descriptor it lacks)
    raises `DetectorWeightsError` / `ConfigError` when `explicit` (the user named it), else it is
    skipped with a warning. Errors while running are never swallowed."""
    config = config or Config()
    rows: list[BenchRow] = []
    with tempfile.TemporaryDirectory(prefix="mosaic-bench-") as tmp:
        video = make_video(Path(tmp), size, n_frames)
        for name in detectors:
            progress(name)
            cfg = with_overrides(config, features={"detector": name})
            try:
                extractor = FeatureExtractor(cfg.features)
            except (DetectorWeightsError, ConfigError) as exc:
                if explicit:
                    raise
                log.warning("detector %s skipped: %s", name, exc)
                continue
            rows.append(run_variant(name, video, cfg, extractor=extractor))
        if not rows:
            return rows
        base = rows[0]
        cfg = with_overrides(config, features={"detector": base.detector})
        if base.detector == "glampoints" and cuda_available():
            progress(f"{base.name} on the GPU")
            gpu = with_overrides(cfg, features={"device": "cuda"})
            rows.append(run_variant(f"{base.name} (cuda)", video, gpu))
        if base.detector == "glampoints" and cfg.features.device == "cpu" and native_bfloat16():
            other = "float32" if resolve_precision(cfg.features, True) == "bfloat16" else "bfloat16"
            progress(f"{base.name} in {other}")
            precise = with_overrides(cfg, features={"precision": other})
            rows.append(run_variant(f"{base.name} ({other})", video, precise))
        for scale in scales:
            progress(f"{base.name} detecting at scale {scale:g}")
            scaled = with_overrides(cfg, features={"detect_scale": scale})
            rows.append(run_variant(f"{base.name} (scale {scale:g})", video, scaled))
        for mode, label in (("on", "overlap"), ("off", "no overlap")):
            if cfg.pipeline.overlap != mode:
                progress(f"{base.name} with {label}")
                fixed = with_overrides(cfg, pipeline={"overlap": mode})
                rows.append(run_variant(f"{base.name} ({label})", video, fixed))
        if viewer_factory is not None:
            progress(f"{base.name} with --rerun save")
            rrd = Path(tmp) / "bench.rrd"
            viewer = viewer_factory(rrd)
            row = run_variant(f"{base.name} (--rerun save)", video, cfg, viewer=viewer)
            size_mb = rrd.stat().st_size / 2**20 if rrd.exists() else float("nan")
            per_1000 = round(size_mb * 1000 / max(row.frames, 1), 1)
            rows.append(dataclasses.replace(row, notes={"rrd_mb_per_1000_frames": per_1000}))
    return rows


def profile_pipeline(
    detector: str,
    size: tuple[int, int] = (660, 350),
    n_frames: int = 60,
    config: Config | None = None,
    top: int = 20,
) -> str:
    """cProfile of a serial run (`overlap` off, so every stage runs in the profiled thread):
    the `top` functions by own time, as pstats prints them."""
    import cProfile
    import io
    import pstats

    cfg = with_overrides(config or Config(), features={"detector": detector})
    cfg = with_overrides(cfg, pipeline={"overlap": "off"})
    with tempfile.TemporaryDirectory(prefix="mosaic-profile-") as tmp:
        video = make_video(Path(tmp), size, n_frames)
        profiler = cProfile.Profile()
        profiler.enable()
        run_variant(detector, video, cfg)
        profiler.disable()
    out = io.StringIO()
    stats = pstats.Stats(profiler, stream=out).strip_dirs().sort_stats("tottime")
    stats.print_stats(top)
    return out.getvalue()


def format_table(rows: list[BenchRow], reference: str = "sift") -> str:
    """Rows = variants; columns = median ms per stage, frame median/p90, fps, ratio to SIFT."""
    ref = next((r for r in rows if r.name == reference), None)
    header = ["variant", *COLUMNS, "frame", "p90", "fps", f"x{reference}", "reg", "RSS MB", "ovl"]
    lines = []
    for r in rows:
        ratio = f"{r.fps / ref.fps:.2f}" if ref is not None and ref.fps > 0 else "-"
        lines.append(
            [
                r.name,
                *(f"{r.stage_ms[c][0]:.1f}" for c in COLUMNS),
                f"{r.frame_ms[0]:.1f}",
                f"{r.frame_ms[1]:.1f}",
                f"{r.fps:.1f}",
                ratio,
                f"{r.registered}/{r.frames}",
                f"{r.peak_rss_mb:.0f}",
                {"serial": "off", "overlapped": "on", "turns": "turns"}.get(
                    r.extraction or "", "-"
                ),
            ]
        )
    return _aligned(header, lines)


def _aligned(header: list[str], lines: list[list[str]]) -> str:
    """A plain-text table: the first column left-aligned, the others right-aligned."""
    widths = [max([len(h), *(len(line[i]) for line in lines)]) for i, h in enumerate(header)]
    fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
    return "\n".join([fmt.format(*header), *(fmt.format(*line) for line in lines)])


def environment() -> dict[str, Any]:
    """Thread settings and hardware facts printed with the table."""
    import os
    import platform

    import cv2
    import torch

    return {
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "torch_interop_threads": torch.get_num_interop_threads(),
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "cuda": torch.cuda.is_available(),
    }


def parse_scales(text: str) -> list[float]:
    """`mosaic bench --scales`: comma-separated detection scales, each in (0, 1]."""
    try:
        scales = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise MosaicError(f"--scales must be numbers like 0.75,0.5, got {text!r}") from None
    if any(not 0 < v <= 1 for v in scales):
        raise MosaicError(f"--scales must lie in (0, 1], got {text!r}")
    return scales


def bench_document(
    rows: list[BenchRow], builds: list[BuildRow], env: dict[str, Any]
) -> dict[str, Any]:
    """What `mosaic bench --json` prints: the environment, the rows, the whole builds (with
    their rates)."""
    whole = [
        {**r.__dict__, "streaming_fps": r.streaming_fps, "whole_fps": r.whole_fps} for r in builds
    ]
    return {"environment": env, "rows": [r.__dict__ for r in rows], "builds": whole}


def format_bench(rows: list[BenchRow], builds: list[BuildRow], env: dict[str, Any]) -> str:
    """What `mosaic bench` prints: the variants' table and its legend (with each variant's
    notes), the whole builds' table and its legend, the environment."""
    notes = [f"{r.name}: {r.notes}" for r in rows if r.notes]
    parts = [
        format_table(rows),
        "ms per stage (median); frame = wall time per registered frame, p90 over frames; "
        "x sift = fps ratio; ovl = the next frame extracted meanwhile: on (freely), turns (its "
        "network taking turns with the registration) or off (serially); default rows: as "
        f"[pipeline] overlap chose. {'; '.join(notes)}",
    ]
    if builds:
        parts.append("\n" + format_build_table(builds))
        parts.append(
            "stream = start of the run to the last frame registered; wall = to the mosaic "
            "and report written (model loaded before); x stream = whole fps / stream fps"
        )
    parts.append("environment: " + ", ".join(f"{k}={v}" for k, v in env.items()))
    return "\n".join(parts)
