"""`mosaic batch`: many videos, on this machine (a process pool) or on a Ray cluster.

`find_tasks` turns the input into one `VideoTask` per video: a folder is searched recursively
(video files, and folders of frames as one video each), a CSV manifest lists them (`video`,
optional `config`, `id`, and `patient` / `eye` with `visit`). `run_batch` skips the videos
already done (`--resume`: their report says `summary.complete`, see `mosaic.runner`), runs
the others with an engine, each through `process_video` (which calls `runner.run_video`, the
code path of `mosaic build`), and keeps OUT_DIR/summary.csv, summary.json and index.html up
to date. With patients named, each patient's (eye's) later visits are then compared onto the
first (`compare_patients`: the per-patient loop of `mosaic compare --manifest`) into
OUT_DIR/compare/<patient>/<visit>/.

A video's failure is its row: an unreadable, empty or corrupt input, a bad per-video config, a
crash of the process running it (the videos running beside it are tried again, alone) or of a
Ray worker (Ray retries it first). Per video, OUT_DIR/<id>/ holds mosaic.png (and
mosaic_segNNN.png when there are several segments), report.json, thumbnail.jpg and log.txt
(this video's log, and OpenCV / ffmpeg's own messages), and recording.rrd with `--rerun save`.
"""

from __future__ import annotations

import csv
import fnmatch
import html
import io
import logging
import math
import os
import re
import signal
import socket
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, CancelledError, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import AbstractContextManager, ExitStack, contextmanager, suppress
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from urllib.parse import quote

from mosaic.config import Config, load_config
from mosaic.errors import InputError, MosaicError, OutputError
from mosaic.io import keep_native_stderr, natural_key, write_json, write_text
from mosaic.report import BuildReport, Summary, read_report
from mosaic.runner import VIDEO_SUFFIXES, Outputs, is_frame_folder, run_video

log = logging.getLogger(__name__)

ENGINES = ("local", "ray")
MOSAIC, REPORT, THUMBNAIL, LOG, RECORDING = (
    "mosaic.png",
    "report.json",
    "thumbnail.jpg",
    "log.txt",
    "recording.rrd",
)
OK, FAILED, INTERRUPTED, NOT_RUN = "ok", "failed", "interrupted", "not run"
#: Columns of summary.csv (summary.json has the same keys per video).
COLUMNS = (
    "id",
    "status",
    "frames",
    "registered",
    "registered_pct",
    "frames_until_failure",
    "segments",
    "fps",
    "time_s",
    "error",
    "video",
    "mosaic",
    "report",
    "resumed",
)
#: Environment variables that size the thread pools of OpenMP (torch), BLAS and friends.
THREAD_ENV = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
)
RAY_HINT = "the ray engine needs Ray: pip install 'retina-mosaic[ray]'"
SUMMARY_EVERY_S = 5.0  # summary files rewritten at most this often while the batch runs
INTERRUPT_WAIT_S = 120.0  # after Ctrl-C, how long the running videos are waited for
RAY_TIMEOUT_S = 60.0  # joining a Ray cluster gives up after this long (--ray-timeout)
#: Ray's waits in one attempt to reach a cluster, read when `ray` is imported: connecting,
#: twice (the GCS, its pubsub), 5 s each by default, then the cluster id, 30 s; 20 attempts,
#: ~14 minutes. Joining a cluster, each is shortened to RAY_ATTEMPT_WAIT_S so that attempts
#: fit the timeout and SIGTERM (handled between Ray's calls) ends the wait within seconds.
RAY_CONNECT_WAIT, RAY_CLUSTER_ID_WAIT = (
    "RAY_gcs_rpc_server_connect_timeout_s",
    "RAY_py_gcs_connect_timeout_s",
)
RAY_ATTEMPT_WAIT_S = 2
RAY_ATTEMPTS = "RAY_gcs_server_port_wait_time_s"  # how many attempts (read by ray.init)
COMPARISONS = "compare"  # OUT_DIR/compare/<patient>/<visit>/: visits on their first's map
VISIT_COLUMNS = ("patient", "visit")  # summary.csv's extra columns when patients are named


