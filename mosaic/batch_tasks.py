"""The videos of a batch (`mosaic batch`): one `VideoTask` per video, from a folder searched
recursively (video files, and folders of frames as one video each) or a CSV manifest (`video`,
optional `config`, `id`, and `patient` / `eye` with `visit`), each with a unique id: the
folder under OUT_DIR its outputs go to.
"""

from __future__ import annotations

import csv
import fnmatch
import re
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

from mosaic.errors import InputError
from mosaic.io import natural_key
from mosaic.runner import VIDEO_SUFFIXES, is_frame_folder


@dataclass(frozen=True)
class VideoTask:
    """One video of the batch: its id (the folder under OUT_DIR), its path, its config file."""

    id: str
    video: Path
    config: Path | None = None  # a manifest's per-video config (replaces --config)
    error: str | None = None  # a manifest row that cannot run: failed as it is
    patient: str | None = None  # a manifest's patient (and eye): its visits are compared
    visit: str | None = None  # the visit's label (a date), ordering the patient's visits


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
