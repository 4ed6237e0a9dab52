"""`mosaic batch`: a folder of short synthetic videos and a corrupt file, through the CLI (local
process pool) and on a local Ray; discovery, manifests, resume, the summary files; signals to
the `mosaic` console script (SIGKILL, Ctrl-C) and an unreachable Ray cluster."""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from contextlib import suppress
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from mosaic.batch import run_batch, run_local
from mosaic.batch_summary import render_index
from mosaic.batch_tasks import VideoTask, find_tasks, read_manifest, safe_id
from mosaic.batch_video import FAILED, INTERRUPTED, NOT_RUN, OK, row_of
from mosaic.config import load_config
from mosaic.errors import InputError
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from tests.conftest import SAMPLE_IMAGE

runner = CliRunner()
IDS = ["corrupt", "deep__frames", "v0", "v1"]
MOSAIC = Path(sys.executable).with_name("mosaic")  # the console script of this environment
LINUX = sys.platform.startswith("linux") and Path("/proc/self/task").is_dir()


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    """in/: two .mp4 videos, a folder of frames one level down, a corrupt .mp4; a SIFT config."""
    root = tmp_path_factory.mktemp("batch")
    videos = root / "in"
    (videos / "deep").mkdir(parents=True)
    for seed, out in enumerate([videos / "v0.mp4", videos / "v1.mp4", videos / "deep" / "frames"]):
        params = SynthParams(n_frames=10, size=(200, 150), seed=seed, max_step_px=4.0)
        write_synthetic_video(SAMPLE_IMAGE, out, params)
    # a truncated copy (a broken download): no index ("moov atom"), OpenCV cannot open it
    (videos / "corrupt.mp4").write_bytes((videos / "v0.mp4").read_bytes()[:3000])
    config = root / "sift.toml"
    config.write_text('[features]\ndetector = "sift"\n')
    return videos, config


@pytest.fixture(scope="module")
def long_videos(tmp_path_factory):
    """in/: two 150-frame videos (over ten seconds each to build: time to signal the batch
    mid-video); a SIFT config."""
    root = tmp_path_factory.mktemp("long")
    (root / "in").mkdir()
    for seed in range(2):
        params = SynthParams(n_frames=150, size=(200, 160), seed=seed, max_step_px=4.0)
        write_synthetic_video(SAMPLE_IMAGE, root / "in" / f"v{seed}.mp4", params)
    config = root / "sift.toml"
    config.write_text('[features]\ndetector = "sift"\n')
    return root / "in", config


@pytest.fixture(scope="module")
def batch_run(archive, tmp_path_factory):
    """`mosaic batch` run once on the archive with 2 workers: (CLI result, OUT_DIR)."""
    videos, config = archive
    out = tmp_path_factory.mktemp("out") / "out"
    args = ["batch", str(videos), "-o", str(out), "-c", str(config), "--workers", "2"]
    return runner.invoke(app(), args), out


def app():
    from mosaic.cli import app

    return app


def _summary(out: Path) -> dict[str, dict]:
    with (out / "summary.csv").open() as fh:
        return {row["id"]: row for row in csv.DictReader(fh)}


class _Rows(HTMLParser):
    """The body rows of index.html: each row's cell texts, and the links and images in it."""

    def __init__(self):
        super().__init__()
        self.rows: list[dict] = []
        self._in_body = False

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "tbody":
            self._in_body = True
        elif self._in_body and tag == "tr":
            self.rows.append({"cells": [], "links": [], "images": [], "class": attrs["class"]})
        elif self._in_body and tag == "td":
            self.rows[-1]["cells"].append("")
        elif self._in_body and tag == "a":
            self.rows[-1]["links"].append(attrs["href"])
        elif self._in_body and tag == "img":
            self.rows[-1]["images"].append(attrs["src"])

    def handle_endtag(self, tag):
        if tag == "tbody":
            self._in_body = False

    def handle_data(self, data):
        if self._in_body and self.rows and self.rows[-1]["cells"]:
            self.rows[-1]["cells"][-1] += data