@dataclass(frozen=True)
class VideoTask:
    """One video of the batch: its id (the folder under OUT_DIR), its path, its config file."""

    id: str
    video: Path
    config: Path | None = None  # a manifest's per-video config (replaces --config)
    error: str | None = None  # a manifest row that cannot run: failed as it is
    patient: str | None = None  # a manifest's patient (and eye): its visits are compared
    visit: str | None = None  # the visit's label (a date), ordering the patient's visits


@dataclass
class BatchResult:
    """The rows of the summary (one per video, in input order) and how the batch ended."""

    rows: list[dict[str, Any]]
    interrupted: bool = False
    counts: dict[str, int] = field(default_factory=dict)
    patients: dict[str, Any] | None = None  # compare_patients' entries, when patients named

    @property
    def failed(self) -> int:
        return sum(row["status"] == FAILED for row in self.rows)

    @property
    def not_compared(self) -> int:
        """Later visits not put on their first's map (refused, or a video failed)."""
        from mosaic.compare import not_compared

        return not_compared(self.patients or {})


# --------------------------------------------------------------------------------------------
# Finding the videos
# --------------------------------------------------------------------------------------------


def safe_id(text: str) -> str:
    """A folder name from a video's relative path: '/' becomes '__', odd characters '_'."""
    text = text.replace("\\", "/").strip("/").replace("/", "__")
    text = re.sub(r"[^A-Za-z0-9._-]+", "_", text).lstrip(".")
    return text or "video"


def _unique(ids: list[str]) -> list[str]:
    seen: set[str] = set()
    out = []
    for base in ids:
        name, k = base, 1
        while name in seen:
            k += 1
            name = f"{base}-{k}"
        seen.add(name)
        out.append(name)
    return out


def _walk(
    folder: Path, pattern: str | None, exclude: Path | None, root: Path | None = None
) -> Iterator[Path]:
    """Videos under `folder`, in natural order: files with a video suffix and folders of
    frames (not searched further), those whose path relative to `root` or whose name `pattern`
    matches; hidden entries and `exclude` are left out."""
    root = root or folder
    for path in sorted(folder.iterdir(), key=lambda p: natural_key(p.name)):
        if path.name.startswith(".") or path == exclude:
            continue
        if path.is_dir() and not is_frame_folder(path):
            yield from _walk(path, pattern, exclude, root)
            continue
        if path.is_file() and path.suffix.lower() not in VIDEO_SUFFIXES:
            continue
        rel = path.relative_to(root).as_posix()
        if pattern is None or fnmatch.fnmatch(rel, pattern) or fnmatch.fnmatch(path.name, pattern):
            yield path


def find_tasks(
    source: str | Path, pattern: str | None = None, exclude: str | Path | None = None
) -> list[VideoTask]:
    """The videos of a folder (recursive), of a CSV manifest, or one video file or folder.

    Ids are the paths relative to the folder (manifest: its `id` column, else the same from
    the `video` column) made into folder names, unique. `exclude` (the output folder) is not
    searched. Raises `InputError` when there is nothing to run.
    """
    src = Path(source).expanduser()
    if not src.exists():
        raise InputError(f"input not found: {src}")
    if src.is_file() and src.suffix.lower() == ".csv":
        return read_manifest(src)
    if src.is_file() or is_frame_folder(src):
        return [VideoTask(safe_id(src.stem if src.is_file() else src.name), src.resolve())]
    skip = Path(exclude).expanduser().resolve() if exclude is not None else None
    root = src.resolve()
    if skip == root:
        raise InputError(f"the output folder must not be the input folder: {src}")
    videos = list(_walk(root, pattern, skip))
    if not videos:
        what = f"matching {pattern!r}" if pattern else "(video files or folders of frames)"
        raise InputError(f"no videos {what} under {src}")
    ids = _unique([safe_id(_stem(v.relative_to(root))) for v in videos])
    return [VideoTask(i, v) for i, v in zip(ids, videos, strict=True)]


def _stem(rel: Path) -> str:
    return rel.with_suffix("").as_posix() if rel.suffix else rel.as_posix()


