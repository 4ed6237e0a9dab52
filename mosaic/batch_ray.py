"""The Ray engine of `mosaic batch`: one Ray task per video on a local Ray or a cluster
(`run_ray`), and joining that cluster within --ray-timeout with one line when it cannot be
reached (`ray_session`, `join_ray`), where Ray would try a wrong address for minutes.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from mosaic.batch_tasks import VideoTask
from mosaic.batch_video import (
    FAILED,
    INTERRUPT_WAIT_S,
    Done,
    Running,
    environ,
    limit_threads,
    mark_worker,
    process_video,
    row_of,
)
from mosaic.config import Config
from mosaic.errors import MosaicError

log = logging.getLogger(__name__)

RAY_HINT = "the ray engine needs Ray: pip install 'retina-mosaic[ray]'"
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
            with _stderr_into(held), environ({} if RAY_ATTEMPTS in os.environ else attempts):
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


def _ray_task(
    task: VideoTask, config: Config, out_dir: Path, rerun: str, threads: int
) -> dict[str, Any]:
    """One video on a Ray worker (as `process_video` in a pool worker)."""
    mark_worker()
    limit_threads(threads)
    return process_video(task, config, out_dir, rerun)
