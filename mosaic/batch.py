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

Here: the local engine (`run_local`), `run_batch` and `compare_patients`; the videos found in
`batch_tasks`, one video's run in a worker in `batch_video`, the Ray engine in `batch_ray`, the
summary files in `batch_summary`.
"""

from __future__ import annotations

import os
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, CancelledError, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import AbstractContextManager, ExitStack, suppress
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from mosaic.batch_ray import RAY_TIMEOUT_S, import_ray, ray_cluster, ray_session, run_ray
from mosaic.batch_summary import COMPARISONS, status_counts, write_summary
from mosaic.batch_tasks import VideoTask, find_tasks
from mosaic.batch_video import (
    FAILED,
    INTERRUPT_WAIT_S,
    NOT_RUN,
    OK,
    RECORDING,
    THREAD_ENV,
    Done,
    Running,
    done_report,
    environ,
    folder_paths,
    init_pool_worker,
    process_video,
    row_of,
)
from mosaic.config import Config
from mosaic.errors import InputError, OutputError

ENGINES = ("local", "ray")
SUMMARY_EVERY_S = 5.0  # summary files rewritten at most this often while the batch runs


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
# The local engine: runs tasks and calls `done(task, row)` as they finish (as `run_ray` does)
# --------------------------------------------------------------------------------------------


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _thread_env(threads: int) -> AbstractContextManager[None]:
    """The thread-pool variables for processes started meanwhile (they are read at import)."""
    return environ({name: str(threads) for name in THREAD_ENV})


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
            workers, context, initializer=init_pool_worker, initargs=(threads, os.getpid())
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


def _check_options(engine: str, rerun: str, ray_address: str | None, ray_timeout_s: float) -> None:
    """An `InputError` for an unknown engine or --rerun, a timeout not above 0; for the ray
    engine, the install hint (a `MosaicError`) when Ray is missing, before anything else."""
    if engine not in ENGINES:
        raise InputError(f"unknown engine {engine!r} (choices: {', '.join(ENGINES)})")
    if rerun not in ("off", "save"):
        raise InputError(f"--rerun for a batch is off or save, not {rerun!r}")
    if not ray_timeout_s > 0:
        raise InputError(f"--ray-timeout must be above 0 s, got {ray_timeout_s:g}")
    if engine == "ray":  # the install hint before anything else
        import_ray(ray_timeout_s if ray_cluster(ray_address) is not None else None)


def _output_folder(out_dir: str | Path) -> Path:
    """OUT_DIR made (an `OutputError` when it cannot be, or is not writable), resolved."""
    out = Path(out_dir).expanduser()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create output folder {out}: {exc.strerror or exc}") from exc
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"output folder is not writable: {out}")
    return out.resolve()


class _Progress:
    """The batch's rows as its videos finish, the progress bar's counts and the summary files
    (rewritten at most every SUMMARY_EVERY_S while the batch runs); `done` and `running` are
    the engines' callbacks."""

    def __init__(
        self, tasks: list[VideoTask], out: Path, meta: dict[str, Any], echo: Callable[[str], None]
    ) -> None:
        self.tasks, self.out, self.meta, self.echo = tasks, out, meta, echo
        self.rows: dict[str, dict[str, Any]] = {}
        self.counts = {"done": 0, "failed": 0, "running": 0}
        self.written = 0.0
        self.bar: Any = None  # the tqdm bar, set once the engine is up

    def skip_done(self, resume: bool) -> list[VideoTask]:
        """The tasks to run: with `resume`, those done already (`done_report`) are rows."""
        todo = []
        for task in self.tasks:
            report = done_report(task, self.out) if resume else None
            if report is not None:
                self.rows[task.id] = {**row_of(task, self.out, report, OK), "resumed": True}
            else:
                todo.append(task)
        return todo

    def ordered(self) -> list[dict[str, Any]]:
        """A row per task, in input order ('not run' for those without one yet)."""
        return [self.rows.get(t.id) or row_of(t, self.out, None, NOT_RUN) for t in self.tasks]

    def write(self, final: bool = False) -> None:
        if final or time.monotonic() - self.written >= SUMMARY_EVERY_S:
            write_summary(self.out, self.ordered(), self.meta)
            self.written = time.monotonic()

    def running(self, n: int) -> None:
        self.counts["running"] = n
        self.bar.set_postfix(self.counts, refresh=True)

    def done(self, task: VideoTask, row: dict[str, Any]) -> None:
        self.rows[task.id] = row
        self.counts["done" if row["status"] == OK else "failed"] += 1
        self.counts["running"] = max(0, self.counts["running"] - 1)
        self.echo(_line(row))
        self.bar.set_postfix(self.counts, refresh=False)
        self.bar.update()
        self.write()


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

    _check_options(engine, rerun, ray_address, ray_timeout_s)
    out = _output_folder(out_dir)
    tasks = find_tasks(source, pattern, exclude=out)
    cores = available_cores()
    workers = workers or cores  # a video keeps about one core busy (README: Many videos)
    if workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    threads = cpus_per_video or max(1, cores // workers)
    meta = {
        "input": str(source),
        "engine": engine,
        "workers": workers if engine == "local" else None,
        "cpus_per_video": threads,
    }
    batch = _Progress(tasks, out, meta, echo or (lambda text: tqdm.write(text, file=sys.stderr)))
    todo = batch.skip_done(resume)
    if batch.rows:
        batch.echo(
            f"{len(batch.rows)} of {len(tasks)} videos already done, skipped "
            "(--no-resume redoes them)"
        )
    meta["started"] = datetime.now(UTC).isoformat(timespec="seconds")
    interrupted = False
    batch.write(final=True)
    try:
        with ExitStack() as stack:  # Ray up before the bar shows: a failure to reach it is one line
            ray = None
            if engine == "ray":
                ray = stack.enter_context(ray_session(ray_address, ray_timeout_s))
            bar = tqdm(
                disable=not progress,
                total=len(todo),
                unit="video",
                desc="batch",
                dynamic_ncols=True,
            )
            batch.bar = stack.enter_context(bar)
            if engine == "local":
                run_local(todo, config, out, rerun, workers, threads, batch.done, batch.running)
            else:
                cpus = cpus_per_video or 1
                run_ray(ray, todo, config, out, rerun, cpus, batch.done, batch.running)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        meta["finished"] = datetime.now(UTC).isoformat(timespec="seconds")
        batch.write(final=True)
    ordered = batch.ordered()
    patients = None
    if any(t.patient for t in tasks) and not interrupted:
        patients = compare_patients(tasks, ordered, out, config, batch.echo, rerun)
        write_summary(out, ordered, meta, patients)
    return BatchResult(ordered, interrupted, status_counts(ordered), patients)


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
        paths = folder_paths(out, task.id)
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
