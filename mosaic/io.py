"""Frame streaming (video files and image folders) and output writers.

I/O stays at the edges of the application: the pipeline only sees `Frame` objects carrying BGR
uint8 arrays. Inputs are validated eagerly (`open_frames`, `check_output_path`) so a bad path
fails in the first second with a one-line `InputError` / `OutputError`, not after a long run.
Frames are streamed one at a time; a frame that cannot be decoded is reported as a `Frame` with
`image=None` and iteration goes on.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import os
import re
import sys
import tempfile
import threading
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import cv2
import numpy as np

from mosaic.errors import InputError, OutputError

T = TypeVar("T")

log = logging.getLogger(__name__)

#: Suffixes (lower case) of the image files read from a frame folder.
IMAGE_READ_SUFFIXES: frozenset[str] = frozenset(
    {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm"}
)
#: Suffixes accepted for the mosaic image (formats OpenCV writes).
IMAGE_WRITE_SUFFIXES: frozenset[str] = frozenset(
    {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}
)
#: Suffixes accepted for a run's report.
REPORT_SUFFIXES: frozenset[str] = frozenset({".json"})
#: Consecutive failed reads after which a video stream is considered finished.
MAX_CONSECUTIVE_FAILURES = 5

# Process umask, read once: temporary files are created 0600 and get the usual mode on replace.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


UNDECODABLE = "frame could not be decoded"  # the reason a frame with no pixels is skipped


@dataclass(frozen=True)
class VideoInfo:
    """What is known about an input before decoding it: kind, frame count, rate, frame size."""

    path: str
    kind: str  # "video" | "folder"
    n_frames: int | None  # frames in the input (before step/max_frames); None if unknown
    fps: float | None  # None for folders or when the container does not say
    width: int  # size of the first frame
    height: int


@dataclass(frozen=True)
class Frame:
    """One input frame: BGR uint8 HxWx3 image, or None with a short reason if undecodable."""

    index: int  # index in the original video / sorted folder (not counting step)
    image: np.ndarray | None
    error: str | None = None


# --------------------------------------------------------------------------------------------
# Image conversion and reading
# --------------------------------------------------------------------------------------------


def expected_frames(info: VideoInfo, step: int, max_frames: int) -> int | None:
    """Frames a run will read (after `step` and `max_frames`), None if the input does not say."""
    if info.n_frames is None:
        return max_frames or None
    n = -(-info.n_frames // step)
    return min(n, max_frames) if max_frames else n


def to_bgr8(image: np.ndarray) -> np.ndarray:
    """Convert grey / BGRA / 16-bit / float images to BGR uint8 HxWx3, as the pipeline expects."""
    if image.dtype != np.uint8:
        if image.dtype == np.uint16:
            image = (image >> 8).astype(np.uint8)
        elif np.issubdtype(image.dtype, np.floating):
            finite = image[np.isfinite(image)]
            top = 1.0 if finite.size == 0 or float(finite.max()) <= 1.0 else 255.0
            image = np.clip(np.nan_to_num(image) * (255.0 / top), 0, 255).round().astype(np.uint8)
        else:
            image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3:
        channels = image.shape[2]
        if channels == 3:
            return image
        if channels == 1:
            return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if channels == 4:
            return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    raise ValueError(f"unsupported image shape {image.shape}")


def _decode_file(path: Path) -> np.ndarray:
    """Decode an image file to BGR uint8; raises ValueError with a short reason on failure."""
    try:
        data = np.fromfile(path, dtype=np.uint8)  # works with non-ASCII paths, unlike imread
    except OSError as exc:
        raise ValueError(f"cannot read file ({exc.strerror or exc})") from exc
    if data.size == 0:
        raise ValueError("empty file")
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise ValueError("not an image OpenCV can decode")
    return to_bgr8(image)


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as BGR uint8 HxWx3 (grey, alpha and 16-bit inputs are converted)."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise InputError(f"image not found: {p}")
    try:
        return _decode_file(p)
    except ValueError as exc:
        raise InputError(f"cannot read image {p}: {exc}") from exc


def natural_key(name: str) -> list[str | int]:
    """Sort key putting 'frame2' before 'frame10' (digit runs compare as numbers)."""
    parts = re.split(r"(\d+)", name.lower())
    return [int(part) if i % 2 else part for i, part in enumerate(parts)]


# --------------------------------------------------------------------------------------------
# Frame sources
# --------------------------------------------------------------------------------------------


class FrameSource:
    """Iterable, closable stream of `Frame`s from a video file or an image folder.

    Construct with `open_frames`. Iterating twice restarts from the first frame (a video file
    is then reopened). Use as a context manager, or call `close()`, to release the decoder.
    """

    def __init__(
        self,
        info: VideoInfo,
        step: int,
        max_frames: int,
        files: list[Path] | None = None,
        capture: cv2.VideoCapture | None = None,
        first_image: np.ndarray | None = None,
    ) -> None:
        self.info = info
        self.step = step
        self.max_frames = max_frames
        self._files = files
        self._capture = capture  # opened during validation, positioned after frame 0
        self._first_image = first_image
        self._closed = False

    @property
    def expected_frames(self) -> int | None:
        """Number of frames iteration will yield (after step/max_frames), None if unknown."""
        return expected_frames(self.info, self.step, self.max_frames)

    def __iter__(self) -> Iterator[Frame]:
        if self._closed:
            raise ValueError("frame source is closed")
        if self._files is not None:
            return self._iter_folder()
        return self._iter_video()

    def close(self) -> None:
        """Release the video decoder (if any); further iteration raises ValueError."""
        self._closed = True
        if self._capture is not None:
            self._capture.release()
            self._capture = None
        self._first_image = None

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- helpers ----------------------------------------------------------------------------

    def _checked(self, index: int, image: np.ndarray) -> Frame:
        """Frame with a BGR uint8 image, or a corrupt frame if its size differs from frame 0's."""
        image = to_bgr8(image)
        h, w = image.shape[:2]
        if (w, h) != (self.info.width, self.info.height):
            return self._corrupt(
                index,
                f"size {w}x{h} differs from the first frame's {self.info.width}x{self.info.height}",
            )
        return Frame(index, image, None)

    def _corrupt(self, index: int, reason: str) -> Frame:
        # the pipeline warns when it skips the frame (once); a re-read must not warn again
        log.info("frame %d of %s unusable: %s", index, self.info.path, reason)
        return Frame(index, None, reason)

    def _iter_folder(self) -> Iterator[Frame]:
        assert self._files is not None
        selected = range(0, len(self._files), self.step)
        if self.max_frames:
            selected = selected[: self.max_frames]
        for index in selected:
            if self._closed:
                return
            try:
                image = _decode_file(self._files[index])
            except ValueError as exc:
                yield self._corrupt(index, f"{self._files[index].name}: {exc}")
                continue
            yield self._checked(index, image)

    def _iter_video(self) -> Iterator[Frame]:
        capture, first = self._capture, self._first_image
        self._capture, self._first_image = None, None  # a second iteration reopens the file
        if capture is None:
            with quiet_stderr():
                capture = cv2.VideoCapture(self.info.path)
                opened = capture.isOpened()
                ok, first = capture.read() if opened else (False, None)
            if not opened:
                raise InputError(f"not a video OpenCV can read: {self.info.path}")
            if not ok:
                first = None
        try:
            yield from self._decode_stream(capture, first)
        finally:
            capture.release()

    def _decode_stream(
        self, capture: cv2.VideoCapture, first: np.ndarray | None
    ) -> Iterator[Frame]:
        """Read frames 1.. from `capture` (frame 0 already decoded as `first`).

        A failed read is held back until a later frame decodes: then it was a corrupt frame in
        the middle of the stream and is reported; after `MAX_CONSECUTIVE_FAILURES` failures in
        a row the stream has ended (the container's frame count is only an estimate).
        """
        total = self.info.n_frames
        yielded = 0
        if first is not None:
            yield self._checked(0, first)
        else:
            yield self._corrupt(0, UNDECODABLE)
        yielded += 1
        pending: list[int] = []  # selected indices whose read failed, not yet reported
        failures = 0
        index = 0
        while not self.max_frames or yielded < self.max_frames:
            if self._closed:
                return
            index += 1
            wanted = index % self.step == 0
            if wanted:
                ok, image = capture.read()
                ok = ok and image is not None and image.size > 0
            else:
                ok, image = capture.grab(), None  # skipped frame: advance without decoding
            if not ok:
                failures += 1
                if wanted:
                    pending.append(index)
                if failures >= MAX_CONSECUTIVE_FAILURES:
                    if total is not None and pending and pending[0] < total:
                        log.warning(
                            "%s: decoding stopped at frame %d of %d announced",
                            self.info.path,
                            pending[0],
                            total,
                        )
                    return
                continue
            failures = 0
            for bad in pending:
                if self.max_frames and yielded >= self.max_frames:
                    return
                yield self._corrupt(bad, UNDECODABLE)
                yielded += 1
            pending.clear()
            if wanted:
                if self.max_frames and yielded >= self.max_frames:
                    return
                yield self._checked(index, image)
                yielded += 1