def _frames(report: dict) -> list[tuple[int, str]]:
    return [(f["index"], f["status"]) for f in report["frames"]]


def test_batch_builds_every_video_and_lists_the_corrupt_one_as_failed(archive, batch_run):
    result, out = batch_run
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    rows = _summary(out)
    assert sorted(rows) == IDS
    assert rows["corrupt"]["status"] == FAILED and "corrupt.mp4" in rows["corrupt"]["error"]
    for video_id in IDS[1:]:
        row = rows[video_id]
        assert row["status"] == OK and row["error"] == "", row
        assert int(row["frames"]) == 10 and float(row["registered_pct"]) >= 70
        assert float(row["fps"]) > 0 and float(row["time_s"]) > 0
        folder = out / video_id
        assert cv2.imread(str(folder / "mosaic.png")) is not None
        assert cv2.imread(str(folder / "thumbnail.jpg")) is not None
        report = json.loads((folder / "report.json").read_text())
        assert report["summary"]["complete"] is True
        assert "opened" in (folder / "log.txt").read_text()
    assert "moov atom" in (out / "corrupt" / "log.txt").read_text()  # ffmpeg's own stderr
    document = json.loads((out / "summary.json").read_text())
    assert document["counts"] == {"ok": 3, "failed": 1, "interrupted": 0, "not run": 0}
    assert [v["id"] for v in document["videos"]] == IDS  # input order (natural, recursive)
    assert "ok      v0: 10 frames" in result.output and "failed  corrupt:" in result.output


def test_batch_reports_match_mosaic_build(archive, batch_run, tmp_path):
    videos, config = archive
    _, out = batch_run
    for video, video_id in [
        (videos / "v0.mp4", "v0"),
        (videos / "deep" / "frames", "deep__frames"),
    ]:
        target = tmp_path / f"{video_id}.png"
        built = runner.invoke(app(), ["build", str(video), "-o", str(target), "-c", str(config)])
        assert built.exit_code == 0, built.output
        expected = json.loads(target.with_suffix(".json").read_text())
        got = json.loads((out / video_id / "report.json").read_text())
        assert _frames(got) == _frames(expected)
        assert got["summary"]["registered"] == expected["summary"]["registered"]
        for a, b in zip(got["frames"], expected["frames"], strict=True):
            if b["H_to_canvas"] is not None:
                np.testing.assert_allclose(a["H_to_canvas"], b["H_to_canvas"], atol=1e-3)
        assert got["config"] == expected["config"]


def test_index_html_lists_every_video_failed_first(batch_run):
    _, out = batch_run
    page = (out / "index.html").read_text()
    parser = _Rows()
    parser.feed(page)
    rows = parser.rows
    assert len(rows) == 4
    assert rows[0]["class"] == FAILED and "corrupt" in rows[0]["cells"][2]
    listed = sorted(row["cells"][2].split()[0] for row in rows)
    assert listed == IDS
    for row in rows[1:]:
        video_id = row["cells"][2].split()[0]
        assert row["images"] == [f"{video_id}/thumbnail.jpg"]
        assert f"{video_id}/mosaic.png" in row["links"]
        assert (out / row["images"][0]).is_file()
    assert "<script>" in page and "http" not in page  # self-contained: no external resource


def test_rerun_skips_the_videos_done(archive, batch_run):
    videos, config = archive
    _, out = batch_run
    before = {i: (out / i / "report.json").stat().st_mtime_ns for i in IDS[1:]}
    args = ["batch", str(videos), "-o", str(out), "-c", str(config), "--workers", "1"]
    again = runner.invoke(app(), args)
    assert again.exit_code == 1, again.output
    assert "3 of 4 videos already done" in again.output
    assert {i: (out / i / "report.json").stat().st_mtime_ns for i in IDS[1:]} == before
    rows = _summary(out)
    assert [rows[i]["resumed"] for i in IDS] == ["False", "True", "True", "True"]
    assert rows["v0"]["status"] == OK and rows["v0"]["frames"] == "10"