def read_manifest(path: Path) -> list[VideoTask]:
    """Tasks of a CSV manifest: column `video` (paths relative to the manifest), optional
    `config` (a TOML file per video, replacing --config) and `id`, and optional `patient`
    and/or `eye` with `visit` (a date): each patient's (eye's) visits are compared after the
    mosaics are built. A row without a video is a failed row; duplicate ids, a patient's row
    without a visit, or a patient's visit twice are errors."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read manifest {path}: {exc}") from exc
    if not rows or "video" not in rows[0]:
        raise InputError(f"{path} must be a CSV with a 'video' column and at least one row")
    named = {"patient", "eye"} & set(rows[0])
    if named and "visit" not in rows[0]:
        raise InputError(f"{path}: a '{sorted(named)[-1]}' column needs a 'visit' column (a date)")
    base = path.parent.resolve()
    tasks, ids = [], []
    for number, row in enumerate(rows, start=2):  # line 1 is the header
        video = (row.get("video") or "").strip()
        config = (row.get("config") or "").strip()
        given = (row.get("id") or "").strip()
        ids.append(safe_id(given or (_stem(Path(video)) if video else f"row{number}")))
        patient = " ".join(v for c in ("patient", "eye") if (v := (row.get(c) or "").strip()))
        visit = (row.get("visit") or "").strip()
        if named and not (patient and visit):
            raise InputError(f"{path} row {number}: give the patient (or eye) and the visit")
        tasks.append(
            VideoTask(
                ids[-1],
                (base / video).resolve() if video else base / f"row{number}",
                (base / config).resolve() if config else None,
                None if video else f"manifest row {number}: no video given",
                patient or None,
                visit or None,
            )
        )
    explicit = [t.id for t, row in zip(tasks, rows, strict=True) if (row.get("id") or "").strip()]
    duplicates = sorted({i for i in explicit if explicit.count(i) > 1})
    if duplicates:
        raise InputError(f"{path}: duplicate id(s) {', '.join(duplicates)}")
    unique = _unique(ids)
    tasks = [replace(t, id=u) for u, t in zip(unique, tasks, strict=True)]
    if named:  # a patient's visit given twice: before any video is built
        from mosaic.compare import group_visits

        group_visits(((t.patient or "", t.visit or "", t) for t in tasks), str(path))
    return tasks


# --------------------------------------------------------------------------------------------
# One video (runs in a worker process)
# --------------------------------------------------------------------------------------------

_IN_WORKER = False  # set in pool / Ray workers: stderr is captured into each video's log


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


def _folder_paths(out_dir: Path, task_id: str) -> dict[str, Path]:
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
    paths = _folder_paths(out_dir, task.id)
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
    paths = _folder_paths(out_dir, task.id)
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

    paths = _folder_paths(out_dir, task.id)
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


def _init_worker(threads: int, parent_pid: int | None = None) -> None:
    """Pool worker start: dies with the batch, its share of the cores, Ctrl-C ignored while
    idle."""
    global _IN_WORKER
    _IN_WORKER = True
    if parent_pid is not None:
        die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    limit_threads(threads)


def _ray_task(
    task: VideoTask, config: Config, out_dir: Path, rerun: str, threads: int
) -> dict[str, Any]:
    """One video on a Ray worker (as `process_video` in a pool worker)."""
    global _IN_WORKER
    _IN_WORKER = True
    limit_threads(threads)
    return process_video(task, config, out_dir, rerun)


# --------------------------------------------------------------------------------------------
# Engines: each runs tasks and calls `done(task, row)` as they finish
# --------------------------------------------------------------------------------------------

Done = Callable[[VideoTask, dict[str, Any]], None]
Running = Callable[[int], None]


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@contextmanager
def _environ(values: dict[str, str]) -> Iterator[None]:
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


def _thread_env(threads: int) -> AbstractContextManager[None]:
    """The thread-pool variables for processes started meanwhile (they are read at import)."""
    return _environ({name: str(threads) for name in THREAD_ENV})


def run_local(
    tasks: Iterable[VideoTask],
    config: Config,
    out: Path,
    rerun: str,
    workers: int,
    threads: int,
    done: Done,
    running: Running = lambda n: None,
    job: Callable[..., dict[str, Any]] = process_video,
) -> None:
    """`job(task, config, out, rerun)` (`process_video`) for every task in a pool of `workers`
    fresh processes of `threads` threads each, one task per worker at a time. When a worker
    process dies, the tasks that may have been running in it are tried again one at a time at
    the end; a task whose process dies when it runs alone is failed. After Ctrl-C the running
    videos (which write what they have) are waited for, then KeyboardInterrupt is raised.
    On Linux the workers die with this process (their parent-death signal fires when the
    thread that started them ends: this one, which holds the pool until it returns)."""
    import multiprocessing

    queue, suspects = deque(tasks), deque[VideoTask]()
    context = multiprocessing.get_context("spawn")  # no fork of a process with threads

    def new_pool() -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            workers, context, initializer=_init_worker, initargs=(threads, os.getpid())
        )

    active: dict[Future[dict[str, Any]], VideoTask] = {}
    alone = False  # trying suspects, one at a time
    with _thread_env(threads):
        pool = new_pool()
        try:
            while queue or suspects or active:
                if not queue and not active:
                    queue, suspects, alone = suspects, deque(), True
                while queue and len(active) < (1 if alone else workers):
                    task = queue.popleft()
                    active[pool.submit(job, task, config, out, rerun)] = task
                running(len(active))
                finished, _ = wait(active, return_when=FIRST_COMPLETED)
                broken = False
                for future in finished:
                    task = active.pop(future)
                    try:
                        done(task, future.result())
                    except BrokenProcessPool:
                        broken = True
                        if alone:
                            reason = "the process building it died (a crash, or out of memory)"
                            done(task, row_of(task, out, None, FAILED, reason))
                        else:
                            suspects.append(task)
                if broken:  # the others died with the pool
                    suspects.extend(active.values())
                    active.clear()
                    pool.shutdown(wait=True, cancel_futures=True)
                    pool = new_pool()
        except KeyboardInterrupt:
            for future, task in active.items():
                with suppress(BrokenProcessPool, TimeoutError, CancelledError):
                    done(task, future.result(timeout=INTERRUPT_WAIT_S))
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def import_ray(join_timeout_s: float | None = None) -> Any:
    """The `ray` module, or a `MosaicError` saying how to install it. With `join_timeout_s`
    (a cluster is to be joined) and `ray` not imported yet, Ray's waits in an attempt to reach
    it are set to RAY_ATTEMPT_WAIT_S (a quarter of the timeout when that is shorter) first;
    the variables stay set, for `join_ray` to count attempts (one the user set is kept)."""
    if join_timeout_s is not None and "ray" not in sys.modules:
        wait_s = str(max(1, min(RAY_ATTEMPT_WAIT_S, int(join_timeout_s // 4))))
        os.environ.setdefault(RAY_CONNECT_WAIT, wait_s)
        os.environ.setdefault(RAY_CLUSTER_ID_WAIT, wait_s)
    try:
        import ray
    except ImportError:
        raise MosaicError(RAY_HINT) from None
    return ray


def ray_cluster(address: str | None) -> str | None:
    """The cluster ray.init is to join: `address`, else $RAY_ADDRESS ('auto': the one `ray
    start` started on this machine); None: a new local Ray."""
    address = address or os.environ.get("RAY_ADDRESS") or None
    return None if address in (None, "local") else address


def reach_ray(address: str, timeout_s: float) -> None:
    """A `MosaicError`, within `timeout_s`, when nothing answers at a HOST:PORT (or
    ray://HOST:PORT) cluster address: a refused port at once, an unreachable host on time."""
    host, colon, port = address.split("://", 1)[-1].rpartition(":")
    if not colon or not port.isdigit():
        return  # not a form to probe: left to ray.init
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except TimeoutError:
        raise MosaicError(
            f"cannot reach the Ray cluster at {address}: no answer in {timeout_s:g} s "
            "(--ray-timeout)"
        ) from None
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise MosaicError(f"cannot reach the Ray cluster at {address}: {reason}") from None


@contextmanager
def _stderr_into(held: Any) -> Iterator[None]:
    """The process's stderr (file descriptor 2: Ray's C++ writes there too) into the file
    `held` for the duration."""
    sys.stderr.flush()
    saved = os.dup(2)
    os.dup2(held.fileno(), 2)
    try:
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)