def _open_folder(path: Path, step: int, max_frames: int) -> FrameSource:
    files = [f for f in path.iterdir() if f.suffix.lower() in IMAGE_READ_SUFFIXES and f.is_file()]
    if not files:
        kinds = ", ".join(sorted(s.lstrip(".") for s in IMAGE_READ_SUFFIXES))
        raise InputError(f"folder has no images ({kinds}): {path}")
    files.sort(key=lambda f: natural_key(f.name))
    first = None
    for f in files:  # the frame size comes from the first readable image
        try:
            first = _decode_file(f)
            break
        except ValueError:
            continue
    if first is None:
        raise InputError(f"no readable image in folder: {path}")
    h, w = first.shape[:2]
    info = VideoInfo(str(path), "folder", len(files), None, w, h)
    return FrameSource(info, step, max_frames, files=files)


_native_stderr = threading.local()  # .kept: OpenCV's / ffmpeg's lines go to a log file


@contextlib.contextmanager
def keep_native_stderr() -> Iterator[None]:
    """Within: `quiet_stderr` keeps OpenCV's and ffmpeg's lines (stderr is a log file, as in
    a `mosaic batch` worker, where they help diagnose a broken video)."""
    before = getattr(_native_stderr, "kept", False)
    _native_stderr.kept = True
    try:
        yield
    finally:
        _native_stderr.kept = before


