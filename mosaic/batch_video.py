"""One video of a batch (`mosaic batch`), as a pool or Ray worker runs it: `process_video`
builds it into OUT_DIR/<id>/ through `runner.run_video` (the code path of `mosaic build`) with
its own log, and returns its summary row (`row_of`); `done_report` is what `--resume` skips.
The worker processes' setup (threads, Ctrl-C, dying with the batch) is here too.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

from mosaic.batch_tasks import VideoTask
from mosaic.config import Config, load_config
from mosaic.errors import InputError, MosaicError
from mosaic.io import keep_native_stderr
from mosaic.report import BuildReport, Summary, read_report
from mosaic.runner import Outputs, run_video

log = logging.getLogger(__name__)

MOSAIC, REPORT, THUMBNAIL, LOG, RECORDING = (
    "mosaic.png",
    "report.json",
    "thumbnail.jpg",
    "log.txt",
    "recording.rrd",
)
OK, FAILED, INTERRUPTED, NOT_RUN = "ok", "failed", "interrupted", "not run"
#: Environment variables that size the thread pools of OpenMP (torch), BLAS and friends.
THREAD_ENV = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
)
INTERRUPT_WAIT_S = 120.0  # after Ctrl-C, how long the running videos are waited for
#: What an engine calls as a video finishes (its row), and with the number running.
Done = Callable[[VideoTask, dict[str, Any]], None]
Running = Callable[[int], None]

_IN_WORKER = False  # set in pool / Ray workers: stderr is captured into each video's log


def mark_worker() -> None:
    """This process runs a batch's videos (a pool or Ray worker): each video's log captures
    the process's stderr, and Ctrl-C interrupts only a running video."""
    global _IN_WORKER
    _IN_WORKER = True


def limit_threads(threads: int) -> None:
    """Size this process's torch, OpenCV and (through the environment, for what starts later)
    BLAS thread pools to `threads`."""
    import cv2
    import torch

    for name in THREAD_ENV:
        os.environ[name] = str(threads)
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)