def test_ray_engine_on_a_local_two_cpu_ray(archive, batch_run, tmp_path):
    ray = pytest.importorskip("ray")
    videos, config = archive
    _, local = batch_run
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        result = run_batch(videos, tmp_path, load_config(config), engine="ray", progress=False)
    finally:
        ray.shutdown()
    assert result.counts == {"ok": 3, "failed": 1, "interrupted": 0, "not run": 0}
    assert [row["id"] for row in result.rows] == IDS
    for video_id in IDS[1:]:
        got = json.loads((tmp_path / video_id / "report.json").read_text())
        expected = json.loads((local / video_id / "report.json").read_text())
        assert _frames(got) == _frames(expected)
        assert (tmp_path / video_id / "mosaic.png").is_file()
    assert (tmp_path / "index.html").is_file()


def test_ray_engine_without_ray_says_how_to_install_it(archive, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    videos, _ = archive
    result = runner.invoke(app(), ["batch", str(videos), "-o", str(tmp_path), "--engine", "ray"])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "pip install 'retina-mosaic[ray]'" in lines[0], result.output


def test_find_tasks_searches_recursively_and_leaves_out_the_output(tmp_path):
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / "b" / "x.mp4").write_bytes(b"")
    (tmp_path / "a" / "x.avi").write_bytes(b"")
    (tmp_path / "a" / "x.mp4").write_bytes(b"")
    (tmp_path / "a" / "x.gt.json").write_text("{}")
    (tmp_path / ".hidden.mp4").write_bytes(b"")
    frames = tmp_path / "clip 2"
    frames.mkdir()
    cv2.imwrite(str(frames / "0.png"), np.zeros((4, 4, 3), np.uint8))
    (frames / "nested").mkdir()  # not searched: the folder is a video
    (frames / "nested" / "y.mp4").write_bytes(b"")
    out = tmp_path / "out" / "v"
    out.mkdir(parents=True)
    cv2.imwrite(str(out / "mosaic.png"), np.zeros((4, 4, 3), np.uint8))
    tasks = find_tasks(tmp_path, exclude=tmp_path / "out")
    assert [t.id for t in tasks] == ["a__b__x", "a__x", "a__x-2", "clip_2"]
    assert [t.video.name for t in tasks] == ["x.mp4", "x.avi", "x.mp4", "clip 2"]
    assert [t.id for t in find_tasks(tmp_path, "*.avi", tmp_path / "out")] == ["a__x"]
    assert [t.id for t in find_tasks(tmp_path, "a/b/*", tmp_path / "out")] == ["a__b__x"]
    assert [t.id for t in find_tasks(frames)] == ["clip_2"]  # a frame folder is one video
    with pytest.raises(InputError, match="no videos"):
        find_tasks(tmp_path, "*.mkv")
    with pytest.raises(InputError, match="not found"):
        find_tasks(tmp_path / "missing")


def test_manifest_columns_and_bad_rows(tmp_path):
    manifest = tmp_path / "list.csv"
    manifest.write_text(
        "video,config,id\nvids/a.mp4,fast.toml,first\nb.mp4,,\n,,\nc/b.mp4,,\n",
        encoding="utf-8",
    )
    tasks = read_manifest(manifest)
    assert [t.id for t in tasks] == ["first", "b", "row4", "c__b"]
    assert tasks[0].video == tmp_path / "vids" / "a.mp4"
    assert tasks[0].config == tmp_path / "fast.toml" and tasks[1].config is None
    assert tasks[2].error == "manifest row 4: no video given"
    assert find_tasks(manifest) == tasks
    manifest.write_text("video,id\na.mp4,x\nb.mp4,x\n")
    with pytest.raises(InputError, match="duplicate id"):
        read_manifest(manifest)
    manifest.write_text("path\na.mp4\n")
    with pytest.raises(InputError, match="'video' column"):
        read_manifest(manifest)