@contextlib.contextmanager
def quiet_stderr() -> Iterator[None]:
    """Silence the process's stderr (file descriptor 2) for a moment: OpenCV and ffmpeg print
    their own lines there ("moov atom not found") when probing a file, before our one-line
    error. Python's own stderr is flushed first; the descriptor is restored on exit."""
    fd = 2  # where native code writes, whatever sys.stderr is
    try:
        os.fstat(fd)
    except OSError:  # no stderr at all: nothing to hide
        fd = None
    if fd is None or getattr(_native_stderr, "kept", False):
        yield
        return
    with contextlib.suppress(AttributeError, OSError, ValueError):
        sys.stderr.flush()
    saved = os.dup(fd)
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)


def _open_video(path: Path, step: int, max_frames: int) -> FrameSource:
    with quiet_stderr():
        capture = cv2.VideoCapture(str(path))
        opened = capture.isOpened()
        ok, first = capture.read() if opened else (False, None)
    if not opened:
        capture.release()
        raise InputError(f"not a video OpenCV can read: {path}")
    if not ok or first is None or first.size == 0:
        capture.release()
        raise InputError(f"video has no readable frames: {path}")
    count = capture.get(cv2.CAP_PROP_FRAME_COUNT)
    fps = capture.get(cv2.CAP_PROP_FPS)
    n_frames = round(count) if np.isfinite(count) and count > 0 else None
    fps_value = float(fps) if np.isfinite(fps) and fps > 0 else None
    first = to_bgr8(first)
    h, w = first.shape[:2]
    info = VideoInfo(str(path), "video", n_frames, fps_value, w, h)
    return FrameSource(info, step, max_frames, capture=capture, first_image=first)


