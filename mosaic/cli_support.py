"""The `mosaic` command line's parts that need no typer: logging (each warning kind once),
SIGTERM handled as Ctrl-C, the options made into a `Config`, the viewer flags resolved, and the
text the commands print (a build's summary, a pair's answer). `mosaic.cli` parses the options,
calls the application and prints what these return.
"""

from __future__ import annotations

import logging
import os
import re
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mosaic.config import Config, load_config, with_overrides
from mosaic.errors import InputError, MosaicError
from mosaic.features import DETECTORS, FeatureExtractor
from mosaic.io import check_output_path
from mosaic.report import BuildReport, Summary
from mosaic.viz import VIEWER_MODES


@contextmanager
def terminate_as_interrupt(children: bool = False) -> Iterator[None]:
    """SIGTERM (`kill`, a job scheduler, `docker stop`) handled as Ctrl-C: the run stops where
    it is and writes what it has, instead of dying with nothing written. `children`: the
    worker processes get Ctrl-C too (a terminal sends it to them all; `kill` to one)."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set from the main thread
        return

    def interrupt(signum: int, frame: object) -> None:
        if children:
            import multiprocessing

            for child in multiprocessing.active_children():
                with suppress(OSError):  # gone meanwhile
                    os.kill(child.pid, signal.SIGINT)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:  # None: a handler not set from Python, which cannot be put back
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


class _OncePerKind(logging.Filter):
    """Let the first warning of each kind through, a kind being its message with the numbers
    left out ("frame 12 skipped: blurred ..."): per-frame problems are counted in the report."""

    def __init__(self) -> None:
        super().__init__()
        self._seen: set[tuple[str, str]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING:
            return True
        kind = (record.name, re.sub(r"\d+(\.\d+)?", "#", record.getMessage()))
        if kind in self._seen:
            return False
        self._seen.add(kind)
        return True


def setup_logging(verbose: bool) -> None:
    """Warnings (each kind once) or, with `verbose`, everything, on stderr; OpenCV's own log
    lines only with `verbose` (our messages say what went wrong, on one line)."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if verbose:
        return
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    for handler in logging.getLogger().handlers:
        plain = type(handler) is logging.StreamHandler  # ours, not a test's capture
        if plain and not any(isinstance(f, _OncePerKind) for f in handler.filters):
            handler.addFilter(_OncePerKind())


def require_detectors(config: Config, names: list[str]) -> None:
    """Detectors the user named must load (GLAMpoints: its weights): else the error, not a
    table without them."""
    for name in names:
        FeatureExtractor(with_overrides(config, features={"detector": name}).features)


def options_config(
    path: Path | None,
    detector: str | None = None,
    **pipeline: Any,
) -> Config:
    """The config file (or the defaults) with the command's `--detector` and `[pipeline]`
    options (None: not given) laid over it."""
    config = load_config(path)
    overrides: dict[str, dict[str, Any]] = {}
    if detector is not None:
        if detector not in DETECTORS:
            raise MosaicError(f"unknown detector {detector!r} (choices: {', '.join(DETECTORS)})")
        overrides["features"] = {"detector": detector}
    pipeline = {k: v for k, v in pipeline.items() if v is not None}
    if pipeline:
        overrides["pipeline"] = pipeline
    return with_overrides(config, **overrides) if overrides else config


def viewer_args(mode: str, target: str | None, spawn: bool, output: Path) -> tuple[str, str | None]:
    """Resolve --rerun / --viewer / --rerun-target into a mode and its target, failing early."""
    if mode not in VIEWER_MODES:
        raise InputError(f"unknown --rerun mode {mode!r} (choices: {', '.join(VIEWER_MODES)})")
    if spawn:
        if mode not in ("off", "spawn"):
            raise InputError(
                f"--viewer is short for --rerun spawn; it cannot go with --rerun {mode}"
            )
        mode = "spawn"
    if target is not None and mode not in ("save", "connect"):
        raise InputError(f"--rerun-target is only used with --rerun save or connect, not {mode}")
    if mode == "save":
        rrd = target or output.with_suffix(".rrd")
        target = str(check_output_path(rrd, frozenset({".rrd"})))
    return mode, target