def join_ray(ray: Any, address: str, timeout_s: float, **options: Any) -> None:
    """`ray.init(address, **options)` that gives up in about `timeout_s` with one line (a
    `MosaicError`) where Ray would try a wrong address for minutes: the port is probed first,
    then Ray's attempts (each a few seconds, see `import_ray`) are as many as fit. Ray's line
    per failed attempt goes to the log (-v); what a good start prints is shown as before."""
    started = time.monotonic()
    reach_ray(address, timeout_s)
    left_s = timeout_s - (time.monotonic() - started)
    connect_s = float(os.environ.get(RAY_CONNECT_WAIT, 5))
    attempt_s = 2 * connect_s + float(os.environ.get(RAY_CLUSTER_ID_WAIT, 30)) + 1  # 1 s pause
    # the attempts that fit, less one: the command's start took seconds of the user's wait too
    attempts = {RAY_ATTEMPTS: str(max(1, int(left_s // attempt_s) - 1))}
    with tempfile.TemporaryFile() as held:
        try:
            with _stderr_into(held), _environ({} if RAY_ATTEMPTS in os.environ else attempts):
                ray.init(address=address, **options)
        except (OSError, ValueError, RuntimeError) as exc:
            held.seek(0)
            log.info("ray.init(%r): %s", address, held.read().decode(errors="replace"))
            tried = f"tried {time.monotonic() - started:.0f} s, --ray-timeout {timeout_s:g}"
            message = f"cannot join the Ray cluster at {address} ({tried}): {exc}"
            raise MosaicError(message.splitlines()[0]) from exc
        held.seek(0)
        sys.stderr.write(held.read().decode(errors="replace"))


@contextmanager
def ray_session(address: str | None, timeout_s: float = RAY_TIMEOUT_S) -> Iterator[Any]:
    """The `ray` module, initialised: the Ray this process has already started, the cluster
    at `address` (or $RAY_ADDRESS; given up after `timeout_s` when it cannot be reached), or
    a new local Ray (Ray has its daemons and workers die with this process on Linux, its
    agents a minute later). A Ray started here is shut down on exit."""
    cluster = ray_cluster(address)
    ray = import_ray(timeout_s if cluster is not None else None)
    if ray.is_initialized():
        yield ray
        return
    options = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.WARNING}
    on_terminate = signal.getsignal(signal.SIGTERM)
    if cluster is not None:
        join_ray(ray, cluster, timeout_s, **options)
    else:
        try:  # not ray.init's default, which joins the last `ray start`, even a dead one
            ray.init(address="local", **options)
        except (ConnectionError, ValueError, RuntimeError) as exc:
            message = f"cannot start a local Ray: {exc}"
            raise MosaicError(message.splitlines()[0]) from exc
    if callable(on_terminate) and threading.current_thread() is threading.main_thread():
        # ray.init puts its own SIGTERM handler (exit at once) in place of the caller's, which
        # takes SIGTERM as Ctrl-C so that the running videos write what they have
        signal.signal(signal.SIGTERM, on_terminate)
    try:
        yield ray
    finally:
        ray.shutdown()


def run_ray(
    ray: Any,
    tasks: Iterable[VideoTask],
    config: Config,
    out: Path,
    rerun: str,
    cpus_per_video: int,
    done: Done,
    running: Running = lambda n: None,
) -> None:
    """One Ray task per video (`num_cpus` each, retried on worker loss) on an initialised
    `ray` (`ray_session`). Tasks write their outputs to OUT_DIR: on a cluster it must be
    storage every node sees at the same path (as the inputs). After Ctrl-C the running tasks
    are cancelled (each gets KeyboardInterrupt and writes what it has, as in a pool worker)
    and their rows waited for, then KeyboardInterrupt is raised."""
    remote = ray.remote(num_cpus=cpus_per_video, max_retries=2)(_ray_task)
    slots = max(1, int(ray.cluster_resources().get("CPU", 1) // cpus_per_video))
    pending = {remote.remote(task, config, out, rerun, cpus_per_video): task for task in tasks}
    try:
        while pending:
            running(min(len(pending), slots))
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                task = pending.pop(ref)
                try:
                    row = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    reason = f"ray: {type(exc).__name__}: {exc}".splitlines()[0]
                    row = row_of(task, out, None, FAILED, reason)
                done(task, row)
    except KeyboardInterrupt:
        _cancel_ray(ray, pending, done)
        raise


def _cancel_ray(ray: Any, pending: dict[Any, VideoTask], done: Done) -> None:
    """Cancel the tasks: a queued one is dropped (its video stays 'not run'), a running one
    gets KeyboardInterrupt and returns its 'interrupted' row, waited for here."""
    for ref in pending:
        ray.cancel(ref)
    if not pending:
        return
    ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=INTERRUPT_WAIT_S)
    for ref in ready:
        try:
            row = ray.get(ref)
        except ray.exceptions.RayError:  # cancelled before it started, or lost
            continue
        done(pending[ref], row)


# --------------------------------------------------------------------------------------------
# The batch
# --------------------------------------------------------------------------------------------


def _line(row: dict[str, Any]) -> str:
    """The line printed when a video finishes."""
    if row["status"] == OK:
        return (
            f"ok      {row['id']}: {row['frames']} frames, {row['registered_pct']} % registered, "
            f"{row['segments']} segment(s), {row['time_s']} s"
        )
    return f"{row['status']:<7} {row['id']}: {row['error']}"


def run_batch(
    source: str | Path,
    out_dir: str | Path,
    config: Config,
    *,
    workers: int | None = None,
    engine: str = "local",
    ray_address: str | None = None,
    ray_timeout_s: float = RAY_TIMEOUT_S,
    cpus_per_video: int | None = None,
    resume: bool = True,
    pattern: str | None = None,
    rerun: str = "off",
    progress: bool = True,
    echo: Callable[[str], None] | None = None,
) -> BatchResult:
    """Run every video of `source` into `out_dir` (see the module doc); the summary files are
    written as videos finish and at the end, also after Ctrl-C (then `interrupted`)."""
    from tqdm import tqdm

    if engine not in ENGINES:
        raise InputError(f"unknown engine {engine!r} (choices: {', '.join(ENGINES)})")
    if rerun not in ("off", "save"):
        raise InputError(f"--rerun for a batch is off or save, not {rerun!r}")
    if not ray_timeout_s > 0:
        raise InputError(f"--ray-timeout must be above 0 s, got {ray_timeout_s:g}")
    if engine == "ray":  # the install hint before anything else
        import_ray(ray_timeout_s if ray_cluster(ray_address) is not None else None)
    out = Path(out_dir).expanduser()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create output folder {out}: {exc.strerror or exc}") from exc
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"output folder is not writable: {out}")
    out = out.resolve()
    tasks = find_tasks(source, pattern, exclude=out)
    cores = available_cores()
    workers = workers or cores  # a video keeps about one core busy (README: Many videos)
    if workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    threads = cpus_per_video or max(1, cores // workers)
    rows: dict[str, dict[str, Any]] = {}
    todo = []
    for task in tasks:
        report = done_report(task, out) if resume else None
        if report is not None:
            rows[task.id] = {**row_of(task, out, report, OK), "resumed": True}
        else:
            todo.append(task)
    echo = echo or (lambda text: tqdm.write(text, file=sys.stderr))
    if rows:
        echo(f"{len(rows)} of {len(tasks)} videos already done, skipped (--no-resume redoes them)")
    meta = {
        "input": str(source),
        "engine": engine,
        "workers": workers if engine == "local" else None,
        "cpus_per_video": threads,
        "started": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    state = {"written": 0.0}

    def write(final: bool = False) -> None:
        if final or time.monotonic() - state["written"] >= SUMMARY_EVERY_S:
            ordered = [rows.get(t.id) or row_of(t, out, None, NOT_RUN) for t in tasks]
            write_summary(out, ordered, meta)
            state["written"] = time.monotonic()

    bar_options = dict(total=len(todo), unit="video", desc="batch", dynamic_ncols=True)
    counts = {"done": 0, "failed": 0, "running": 0}

    def postfix() -> None:
        bar.set_postfix(counts, refresh=True)

    def on_running(n: int) -> None:
        counts["running"] = n
        postfix()

    def on_done(task: VideoTask, row: dict[str, Any]) -> None:
        rows[task.id] = row
        counts["done" if row["status"] == OK else "failed"] += 1
        counts["running"] = max(0, counts["running"] - 1)
        echo(_line(row))
        bar.set_postfix(counts, refresh=False)
        bar.update()
        write()

    interrupted = False
    write(final=True)
    try:
        with ExitStack() as stack:  # Ray up before the bar shows: a failure to reach it is one line
            ray = None
            if engine == "ray":
                ray = stack.enter_context(ray_session(ray_address, ray_timeout_s))
            bar = stack.enter_context(tqdm(disable=not progress, **bar_options))
            if engine == "local":
                run_local(todo, config, out, rerun, workers, threads, on_done, on_running)
            else:
                run_ray(ray, todo, config, out, rerun, cpus_per_video or 1, on_done, on_running)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        meta["finished"] = datetime.now(UTC).isoformat(timespec="seconds")
        write(final=True)
    ordered = [rows.get(t.id) or row_of(t, out, None, NOT_RUN) for t in tasks]
    tally = {s: sum(r["status"] == s for r in ordered) for s in (OK, FAILED, INTERRUPTED, NOT_RUN)}
    patients = None
    if any(t.patient for t in tasks) and not interrupted:
        patients = compare_patients(tasks, ordered, out, config, echo, rerun)
        write_summary(out, ordered, meta, patients)
    return BatchResult(ordered, interrupted, tally, patients)


def compare_patients(
    tasks: list[VideoTask],
    rows: list[dict[str, Any]],
    out: Path,
    config: Config,
    echo: Callable[[str], None],
    rerun: str = "off",
) -> dict[str, Any]:
    """Each patient's (eye's) later visits compared onto the first visit's mosaic, as
    `mosaic compare --manifest` does (`compare.compare_patient`), into OUT/compare/ (with
    `rerun` save, each comparison's layers in its folder's recording.rrd); a visit whose
    video failed is a failed row. Returns the patients' summary entries."""
    from mosaic.compare import compare_patient, group_visits, load_visit
    from mosaic.features import FeatureExtractor
    from mosaic.viz import make_compare_viewer

    def viewer(folder: Path) -> Any:
        return make_compare_viewer("save", folder / RECORDING)

    row_of_task = {t.id: r for t, r in zip(tasks, rows, strict=True)}
    named = ((t.patient, t.visit or "", t) for t in tasks if t.patient)
    extractor = FeatureExtractor(config.features)

    def load(task: VideoTask, name: str, folder: Path) -> Any:
        row = row_of_task[task.id]
        if row["status"] != OK:
            raise InputError(f"video {task.id} {row['status']}: {row['error']}")
        paths = _folder_paths(out, task.id)
        return load_visit(paths["mosaic"], name, folder, config, extractor, paths["report"])

    patients = {}
    for patient, visits in group_visits(named, "manifest").items():
        patients[patient] = compare_patient(
            patient,
            visits,
            out / COMPARISONS,
            load,
            config,
            extractor,
            viewer if rerun == "save" else None,
        )
        for row in patients[patient]["visits"]:
            detail = f"{row['regions']} changed region(s)" if "regions" in row else row["reason"]
            echo(f"{row['status']:<10} {patient} {row['visit']}: {detail}")
    return patients


# --------------------------------------------------------------------------------------------
# Summary files
# --------------------------------------------------------------------------------------------


def write_summary(
    out: Path,
    rows: list[dict[str, Any]],
    meta: dict[str, Any],
    patients: dict[str, Any] | None = None,
) -> None:
    """summary.csv, summary.json and index.html in `out`, each written atomically; with the
    patients' comparisons (`compare_patients`), their entries and table too."""
    buffer = io.StringIO()
    columns = COLUMNS + VISIT_COLUMNS if any("patient" in r for r in rows) else COLUMNS
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row[k] for k in columns})
    write_text(out / "summary.csv", buffer.getvalue())
    counts = {s: sum(r["status"] == s for r in rows) for s in (OK, FAILED, INTERRUPTED, NOT_RUN)}
    summary = {"meta": meta, "counts": counts, "videos": rows}
    write_json(out / "summary.json", summary | ({"patients": patients} if patients else {}))
    write_text(out / "index.html", render_index(rows, meta, counts, patients))


_STATUS_ORDER = {FAILED: 0, INTERRUPTED: 1, NOT_RUN: 2, OK: 3}
_HTML_COLUMNS = (  # (key, header, numeric)
    ("status", "status", False),
    ("id", "video", False),
    ("frames", "frames", True),
    ("registered_pct", "registered %", True),
    ("frames_until_failure", "until failure", True),
    ("segments", "segments", True),
    ("fps", "frames/s", True),
    ("time_s", "time s", True),
    ("error", "error", False),
)
_STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse}th,td{padding:4px 8px;border-bottom:1px solid #ddd;
vertical-align:middle;text-align:left}th{cursor:pointer;background:#f4f4f4;position:sticky;top:0}
th:hover{background:#e8e8e8}td.n{text-align:right;font-variant-numeric:tabular-nums}
tr.failed td,tr.interrupted td{background:#fdecea}tr.not.run td{color:#888}
img{max-width:160px;max-height:120px;display:block}.err{color:#a00;max-width:40em}
"""
_SCRIPT = """
document.querySelectorAll('th').forEach(function(th, col){
  th.addEventListener('click', function(){
    var body = th.closest('table').tBodies[0];
    var asc = th.dataset.dir !== 'asc';
    th.parentNode.querySelectorAll('th').forEach(function(h){ delete h.dataset.dir; });
    th.dataset.dir = asc ? 'asc' : 'desc';
    var rows = Array.prototype.slice.call(body.rows);
    rows.sort(function(a, b){
      var x = a.cells[col].dataset.v, y = b.cells[col].dataset.v;
      var nx = parseFloat(x), ny = parseFloat(y);
      var c = (!isNaN(nx) && !isNaN(ny)) ? nx - ny : x.localeCompare(y);
      return asc ? c : -c;
    });
    rows.forEach(function(r){ body.appendChild(r); });
  });
});
"""


def _cell(row: dict[str, Any], key: str, numeric: bool) -> str:
    value = row.get(key)
    if key == "status":
        sort = str(_STATUS_ORDER.get(value, 9))
    elif value is None or (isinstance(value, float) and math.isnan(value)):
        sort = "" if not numeric else "-1"
    else:
        sort = str(value)
    text = "" if value is None else str(value)
    if key == "id":
        inner = html.escape(text)
        if row.get("report"):
            inner = f'<a href="{quote(row["report"])}">{inner}</a>'
        if row.get("log"):
            inner += f' <small>(<a href="{quote(row["log"])}">log</a>)</small>'
        body = inner
    else:
        body = html.escape(text)
    klass = ' class="n"' if numeric else ' class="err"' if key == "error" else ""
    return f'<td{klass} data-v="{html.escape(sort)}">{body}</td>'


def render_index(
    rows: list[dict[str, Any]],
    meta: dict[str, Any],
    counts: dict[str, int],
    patients: dict[str, Any] | None = None,
) -> str:
    """The browsable summary: one self-contained page (inline style and script, no server),
    a thumbnail per video linked to its mosaic, failed videos first, sortable by any column;
    with `patients`, then each patient's visits side by side with their change maps."""
    ordered = sorted(
        enumerate(rows), key=lambda item: (_STATUS_ORDER.get(item[1]["status"], 9), item[0])
    )
    head = "<th data-v>mosaic</th>" + "".join(
        f"<th>{html.escape(title)}</th>" for _, title, _ in _HTML_COLUMNS
    )
    lines = []
    for _, row in ordered:
        thumb = ""
        if row.get("thumbnail") and row.get("mosaic"):
            thumb = (
                f'<a href="{quote(row["mosaic"])}"><img src="{quote(row["thumbnail"])}" '
                f'alt="{html.escape(row["id"])}" loading="lazy"></a>'
            )
        cells = "".join(_cell(row, key, numeric) for key, _, numeric in _HTML_COLUMNS)
        status = html.escape(row["status"])
        lines.append(f'<tr class="{status}"><td data-v="">{thumb}</td>{cells}</tr>')
    tally = ", ".join(f"{n} {html.escape(s)}" for s, n in counts.items() if n)
    when = html.escape(str(meta.get("finished") or meta.get("started") or ""))
    title = f"mosaic batch: {html.escape(str(meta.get('input', '')))}"
    return (
        "<!DOCTYPE html>\n"
        f'<html lang="en"><head><meta charset="utf-8"><title>{title}</title>'
        f"<style>{_STYLE}</style></head><body>\n"
        f"<h1>{title}</h1>\n<p>{len(rows)} videos: {tally}. Engine "
        f"{html.escape(str(meta.get('engine', '')))}; {when}. Click a column to sort.</p>\n"
        f"<table><thead><tr>{head}</tr></thead><tbody>\n"
        + "\n".join(lines)
        + "\n</tbody></table>\n"
        + _visits_section(patients)
        + f"<script>{_SCRIPT}</script>\n</body></html>\n"
    )


def _visits_section(patients: dict[str, Any] | None) -> str:
    """Each patient's row of visits (`compare.patients_table`), or nothing."""
    if not patients:
        return ""
    from mosaic.compare import patients_table

    return "<h2>Visits compared</h2>\n" + patients_table(patients, root=f"{COMPARISONS}/")