def test_manifest_per_video_config_and_missing_files_are_failed_rows(archive, tmp_path):
    videos, config = archive
    manifest = tmp_path / "list.csv"
    manifest.write_text(
        f"video,config,id\n{videos / 'v1.mp4'},{tmp_path / 'nope.toml'},badconfig\n"
        f"{videos / 'gone.mp4'},,missing\n,,\n"
    )
    stale = tmp_path / "out" / "missing" / "mosaic.png"  # of an earlier run
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"old")
    result = run_batch(manifest, tmp_path / "out", load_config(config), workers=1, progress=False)
    errors = {row["id"]: row["error"] for row in result.rows}
    assert all(row["status"] == FAILED for row in result.rows)
    assert not stale.exists() and all(row["mosaic"] is None for row in result.rows)
    assert "nope.toml" in errors["badconfig"] and "gone.mp4" in errors["missing"]
    assert errors["row4"] == "manifest row 4: no video given"


def crash_on_id(task, config, out, rerun):
    """A job for `run_local` whose worker process dies on the video named 'crash'."""
    if task.id == "crash":
        os._exit(3)
    return row_of(task, out, None, OK)


def test_a_crashing_worker_fails_only_its_own_video(tmp_path):
    tasks = [VideoTask(name, tmp_path / name) for name in ("a", "crash", "b", "c")]
    rows = {}
    run_local(
        tasks,
        None,
        tmp_path,
        "off",
        workers=2,
        threads=1,
        done=lambda task, row: rows.update({task.id: row}),
        job=crash_on_id,
    )
    assert {k: rows[k]["status"] for k in sorted(rows)} == {
        "a": OK,
        "b": OK,
        "c": OK,
        "crash": FAILED,
    }
    assert "died" in rows["crash"]["error"]


# --------------------------------------------------------------------------------------------
# The `mosaic` console script under signals
# --------------------------------------------------------------------------------------------


def _start(args: list, logs: Path) -> subprocess.Popen:
    """`mosaic batch ARGS` in a session of its own, as a terminal's foreground job (Ctrl-C goes
    to its whole process group); stdout / stderr into files in `logs`."""
    with (logs / "stdout.txt").open("wb") as out, (logs / "stderr.txt").open("wb") as err:
        command = [str(MOSAIC), "batch", *map(str, args)]
        return subprocess.Popen(command, stdout=out, stderr=err, start_new_session=True)