@contextmanager
def _video_log(path: Path) -> Iterator[None]:
    """Send the mosaic / glampoints loggers (INFO and up) to `path` for the duration; in a
    worker also the process's stderr (OpenCV and ffmpeg write there)."""
    handler = logging.FileHandler(path, mode="w", encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    loggers = [logging.getLogger(name) for name in ("mosaic", "glampoints")]
    saved = [(lg.level, lg.propagate) for lg in loggers]
    for lg in loggers:
        lg.addHandler(handler)
        lg.setLevel(logging.INFO)
        lg.propagate = False  # the terminal has the progress bar and a line per video
    saved_fd = None
    kept = ExitStack()
    if _IN_WORKER:
        sys.stderr.flush()
        saved_fd = os.dup(2)
        os.dup2(handler.stream.fileno(), 2)
        kept.enter_context(keep_native_stderr())  # ffmpeg's own reason, in the video's log
    try:
        with kept:
            yield
    finally:
        if saved_fd is not None:
            sys.stderr.flush()
            os.dup2(saved_fd, 2)
            os.close(saved_fd)
        for lg, (level, propagate) in zip(loggers, saved, strict=True):
            lg.removeHandler(handler)
            lg.setLevel(level)
            lg.propagate = propagate
        handler.close()


def folder_paths(out_dir: Path, task_id: str) -> dict[str, Path]:
    """A video's folder under `out_dir` and the paths of its outputs in it."""
    folder = out_dir / task_id
    return {
        "folder": folder,
        "mosaic": folder / MOSAIC,
        "report": folder / REPORT,
        "thumbnail": folder / THUMBNAIL,
        "log": folder / LOG,
        "recording": folder / RECORDING,
    }


def _summary_cells(summary: Summary | None) -> dict[str, Any]:
    """A row's figures from a video's report summary (None each without one)."""
    if summary is None:
        names = ("frames", "registered", "registered_pct", "frames_until_failure", "segments")
        return dict.fromkeys((*names, "fps"))
    frames, registered = summary.frames_read, summary.registered
    return {
        "frames": frames,
        "registered": registered,
        "registered_pct": round(100.0 * registered / frames, 1) if frames else None,
        "frames_until_failure": summary.frames_until_failure,
        "segments": summary.segments,
        "fps": summary.fps,
    }


def row_of(
    task: VideoTask,
    out_dir: Path,
    report: BuildReport | None,
    status: str,
    error: str | None = None,
    time_s: float | None = None,
) -> dict[str, Any]:
    """The summary row of a video, from its report where there is one."""
    paths = folder_paths(out_dir, task.id)
    summary = None if report is None else report.summary
    seconds = time_s if time_s is not None or summary is None else summary.wall_time_s
    has_mosaic = report is not None and report.mosaic is not None
    return {
        "id": task.id,
        "status": status,
        **_summary_cells(summary),
        "time_s": None if seconds is None else round(seconds, 2),
        "error": error,
        "video": str(task.video),
        "mosaic": f"{task.id}/{MOSAIC}" if has_mosaic else None,
        "thumbnail": f"{task.id}/{THUMBNAIL}"
        if has_mosaic and paths["thumbnail"].is_file()
        else None,
        "report": f"{task.id}/{REPORT}" if paths["report"].is_file() else None,
        "log": f"{task.id}/{LOG}" if paths["log"].is_file() else None,
        "resumed": False,
    } | ({"patient": task.patient, "visit": task.visit} if task.patient else {})


def done_report(task: VideoTask, out_dir: Path) -> BuildReport | None:
    """The report of a video already done (complete, its mosaic there, the same input), else
    None: what `--resume` skips."""
    paths = folder_paths(out_dir, task.id)
    report = read_report(paths["report"])
    if report is None or not report.summary.complete:
        return None
    if not paths["mosaic"].is_file():
        return None
    if report.input is None or report.input.path != str(task.video):
        return None
    return report


def process_video(
    task: VideoTask, config: Config, out_dir: Path, rerun: str = "off"
) -> dict[str, Any]:
    """Build one video of the batch into OUT_DIR/<id>/ and return its summary row; every error
    (but the interrupt, which is its own status) becomes a failed row."""
    from mosaic.viz import make_viewer

    paths = folder_paths(out_dir, task.id)
    started = time.perf_counter()
    try:
        paths["folder"].mkdir(parents=True, exist_ok=True)
        _remove_outputs(paths)
    except OSError as exc:
        reason = f"cannot prepare {paths['folder']}: {exc.strerror or exc}"
        return row_of(task, out_dir, None, FAILED, reason)
    previous = signal.getsignal(signal.SIGINT)
    if _IN_WORKER:  # idle workers ignore Ctrl-C; a running video writes what it has
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with _video_log(paths["log"]):
            log.info("video %s: %s", task.id, task.video)
            try:
                if task.error is not None:
                    raise InputError(task.error)
                cfg = load_config(task.config) if task.config is not None else config
                viewer = None
                if rerun == "save":

                    def viewer(info: Any) -> Any:
                        return make_viewer("save", paths["recording"], cfg, info)

                run = run_video(
                    task.video,
                    cfg,
                    Outputs(paths["mosaic"], paths["report"], paths["thumbnail"]),
                    viewer=viewer,
                )
            except MosaicError as exc:
                log.error("%s", exc)
                report = read_report(paths["report"]) if paths["report"].is_file() else None
                elapsed = time.perf_counter() - started
                return row_of(task, out_dir, report, FAILED, str(exc), elapsed)
            except Exception as exc:
                log.exception("internal error")
                message = f"internal error: {type(exc).__name__}: {exc}".splitlines()[0]
                return row_of(task, out_dir, None, FAILED, message, time.perf_counter() - started)
            status = OK if run.complete else INTERRUPTED if run.interrupted else FAILED
            error = run.error or (
                "interrupted: partial mosaic and report" if run.interrupted else None
            )
            log.info("video %s: %s", task.id, status)
            return row_of(task, out_dir, run.report, status, error)
    finally:
        if _IN_WORKER:
            signal.signal(signal.SIGINT, previous)


def _remove_outputs(paths: dict[str, Path]) -> None:
    """An earlier run's outputs of a video run again: the folder shows this run only."""
    stale = [paths[k] for k in ("report", "mosaic", "thumbnail", "recording")]
    stale += paths["folder"].glob(f"{Path(MOSAIC).stem}_seg*{Path(MOSAIC).suffix}")
    for path in stale:
        path.unlink(missing_ok=True)


def die_with_parent(parent_pid: int) -> None:
    """Linux: have the kernel SIGKILL this process when its parent dies (killed by the OOM
    killer, say), rather than finish its video for no one and wait for good; then exit at
    once if the parent is already gone. Elsewhere nothing is done."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    pr_set_pdeathsig = 1  # <linux/prctl.h>
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0) != 0:
        log.warning("prctl(PR_SET_PDEATHSIG): %s", os.strerror(ctypes.get_errno()))
    if os.getppid() != parent_pid:  # the parent died before the call: nothing will signal
        os._exit(1)


def init_pool_worker(threads: int, parent_pid: int | None = None) -> None:
    """Pool worker start: dies with the batch, its share of the cores, Ctrl-C ignored while
    idle."""
    mark_worker()
    if parent_pid is not None:
        die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    limit_threads(threads)


@contextmanager
def environ(values: dict[str, str]) -> Iterator[None]:
    """`values` in the environment for the duration, then the variables as they were."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