def _segments_row(report: BuildReport) -> str:
    """The segment count; with several, each one's frames and which is the main mosaic."""
    segments = report.segments
    if len(segments) < 2:
        return str(report.summary.segments)
    sizes = " / ".join(str(s.frames) for s in segments)
    return f"{len(segments)} ({sizes} frames; main mosaic: segment {report.main_segment})"


def _detector_row(summary: Summary) -> str:
    """The detector, with the precision its network ran in where it has one."""
    precision = summary.precision
    return f"{summary.detector} ({precision})" if precision else str(summary.detector)


def _cell(value: Any) -> str:
    """A summary value; "-" where there is none (a one-frame video has no quality: no mosaic
    under its frame to compare with)."""
    return "-" if value is None else str(value)


def summary_text(report: BuildReport, output: Path, report_path: Path) -> str:
    """What `mosaic build` prints at the end: the summary's table, then the files written."""
    summary = report.summary
    rows = [
        ("frames read", summary.frames_read),
        ("registered", summary.registered),
        ("failed", summary.failed),
        ("skipped", summary.skipped),
        ("frames until failure", summary.frames_until_failure),
        ("longest registered run", summary.longest_registered_run),
        ("segments", _segments_row(report)),
        ("mean matches / inliers", f"{summary.mean_matches} / {summary.mean_inliers}"),
        ("quality / flagged", f"{_cell(summary.quality)} / {summary.quality_flagged}"),
        ("frames per second", summary.fps),
        ("detector", _detector_row(summary)),
    ]
    if summary.deinterlaced:  # an interlaced camera: how many frames were combed
        rows.insert(4, ("deinterlaced", summary.deinterlaced))
    elif summary.looks_interlaced:
        rows.insert(4, ("looks interlaced", "yes (see [preprocess] deinterlace)"))
    if summary.reflex_frames:  # lens reflexes left out of those frames
        rows.insert(4, ("lens reflexes masked", f"{summary.reflex_frames} frames"))
    if summary.lens_rim_frames:  # a handheld lens: what lay outside its rim left out
        rows.insert(4, ("lens rim masked", f"{summary.lens_rim_frames} frames"))
    if summary.surround_lifted_frames:  # haze lifted the camera's surround: left out
        rows.insert(4, ("hazy surround masked", f"{summary.surround_lifted_frames} frames"))
    width = max(len(name) for name, _ in rows)
    lines = [f"{name:<{width}}  {_cell(value)}" for name, value in rows]
    lines.append(f"mosaic: {output}")
    segments = report.segments
    for segment in segments if len(segments) > 1 else []:
        if segment.mosaic:
            lines.append(f"segment {segment.index}: {segment.mosaic}")
    lines.append(f"report: {report_path}")
    return "\n".join(lines)


def pair_text(answer: dict[str, Any]) -> str:
    """The human-readable answer of `register` for one pair (a failed pair has no model and
    no residual: those are left out, not printed as None)."""
    reason = f" ({answer['reason']})" if answer["reason"] else ""
    lines = [f"status: {answer['status']}{reason}"]
    counts = f"matches: {answer['n_matches']}  inliers: {answer['n_inliers']}"
    if answer["model"] is not None:
        counts = f"model: {answer['model']}  {counts}"
    if answer["residual_px"] is not None:
        counts += f"  residual: {answer['residual_px']:.2f} px"
    lines.append(counts)
    if answer["working_scale"] is not None:
        s = answer["working_scale"]
        lines.append(
            f"working scale: fixed {s['fixed']:.3f}, moving {s['moving']:.3f}  "
            f"refined levels: {answer['refined_levels']}"
        )
    if answer["Q_moving_to_fixed"] is not None:
        Q = np.array(answer["Q_moving_to_fixed"])
        lines.append("Q_moving_to_fixed:\n" + np.array2string(Q, precision=9, suppress_small=False))
    if answer["H_moving_to_fixed"] is not None:
        H = np.array(answer["H_moving_to_fixed"])
        lines.append("H_moving_to_fixed:\n" + np.array2string(H, precision=6, suppress_small=True))
    return "\n".join(lines)