def _wait_until(ready: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _opened(out: Path, video_id: str) -> bool:
    """Whether the video is being built: its log says it was opened."""
    log = out / video_id / "log.txt"
    return log.is_file() and "opened" in log.read_text(errors="replace")


def _descendants(pid: int) -> set[int]:
    """The processes under `pid` (Linux: /proc/PID/task/TID/children)."""
    found: set[int] = set()
    todo = [pid]
    while todo:
        for children in Path(f"/proc/{todo.pop()}/task").glob("*/children"):
            with suppress(OSError):
                new = {int(child) for child in children.read_text().split()} - found
                found |= new
                todo += new
    return found


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie, dead but not yet reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _stop(proc: subprocess.Popen, others: set[int]) -> None:
    """Kill what a failed test may have left running."""
    if proc.poll() is None:
        proc.kill()
        proc.wait(timeout=10)
    for pid in filter(_alive, others):
        with suppress(OSError):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(not LINUX, reason="the parent-death signal is Linux's; reads /proc")
def test_workers_die_with_a_killed_batch(long_videos, tmp_path):
    videos, config = long_videos
    out = tmp_path / "out"
    batch = _start([videos, "-o", out, "-c", config, "--workers", "2"], tmp_path)
    workers: set[int] = set()
    try:
        _wait_until(lambda: _opened(out, "v0") and _opened(out, "v1"), 120, "both videos")
        workers = _descendants(batch.pid)
        assert len(workers) >= 2
        batch.kill()  # as the OOM killer does: no handler runs
        batch.wait(timeout=10)
        _wait_until(lambda: not any(map(_alive, workers)), 10, f"the workers {workers} to die")
    finally:
        _stop(batch, workers)


@pytest.mark.skipif(not LINUX, reason="reads /proc")
def test_sigterm_to_the_batch_alone_keeps_the_running_videos_partial_outputs(long_videos, tmp_path):
    """`kill PID` (a scheduler, `docker stop`) signals the batch, not its workers: it is taken
    as Ctrl-C and handed on to them, so each running video writes what it has, as after
    Ctrl-C (before: the workers built their videos to the end, or died with nothing)."""
    videos, config = long_videos
    out = tmp_path / "out"
    batch = _start([videos, "-o", out, "-c", config, "--workers", "2"], tmp_path)
    try:
        _wait_until(lambda: _opened(out, "v0") and _opened(out, "v1"), 120, "both videos")
        time.sleep(1.0)  # a few frames in
        batch.terminate()  # SIGTERM to the batch process only
        assert batch.wait(timeout=60) == 130
    finally:
        _stop(batch, set())
    stderr = (tmp_path / "stderr.txt").read_text()
    assert "Traceback" not in stderr, stderr
    rows = _summary(out)
    for video_id in ("v0", "v1"):
        assert rows[video_id]["status"] == INTERRUPTED, rows[video_id]
        summary = json.loads((out / video_id / "report.json").read_text())["summary"]
        assert summary["interrupted"] is True and 0 < summary["frames_read"] < 150
        assert cv2.imread(str(out / video_id / "mosaic.png")) is not None


@pytest.mark.slow  # starts a local Ray
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_under_ray_keeps_the_running_videos_partial_outputs(long_videos, tmp_path, signum):
    """Ctrl-C (the terminal signals the whole job) or SIGTERM to the batch alone (before: Ray's
    own handler ended it at once, nothing written)."""
    pytest.importorskip("ray")
    videos, config = long_videos
    out = tmp_path / "out"
    batch = _start([videos, "-o", out, "-c", config, "--engine", "ray"], tmp_path)
    try:
        _wait_until(lambda: _opened(out, "v0"), 120, "a Ray task to open v0")
        with suppress(AssertionError):  # v1 too, unless Ray has one CPU (then it is queued)
            _wait_until(lambda: _opened(out, "v1"), 5, "v1")
        time.sleep(1.0)  # a few frames in
        if signum == signal.SIGINT:
            os.killpg(batch.pid, signal.SIGINT)
        else:
            batch.terminate()
        assert batch.wait(timeout=60) == 130
    finally:
        _stop(batch, set())
    stderr = (tmp_path / "stderr.txt").read_text()
    assert "Traceback" not in stderr and "interrupted v0" in stderr, stderr
    rows = _summary(out)
    for video_id in ("v0", "v1"):
        if not _opened(out, video_id):  # queued: dropped
            assert rows[video_id]["status"] == NOT_RUN
            continue
        assert rows[video_id]["status"] == INTERRUPTED, rows[video_id]
        summary = json.loads((out / video_id / "report.json").read_text())["summary"]
        assert summary["interrupted"] is True and summary["complete"] is False
        assert 0 < summary["frames_read"] < 150
        assert cv2.imread(str(out / video_id / "mosaic.png")) is not None


def _on_ray_at(address: str, videos: Path, out: Path, *options: str) -> list[str]:
    """The arguments of `mosaic batch` joining the Ray cluster at `address`."""
    return [str(videos), "-o", str(out), "--engine", "ray", "--ray-address", address, *options]


@pytest.mark.parametrize("listening", [False, True], ids=["refused", "silent"])
def test_an_unreachable_ray_cluster_is_one_line_within_the_timeout(archive, tmp_path, listening):
    pytest.importorskip("ray")
    videos, _ = archive
    with socket.socket() as port:
        port.bind(("0.0.0.0", 0))  # all interfaces: Ray connects to this host's address
        if listening:
            port.listen()  # connections are accepted (by the kernel), nothing ever answers
        address = f"127.0.0.1:{port.getsockname()[1]}"
        command = [
            str(MOSAIC),
            "batch",
            *_on_ray_at(address, videos, tmp_path, "--ray-timeout", "5"),
        ]
        started = time.monotonic()
        result = subprocess.run(command, capture_output=True, text=True, timeout=60)
        elapsed_s = time.monotonic() - started
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert address in lines[0]
    assert elapsed_s < 30  # 5 s, and the start (Ray alone tries for about 14 minutes)


@pytest.mark.slow  # a time bound
def test_sigterm_ends_the_wait_for_a_ray_cluster_within_seconds(archive, tmp_path):
    pytest.importorskip("ray")
    videos, _ = archive
    with socket.socket() as port:
        port.bind(("0.0.0.0", 0))
        port.listen()
        port.settimeout(60)
        address = f"127.0.0.1:{port.getsockname()[1]}"
        batch = _start(_on_ray_at(address, videos, tmp_path / "out"), tmp_path)
        try:
            port.accept()[0].close()  # the probe, then Ray's attempts
            port.accept()[0].close()
            time.sleep(0.5)
            batch.terminate()
            started = time.monotonic()
            batch.wait(timeout=30)
            elapsed_s = time.monotonic() - started
        finally:
            _stop(batch, set())
    assert batch.returncode != 0
    assert elapsed_s < 10  # each of Ray's waits is 2 s (30 s by default)
    assert "Traceback" not in (tmp_path / "stderr.txt").read_text()


def test_ids_and_page_escape_odd_names():
    assert safe_id("visit 1/eye<left>.mp4") == "visit_1__eye_left_.mp4"
    assert safe_id("../..") == "__.."
    row = {
        "id": "<b>",
        "status": FAILED,
        "error": "x < y & z",
        "report": None,
        "log": None,
        "thumbnail": None,
        "mosaic": None,
    }
    page = render_index([row], {"input": "<in>"}, {FAILED: 1})
    assert "<b>" not in page.replace("<body>", "") and "x &lt; y &amp; z" in page


def test_manifest_patient_eye_and_visit_columns(tmp_path):
    """patient and eye name one eye's visits; a named manifest needs every row's visit."""
    manifest = tmp_path / "visits.csv"
    manifest.write_text(
        "video,patient,eye,visit\nb.mp4,anna,OD,2025-06-01\na.mp4,anna,OD,2024-11-20\n"
    )
    tasks = read_manifest(manifest)
    assert [(t.id, t.patient, t.visit) for t in tasks] == [
        ("b", "anna OD", "2025-06-01"), ("a", "anna OD", "2024-11-20")]  # fmt: skip
    assert [r["patient"] for r in (row_of(t, tmp_path, None, NOT_RUN) for t in tasks)] == [
        "anna OD"] * 2  # fmt: skip
    for text, fragment in (
        ("video,patient\na.mp4,anna\n", "needs a 'visit' column"),
        ("video,patient,visit\na.mp4,anna,1\nb.mp4,,2\n", "row 3: give the patient"),
        ("video,patient,visit\na.mp4,anna,1\nb.mp4,anna,1\n", "has a visit twice"),
    ):
        manifest.write_text(text)
        with pytest.raises(InputError, match=fragment):
            read_manifest(manifest)
    assert "patient" not in row_of(VideoTask("v", tmp_path / "v.mp4"), tmp_path, None, NOT_RUN)


@pytest.mark.slow  # two videos built, then compared: ~40 s on 2 shared cores
def test_batch_compares_a_patients_visits_onto_the_first(tmp_path):
    """Two synthetic visits of one eye (`synth --followup-of`'s hook: changes planted) in a
    manifest with patient, eye and visit, rows out of date order: the later visit is put on
    the earlier's mosaic within 2 px of the truth over the overlap, and the page shows both
    visits with the change map."""
    from types import SimpleNamespace

    from mosaic.compare import covered_area
    from mosaic.synthetic.followup import followup_hook, load_baseline_gt, source_to_mosaic
    from tests.mosaic.test_compare import MAX_ERROR_PX, alignment_error

    base, follow = tmp_path / "base.mp4", tmp_path / "follow.mp4"
    params = dict(n_frames=30, size=(480, 320))
    write_synthetic_video(SAMPLE_IMAGE, base, SynthParams(seed=0, **params))
    hook = followup_hook(load_baseline_gt(base), 1)
    write_synthetic_video(SAMPLE_IMAGE, follow, SynthParams(seed=1, **params), hook)
    manifest = tmp_path / "visits.csv"
    manifest.write_text(
        "video,patient,eye,visit\nfollow.mp4,anna,OD,2025-06-01\nbase.mp4,anna,OD,2024-11-20\n"
    )
    out = tmp_path / "out"
    args = ["batch", str(manifest), "-o", str(out), "--workers", "1", "--rerun", "save"]
    result = runner.invoke(app(), args)
    assert result.exit_code == 0, result.output
    assert "1 patients, 1 later visits: 1 compared, 0 not" in result.output
    summary = json.loads((out / "summary.json").read_text())
    anna = summary["patients"]["anna OD"]
    assert anna["baseline"] == "2024-11-20"
    assert [(r["visit"], r["status"]) for r in anna["visits"]] == [("2025-06-01", "registered")]
    written = json.loads((out / "compare" / "anna_OD" / "2025-06-01" / "compare.json").read_text())
    assert written["baseline"]["kind"] == written["followup"]["kind"] == "mosaic"

    reports = [json.loads((out / i / "report.json").read_text()) for i in ("base", "follow")]
    truths = [json.loads(p.with_suffix(".gt.json").read_text()) for p in (base, follow)]
    S_base, S_follow = (source_to_mosaic(r, g) for r, g in zip(reports, truths, strict=True))
    H_truth = S_base @ np.linalg.inv(S_follow)
    mosaics = [cv2.imread(str(out / i / "mosaic.png")) for i in ("base", "follow")]
    covered = [covered_area(m, r) for m, r in zip(mosaics, reports, strict=True)]
    h, w = covered[0].shape
    follow_on_base = cv2.warpPerspective(covered[1].astype(np.uint8), H_truth, (w, h)) > 0
    answer = SimpleNamespace(
        H_followup_to_baseline=np.asarray(written["H_followup_to_baseline"]),
        Q_followup_to_baseline=None
        if written["Q_followup_to_baseline"] is None
        else np.asarray(written["Q_followup_to_baseline"]),
        overlap=covered[0] & follow_on_base,
    )
    assert answer.overlap.mean() > 0.2
    assert alignment_error(answer, H_truth) < MAX_ERROR_PX
    assert written["regions"]  # the planted changes show

    page = (out / "index.html").read_text()
    assert "Visits compared" in page
    for src in ("compare/anna_OD/2024-11-20/baseline.jpg",
                "compare/anna_OD/2025-06-01/followup_warped.jpg",
                "compare/anna_OD/2025-06-01/change_map.jpg"):  # fmt: skip
        assert f"src='{src}'" in page and (out / src).is_file()
    header = (out / "summary.csv").read_text().splitlines()[0]
    assert header.endswith(",patient,visit")
    # --rerun save: the comparison's layers in its folder, the follow-up as written
    from tests.mosaic.test_viz import read_rrd
    from tests.mosaic.test_viz_compare import layer_image

    visit = out / "compare" / "anna_OD" / "2025-06-01"
    shown = layer_image(read_rrd(visit / "recording.rrd")["compare/followup"])
    warped = cv2.imread(str(visit / "followup_warped.png"))
    assert shown.shape == (*mosaics[0].shape[:2], 4)
    assert np.array_equal(shown[..., :3], warped[..., ::-1])