def open_frames(path: str | Path, step: int = 1, max_frames: int = 0) -> FrameSource:
    """Open a video file or an image folder for streaming, validating it now.

    `step` K keeps frames 0, K, 2K, ... (`Frame.index` stays the index in the input);
    `max_frames` caps the number of frames yielded (0: all). Raises `InputError` for a missing
    path, a file OpenCV cannot open as video, or an input without frames.
    """
    if step < 1:
        raise InputError(f"frame step must be >= 1, got {step}")
    if max_frames < 0:
        raise InputError(f"max_frames must be >= 0, got {max_frames}")
    p = Path(path).expanduser()
    if not p.exists():
        raise InputError(f"input not found: {p}")
    opener = _open_folder if p.is_dir() else _open_video
    source = opener(p, step, max_frames)
    info = source.info
    log.info(
        "opened %s %s: %s frames, %dx%d, fps %s",
        info.kind,
        info.path,
        info.n_frames if info.n_frames is not None else "?",
        info.width,
        info.height,
        f"{info.fps:g}" if info.fps else "?",
    )
    return source


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------


def check_output_path(
    path: str | Path, suffixes: frozenset[str] | None = None, probe: bool = True
) -> Path:
    """Fail early if `path` cannot be written: missing / read-only folder, a read-only or
    immutable file, or an unsupported format.

    `suffixes` are the accepted (lower-case) suffixes; by default (None) the image formats
    OpenCV writes for the mosaic plus `.json` (the run report). `probe`: also try it, so that
    what permissions do not tell (an immutable file or folder, a read-only file system, a name
    too long, root on a read-only folder) fails now: a new file is created then removed, an
    existing one opened for appending (its contents untouched).
    """
    p = Path(path).expanduser()
    parent = p.parent
    if not parent.is_dir():
        raise OutputError(f"output folder does not exist: {parent}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"output folder is not writable: {parent}")
    try:
        is_dir = p.is_dir()
    except OSError as exc:  # e.g. a name longer than the file system takes
        raise OutputError(f"cannot write {p}: {exc.strerror or exc}") from exc
    if is_dir:
        raise OutputError(f"output path is a folder, expected a file: {p}")
    allowed = IMAGE_WRITE_SUFFIXES | {".json"} if suffixes is None else suffixes
    suffix = p.suffix.lower()
    image_ok = suffix not in IMAGE_WRITE_SUFFIXES or cv2.haveImageWriter(p.name)
    if suffix not in allowed or not image_ok:
        kinds = ", ".join(sorted(s.lstrip(".") for s in allowed))
        raise OutputError(f"unsupported output format '{p.suffix}' (use {kinds}): {p}")
    if probe:
        _probe_writable(p)
    return p


def check_distinct_paths(outputs: dict[str, Path], inputs: dict[str, Path] | None = None) -> None:
    """Fail early if two outputs of one command (named by their option) are one file, or an
    output is one of the inputs: the later write would replace the earlier one, or the input,
    after the whole run. Paths compare resolved (`..`, symbolic links), and as files where both
    exist (hard links)."""
    named = list(outputs.items())
    for i, (name, path) in enumerate(named):
        for other, other_path in named[i + 1 :]:
            if same_file(path, other_path):
                raise OutputError(
                    f"{name} and {other} are the same file, each output needs its own: {path}"
                )
        for other, input_path in (inputs or {}).items():
            if same_file(path, input_path):
                raise OutputError(f"{name} would write over the input {other}: {path}")


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether `a` and `b` name one file, existing or not (resolved: `..`, symbolic links;
    compared as files where both exist: hard links)."""
    a, b = Path(a).expanduser(), Path(b).expanduser()
    try:
        if a.resolve() == b.resolve():
            return True
        return os.path.samefile(a, b)
    except (OSError, RuntimeError):  # one does not exist (yet), or a loop of links
        return a.absolute() == b.absolute()


def _probe_writable(p: Path) -> None:
    """Create and remove `p` (or open an existing `p` for appending); OutputError if refused."""
    try:
        if p.exists():
            if not os.access(p, os.W_OK):
                raise OutputError(f"output file is read-only: {p}")
            os.close(os.open(p, os.O_WRONLY | os.O_APPEND))
            # the atomic writes put a temporary file beside it, then rename
            with tempfile.NamedTemporaryFile(dir=p.parent, prefix=f".{p.name}.", suffix=".tmp"):
                pass
        else:
            os.close(os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            os.unlink(p)
    except OSError as exc:
        raise OutputError(f"cannot write {p}: {exc.strerror or exc}") from exc


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside `path` (same suffix) to write to; renamed onto `path` when the
    block ends normally, removed otherwise: readers never see a half-written file. For writers
    that want a file name (matplotlib's savefig, torch.save, cv2.VideoWriter)."""
    p = Path(path).expanduser()
    if not p.parent.is_dir():
        raise OutputError(f"output folder does not exist: {p.parent}")
    try:
        fd, name = tempfile.mkstemp(dir=p.parent, prefix=f".{p.stem}.", suffix=f".tmp{p.suffix}")
        os.close(fd)
    except OSError as exc:
        raise OutputError(f"cannot write {p}: {exc.strerror or exc}") from exc
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, p)
    except OSError as exc:
        raise OutputError(f"cannot write {p}: {exc.strerror or exc}") from exc
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write `data` atomically (`atomic_path`); OutputError on failure."""
    p = Path(path).expanduser()
    with atomic_path(p) as tmp:
        tmp.write_bytes(data)
    return p


def write_text(path: str | Path, text: str) -> Path:
    """Write UTF-8 text atomically; OutputError on failure."""
    return write_bytes(path, text.encode("utf-8"))


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """Write an image (format from the suffix: PNG, JPG, ...) atomically; OutputError on failure."""
    p = Path(path).expanduser()
    try:
        ok, encoded = cv2.imencode(p.suffix, image)
    except cv2.error as exc:
        raise OutputError(f"cannot encode image as '{p.suffix}': {p}") from exc
    if not ok:
        raise OutputError(f"cannot encode image as '{p.suffix}': {p}")
    write_bytes(p, encoded.tobytes())
    return p


def _json_default(obj: Any) -> Any:
    """json.dumps hook: numpy arrays/scalars to lists/numbers, paths to strings."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def json_text(obj: Any) -> str:
    """`obj` as indented JSON text (numpy values converted): what `write_json` writes."""
    return json.dumps(obj, default=_json_default, indent=2)


def write_json(path: str | Path, obj: Any) -> Path:
    """Write `obj` as indented JSON atomically (numpy values converted); OutputError on failure."""
    p = Path(path).expanduser()
    write_text(p, json_text(obj) + "\n")
    return p


def make_folder(folder: str | Path) -> Path:
    """The output folder, created with its parents where missing; an `OutputError` if not."""
    folder = Path(folder).expanduser()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create output folder {folder}: {exc.strerror or exc}") from exc
    return folder


def read_csv_rows(path: str | Path, what: str, columns: tuple[str, ...]) -> list[dict[str, str]]:
    """The rows of a CSV file (`what` names it in errors) that has at least `columns` and one
    row; an `InputError` naming the file otherwise."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise InputError(f"{what} not found: {path}")
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read {what} {path}: {exc}") from None
    if not rows or not set(columns) <= set(rows[0]):
        raise InputError(f"{path} must be a CSV with columns {','.join(columns)} and a row")
    return rows


def sample_image_path() -> Path:
    """The fundus image shipped with the package (CC0): source of the synthetic sample video."""
    return Path(__file__).resolve().parent / "data" / "retina.jpg"


# --------------------------------------------------------------------------------------------
# Producing the next items while the current one is processed
# --------------------------------------------------------------------------------------------

_END = object()


class Lookahead(Iterator[T]):
    """Iterate `items` while a background thread produces the next ones, up to `depth` ahead,
    as long as `ahead` is set; it may change between items (`mosaic.scheduling`'s overlap trial).

    The items are produced in order by one thread at a time (the caller's, or the one worker's),
    so a generator is safe here. OpenCV and torch release the GIL, so producing item i+1
    overlaps the caller's work on item i. An exception in the producer is re-raised here at its
    item; `close` (or leaving a `with` block) waits for the item in production and stops.
    """

    def __init__(self, items: Iterable[T], depth: int = 2, ahead: bool = True) -> None:
        self._items = iter(items)
        self._depth = depth
        self._pending: deque[Future[Any]] = deque()
        self._pool: ThreadPoolExecutor | None = None
        self.ahead = ahead

    def __next__(self) -> T:
        item = self._pending.popleft().result() if self._pending else next(self._items, _END)
        if item is _END:
            self._pending.clear()
            raise StopIteration
        if self.ahead:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="lookahead")
            while len(self._pending) < self._depth:
                self._pending.append(self._pool.submit(next, self._items, _END))
        return item

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        self._pending.clear()

    def __enter__(self) -> Lookahead[T]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
