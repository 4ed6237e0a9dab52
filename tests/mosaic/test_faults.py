"""Fault injection through the real command line (issue 15): Ctrl-C at start-up, while
registering and while rendering; SIGKILL mid-run; an exception in refinement; unwritable
outputs; NaN, inf and out-of-range config values; broken pairs CSVs; corrupt training state.

Signals need a real process: those tests start the `mosaic` console script (or `python -c`
with a fault patched in, then the same `mosaic.cli.main`) and read its stderr as it runs. The
rest drive the same typer app in-process. Every case asserts what the user sees (exit code,
one `error:` / `interrupted` line, never a traceback) and what survives on disk.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import glampoints.training as training
from glampoints.training import TrainConfig, load_checkpoint, train
from mosaic.cli import app
from mosaic.config import Config, config_from_dict, value_range, with_overrides
from mosaic.errors import ConfigError
from mosaic.glampoints_cli import app as glampoints_app
from mosaic.io import open_frames
from mosaic.runner import Outputs, run_video
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from tests.conftest import SAMPLE_IMAGE
from tests.glampoints.conftest import vessel_image
from tests.helpers import locked

MOSAIC = Path(sys.executable).with_name("mosaic")  # the console script of this environment
N_FRAMES = 80
runner = CliRunner()


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _clip(tmp_path_factory, name: str, **params) -> Path:
    """A synthetic video of the shipped sample (`SynthParams(**params)`) in a fresh folder."""
    out = tmp_path_factory.mktemp("faults") / name
    write_synthetic_video(SAMPLE_IMAGE, out, SynthParams(**params))
    return out


@pytest.fixture(scope="module")
def long_clip(tmp_path_factory) -> Path:
    """80 frames of 200x160: a few seconds of streaming, long enough to signal mid-run."""
    return _clip(
        tmp_path_factory, "clip.mp4", n_frames=N_FRAMES, size=(200, 160), seed=3, max_step_px=4.0
    )


@pytest.fixture(scope="module")
def short_clip(tmp_path_factory) -> Path:
    return _clip(
        tmp_path_factory, "short.mp4",
        n_frames=8, size=(200, 160), seed=4, max_step_px=4.0, nuisances=False,
    )  # fmt: skip


class Running:
    """A started command whose stdout / stderr are read as they come (progress bars too)."""

    def __init__(
        self,
        args: list[str],
        inject: str | None = None,
        cwd: Path | None = None,
        program: Path = MOSAIC,
    ):
        if inject is None:
            command = [str(program), *args]
        else:  # the same entry point, with a fault patched in first
            script = f"{inject}\nimport sys\nfrom mosaic.cli import main\n"
            script += f"sys.argv = {['mosaic', *args]!r}\nmain()\n"
            command = [sys.executable, "-c", script]
        self.proc = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=cwd
        )
        self._out: list[bytes] = []
        self._err: list[bytes] = []
        self._threads = [
            threading.Thread(target=self._pump, args=(self.proc.stdout, self._out), daemon=True),
            threading.Thread(target=self._pump, args=(self.proc.stderr, self._err), daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    @staticmethod
    def _pump(stream, chunks: list[bytes]) -> None:
        for chunk in iter(lambda: os.read(stream.fileno(), 4096), b""):
            chunks.append(chunk)

    @property
    def stderr(self) -> str:
        return b"".join(self._err).decode("utf-8", "replace")

    @property
    def stdout(self) -> str:
        return b"".join(self._out).decode("utf-8", "replace")

    def wait_for(self, ready: Callable[[], bool], timeout_s: float = 120.0) -> None:
        """Poll until `ready()`; fail if the command ends or the time runs out first."""
        deadline = time.monotonic() + timeout_s
        while not ready():
            assert self.proc.poll() is None, f"ended first ({self.proc.returncode}): {self.stderr}"
            assert time.monotonic() < deadline, f"timed out: {self.stderr[-2000:]}"
            time.sleep(0.01)

    def registered(self) -> int:
        """The registered count the progress bar last showed."""
        counts = re.findall(r"mosaic:.*?registered=(\d+)", self.stderr)
        return int(counts[-1]) if counts else 0

    def finish(self, timeout_s: float = 120.0) -> int:
        code = self.proc.wait(timeout=timeout_s)
        for thread in self._threads:
            thread.join(timeout=5)
        return code

    def messages(self) -> list[str]:
        """stderr without the progress bars: what the user reads."""
        parts = re.split(r"[\r\n]", self.stderr)
        return [p for p in parts if p.strip() and not re.match(r"\s*(mosaic|render):", p)]


def _lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def _one_error_line(result, code: int = 2) -> str:
    """The single `error:` line of a failed in-process command (no traceback)."""
    assert result.exit_code == code, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output
    lines = [ln for ln in _lines(result.stderr) if not re.search(r"\d+%\|", ln)]  # not bars
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    return lines[0]


def _report(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def _assert_partial(report: dict, mosaic: Path) -> None:
    """A report of an unfinished run: not complete, one entry per frame read, its mosaic
    readable at the size the report gives."""
    summary = report["summary"]
    assert summary["complete"] is False
    assert len(report["frames"]) == summary["frames_read"] > 0
    assert summary["registered"] == sum(f["status"] == "registered" for f in report["frames"])
    image = cv2.imread(str(mosaic))
    assert image is not None
    main = next(s for s in report["segments"] if s["index"] == report["main_segment"])
    assert image.shape[:2] == (main["height"], main["width"])


# --------------------------------------------------------------------------------------------
# Ctrl-C and SIGKILL
# --------------------------------------------------------------------------------------------


def _torch_loaded(pid: int) -> bool:
    """Whether the process has mapped torch's library: it is importing the libraries."""
    try:
        return "libtorch" in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads /proc/PID/maps")
def test_ctrl_c_at_start_up_exits_130_without_a_traceback(short_clip, tmp_path):
    out = tmp_path / "m.png"
    run = Running(["build", str(short_clip), "-o", str(out)])
    run.wait_for(lambda: _torch_loaded(run.proc.pid), timeout_s=60)
    run.proc.send_signal(signal.SIGINT)  # torch takes a second or more to import
    assert run.finish() == 130, run.stderr
    assert run.messages() == ["interrupted"], run.stderr
    assert not out.exists() and not out.with_suffix(".json").exists()


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads /proc/PID/maps")
def test_ctrl_c_while_glampoints_starts_exits_130_without_a_traceback(tmp_path):
    program = MOSAIC.with_name("glampoints")
    run = Running(["detect", str(tmp_path / "none.png")], program=program)
    run.wait_for(lambda: _torch_loaded(run.proc.pid), timeout_s=60)
    run.proc.send_signal(signal.SIGINT)
    assert run.finish() == 130, run.stderr
    assert run.messages() == ["interrupted"], run.stderr


def test_ctrl_c_while_registering_writes_the_frames_so_far(long_clip, tmp_path):
    out = tmp_path / "m.png"
    run = Running(["build", str(long_clip), "-o", str(out)])
    run.wait_for(lambda: run.registered() >= 5)
    run.proc.send_signal(signal.SIGINT)
    assert run.finish() == 130, run.stderr
    assert run.messages() == ["interrupted: partial mosaic and report written"], run.stderr
    report = _report(out.with_suffix(".json"))
    _assert_partial(report, out)
    assert report["summary"]["interrupted"] is True
    assert 5 <= report["summary"]["frames_read"] < N_FRAMES


def test_ctrl_c_while_rendering_keeps_every_registered_frame(long_clip, tmp_path):
    out = tmp_path / "m.png"
    run = Running(["build", str(long_clip), "-o", str(out)])
    run.wait_for(lambda: "render:" in run.stderr)
    run.proc.send_signal(signal.SIGINT)
    assert run.finish() == 130, run.stderr
    assert run.messages() == ["interrupted: partial mosaic and report written"], run.stderr
    report = _report(out.with_suffix(".json"))
    _assert_partial(report, out)
    summary = report["summary"]
    assert summary["interrupted"] is True and summary["tracking"]["rerendered"] is False
    assert summary["frames_read"] == N_FRAMES  # streaming had ended: nothing was lost
    assert summary["registered"] >= 0.9 * N_FRAMES


def test_sigkill_mid_run_leaves_a_readable_checkpoint(long_clip, tmp_path):
    config = tmp_path / "c.toml"
    config.write_text("[pipeline]\ncheckpoint_every_s = 0.3\n")
    out = tmp_path / "m.png"
    report_path = out.with_suffix(".json")
    run = Running(["build", str(long_clip), "-o", str(out), "-c", str(config)])
    run.wait_for(lambda: report_path.exists() and run.registered() >= 10)
    run.proc.kill()  # no handler runs: what is on disk is what a power cut would leave
    assert run.finish() == -signal.SIGKILL
    report = _report(report_path)  # whole JSON: written atomically
    summary = report["summary"]
    assert summary["checkpoint"] is True and summary["complete"] is False
    assert summary["interrupted"] is False
    assert 0 < summary["frames_read"] < N_FRAMES
    assert len(report["frames"]) == summary["frames_read"]
    assert cv2.imread(str(out)) is not None  # the mosaic beside it is a whole PNG


def test_checkpoints_are_replaced_by_the_final_outputs(short_clip, tmp_path):
    config = with_overrides(Config(), pipeline={"checkpoint_every_s": 1e-3})
    outputs = Outputs(tmp_path / "m.png", tmp_path / "m.json")
    writes: list[dict] = []

    def on_record(record) -> None:  # the checkpoint of the frame before is on disk by now
        if outputs.report.exists():
            writes.append(_report(outputs.report)["summary"])

    run = run_video(short_clip, config, outputs, on_record=on_record)
    assert writes and all(s["checkpoint"] and not s["complete"] for s in writes)
    assert [s["frames_read"] for s in writes] == list(range(1, len(writes) + 1))
    final = _report(outputs.report)["summary"]
    assert run.complete and final["complete"] is True and final["checkpoint"] is False
    assert not list(tmp_path.glob(".*.tmp*"))


# --------------------------------------------------------------------------------------------
# Exceptions
# --------------------------------------------------------------------------------------------

BROKEN_REFINEMENT = """
import numpy as np
from mosaic.segments import Segments
def _broken(self):
    raise np.linalg.LinAlgError("Singular matrix")
Segments.refine = _broken
"""

BROKEN_TRACKER = """
from mosaic import tracking
_track = tracking.KeyframeTracker.track
def _broken(self, index, *args, **kwargs):
    if index == 4:
        raise TypeError("injected bug")
    return _track(self, index, *args, **kwargs)
tracking.KeyframeTracker.track = _broken
"""

BROKEN_PAIR = """
import mosaic.pair_files
def _broken(*args, **kwargs):
    raise TypeError("injected bug\\nsecond line of its text")
mosaic.pair_files.register_pair = _broken
"""


def test_an_exception_in_refinement_writes_the_live_mosaic_and_exits_1(short_clip, tmp_path):
    out = tmp_path / "m.png"
    run = Running(["build", str(short_clip), "-o", str(out)], inject=BROKEN_REFINEMENT)
    assert run.finish() == 1, run.stderr
    assert run.messages() == [
        "error: failed while refining / rendering: LinAlgError: Singular matrix; "
        "the live mosaic and report written"
    ], run.stderr
    report = _report(out.with_suffix(".json"))
    _assert_partial(report, out)
    assert report["summary"]["frames_read"] == 8 and report["summary"]["interrupted"] is False
    assert "Singular matrix" in report["summary"]["error"]


def test_a_bug_while_registering_keeps_the_frames_before_it(short_clip, tmp_path):
    out = tmp_path / "m.png"
    run = Running(["build", str(short_clip), "-o", str(out)], inject=BROKEN_TRACKER)
    assert run.finish() == 1, run.stderr
    [message] = run.messages()
    assert message.startswith("error: failed while registering: TypeError: injected bug")
    assert message.endswith("; the live mosaic and report written")
    report = _report(out.with_suffix(".json"))
    _assert_partial(report, out)
    assert report["summary"]["registered"] == 4  # frames 0-3, placed before the bug
    assert "injected bug" in report["summary"]["error"]


def test_an_internal_error_outside_a_run_is_one_line_and_exit_1(tmp_path):
    image = tmp_path / "a.png"
    cv2.imwrite(str(image), vessel_image((96, 96), seed=1))
    run = Running(["register", str(image), str(image)], inject=BROKEN_PAIR)
    assert run.finish() == 1
    assert run.messages() == [
        "error: internal error: TypeError: injected bug (-v shows the traceback)"
    ], run.stderr


def test_an_empty_or_fake_video_is_one_line(tmp_path):
    fake = tmp_path / "fake.mp4"
    fake.write_bytes(os.urandom(2000))
    run = Running(["build", str(fake), "-o", str(tmp_path / "m.png")])
    assert run.finish() == 2
    assert run.messages() == [f"error: not a video OpenCV can read: {fake}"], run.stderr


def test_probing_a_fake_video_keeps_ffmpeg_off_stderr(tmp_path, capfd):
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    with pytest.raises(Exception, match="not a video OpenCV can read"):
        open_frames(empty)
    assert "moov" not in capfd.readouterr().err


def test_small_frames_and_odd_sizes_are_warned_once_each(tmp_path):
    folder = tmp_path / "tiny"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(8):
        size = (12, 12) if i in (3, 5) else (16, 16)  # two frames of another size
        cv2.imwrite(str(folder / f"f{i}.png"), rng.integers(0, 255, (*size, 3), np.uint8))
    run = Running(["build", str(folder), "-o", str(tmp_path / "m.png"), "--detector", "sift"])
    code = run.finish()
    warnings = [m for m in run.messages() if m.startswith("WARNING")]
    assert sum("too small to register" in w for w in warnings) == 1, warnings
    assert sum("differs from the first frame" in w for w in warnings) == 1, warnings
    assert "Traceback" not in run.stderr and code in (0, 2)


# --------------------------------------------------------------------------------------------
# Unwritable outputs: found before the first frame, whoever runs the tests
# --------------------------------------------------------------------------------------------


def _cannot_create_in(folder: Path) -> bool:
    try:
        (folder / "probe.png").touch()
    except OSError:
        return True
    (folder / "probe.png").unlink()
    return False


def test_an_unwritable_folder_fails_before_the_first_frame(short_clip, tmp_path):
    folder = tmp_path / "locked"
    folder.mkdir()
    with locked(folder):
        assert _cannot_create_in(folder)  # the premise holds, as root too
        result = runner.invoke(app, ["build", str(short_clip), "-o", str(folder / "m.png")])
        line = _one_error_line(result)
    assert str(folder) in line and ("not writable" in line or "cannot write" in line)
    assert "frames read" not in result.stdout  # nothing was processed
    assert list(folder.iterdir()) == []


def test_an_unwritable_report_fails_before_the_mosaic_is_written(short_clip, tmp_path):
    folder = tmp_path / "locked"
    folder.mkdir()
    out = tmp_path / "m.png"
    with locked(folder):
        args = ["build", str(short_clip), "-o", str(out), "--report", str(folder / "r.json")]
        _one_error_line(runner.invoke(app, args))
    assert not out.exists()


def test_a_read_only_or_immutable_file_fails_before_the_first_frame(short_clip, tmp_path):
    out = tmp_path / "m.png"
    out.write_bytes(b"an earlier mosaic")
    with locked(out):
        line = _one_error_line(runner.invoke(app, ["build", str(short_clip), "-o", str(out)]))
    assert str(out) in line
    assert out.read_bytes() == b"an earlier mosaic"  # untouched, and not a 0-byte file


def test_a_name_the_file_system_refuses_fails_before_the_first_frame(short_clip, tmp_path):
    out = tmp_path / ("m" * 300 + ".png")  # longer than NAME_MAX: refused whoever we are
    line = _one_error_line(runner.invoke(app, ["build", str(short_clip), "-o", str(out)]))
    assert "cannot write" in line and "name too long" in line.lower()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("options", "fragment"),
    [
        (["-o", "out.json"], "unsupported output format '.json'"),  # a report is no mosaic
        (["-o", "m.png", "--report", "r.png"], "unsupported output format '.png' (use json)"),
        (["-o", "m.txt"], "unsupported output format '.txt'"),
        (["-o", "m.png", "--rerun", "save", "--rerun-target", "r.json"], "use rrd"),
    ],
)
def test_an_output_format_that_cannot_be_written_fails_before_the_first_frame(
    short_clip, tmp_path, monkeypatch, options, fragment
):
    """The mosaic takes only the image formats OpenCV writes, the report only JSON, the
    recording only .rrd: found before the first frame, not when the whole run is written
    (issue 40: `-o out.json` ran the whole video, then could not encode it)."""
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["build", str(short_clip), *options])
    assert fragment in _one_error_line(result)
    assert "frames read" not in result.stdout
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "options",
    [
        ["-o", "m.png", "--report", "m.png"],
        ["-o", "m.png", "--report", "sub/../m.png"],
        ["-o", "m.png", "--report", "link.json"],  # a link to the mosaic
        ["-o", "m.png", "--rerun", "save", "--rerun-target", "rec.rrd", "--report", "m.rrd.json"],
    ],
)
def test_outputs_of_one_build_must_be_distinct_files(short_clip, tmp_path, monkeypatch, options):
    """Two outputs naming one file (spelt another way, or through a link) are one line, exit
    2, before the first frame (issue 40: `-o m.png --report m.png` exited 0 with the mosaic
    overwritten by the report)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    (tmp_path / "link.json").symlink_to("m.png")
    (tmp_path / "m.rrd.json").symlink_to("rec.rrd")
    result = runner.invoke(app, ["build", str(short_clip), *options])
    line = _one_error_line(result)
    assert "are the same file" in line and ("--report" in line), line
    assert "frames read" not in result.stdout
    assert not (tmp_path / "m.png").exists() and not (tmp_path / "rec.rrd").exists()


def test_outputs_of_one_register_must_be_distinct_and_not_its_inputs(tmp_path):
    """`register --warp X --matches X` and `--warp FIXED` are refused before registering;
    `--warp` and `--matches` take only image formats."""
    fixed, moving = tmp_path / "a.png", tmp_path / "b.png"
    for path, seed in ((fixed, 1), (moving, 2)):
        cv2.imwrite(str(path), vessel_image((160, 160), seed=seed))
    kept = fixed.read_bytes()
    pair = ["register", str(fixed), str(moving), "--detector", "sift"]
    cases = [
        (["--warp", str(tmp_path / "x.png"), "--matches", str(tmp_path / "x.png")], "same file"),
        (["--warp", str(fixed)], "--warp would write over the input FIXED"),
        (["--matches", str(tmp_path / "sub" / ".." / "b.png")], "over the input MOVING"),
        (["--warp", str(tmp_path / "w.json")], "unsupported output format '.json'"),
    ]
    (tmp_path / "sub").mkdir()
    for options, fragment in cases:
        result = runner.invoke(app, [*pair, *options])
        assert fragment in _one_error_line(result), options
        assert "status" not in result.stdout
    assert fixed.read_bytes() == kept and not (tmp_path / "x.png").exists()


# --------------------------------------------------------------------------------------------
# Config values
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "key", "allowed"),
    [
        ("[features]\ndetect_scale = nan\n", "[features] detect_scale", "in [0.1, 1]"),
        ("[features]\ndescriptor_size_px = inf\n", "[features] descriptor_size_px", "in [1, 100]"),
        ("[registration]\nreproj_threshold_px = nan\n", "reproj_threshold_px", "in (0, 100]"),
        ("[registration]\nconfidence = 1.5\n", "[registration] confidence", "in (0, 1)"),
        ("[registration]\nconfidence = 0\n", "[registration] confidence", "in (0, 1)"),
        ("[compose]\nmax_canvas_px = -inf\n", "[compose] max_canvas_px", "in [64, 32768]"),
        ("[keyframes]\nmin_overlap = 2.0\n", "[keyframes] min_overlap", "in [0, 1]"),
        ("[pipeline]\ncheckpoint_every_s = -1\n", "checkpoint_every_s", "in [0, 86400]"),
    ],
)
def test_bad_config_values_are_one_line_naming_key_and_range(short_clip, tmp_path, text, key,
                                                              allowed):  # fmt: skip
    config = tmp_path / "c.toml"
    config.write_text(text)
    out = tmp_path / "m.png"
    line = _one_error_line(runner.invoke(app, ["build", str(short_clip), "-o", str(out),
                                               "-c", str(config)]))  # fmt: skip
    assert key in line and allowed in line, line
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_absurd_values_of_every_numeric_key_are_one_line_naming_the_key(short_clip, tmp_path):
    """1e30, -1, NaN, inf (and for an integer key 2**40, which OpenCV cannot take as a C int)
    in any numeric key of any table: one line naming the key through `mosaic build --config`,
    before the first frame (issue 40: max_iters, descriptor_size_px and nms_window_px were
    accepted and ended the run mid-way)."""
    out = tmp_path / "m.png"
    config = tmp_path / "c.toml"
    for (table, key), default in _numeric_defaults().items():
        huge = [2**40] if isinstance(default, int) else []
        for value in ["1e30", "-1", "nan", "inf", *map(str, huge)]:
            config.write_text(f"[{table}]\n{key} = {value}\n")
            args = ["build", str(short_clip), "-o", str(out), "-c", str(config)]
            line = _one_error_line(runner.invoke(app, args))
            assert f"config [{table}] {key} must be" in line, (value, line)
            assert str(value_range(table, key)) in line, line
    assert list(tmp_path.iterdir()) == [config]  # no output of any run


@pytest.mark.parametrize(("option", "value"), [("--step", "0"), ("--max-frames", "-1")])
def test_bad_command_line_values_are_one_line(short_clip, tmp_path, option, value):
    args = ["build", str(short_clip), "-o", str(tmp_path / "m.png"), option, value]
    assert option.strip("-").replace("-", "_") in _one_error_line(runner.invoke(app, args))


def _edge_values() -> Iterator[tuple[str, str, float]]:
    """Every numeric key at the edges of its range: 0 where allowed, its finite bounds."""
    for (table, key), default in _numeric_defaults().items():
        allowed = value_range(table, key)
        edges = {v for v in (0.0, allowed.low, allowed.high) if math.isfinite(v) and v in allowed}
        for edge in sorted(edges):
            if isinstance(default, float) or edge == int(edge):
                yield table, key, type(default)(edge)


def _numeric_defaults() -> dict[tuple[str, str], float]:
    raw = {t: vars(getattr(Config(), t)) for t in vars(Config())}
    return {
        (t, k): v
        for t, values in raw.items()
        for k, v in values.items()
        if isinstance(v, int | float) and not isinstance(v, bool)
    }


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> Path:
    return _clip(
        tmp_path_factory, "tiny",
        n_frames=4, size=(160, 128), seed=5, max_step_px=3.0, nuisances=False,
    )  # fmt: skip


@pytest.mark.slow
@pytest.mark.filterwarnings("error::RuntimeWarning")  # numpy's overflow: a range too wide
def test_every_value_a_config_accepts_runs(tiny_clip, tmp_path):
    """No value inside a key's range ends in an exception or a numpy warning: the ranges are
    the real limits (each key at 0 where allowed and at its bounds, one short run each)."""
    glampoints = Config()
    sift = with_overrides(Config(), features={"detector": "sift"})
    failures = []
    for table, key, value in _edge_values():
        base = glampoints if table == "features" else sift
        config = with_overrides(base, **{table: {key: value}})
        try:
            run = run_video(tiny_clip, config, rerender=True)
        except ConfigError as exc:  # e.g. a descriptor the detector does not have
            failures.append(f"{table}.{key}={value}: {exc}")
            continue
        except Exception as exc:
            failures.append(f"{table}.{key}={value}: {type(exc).__name__}: {exc}")
            continue
        if run.error is not None:
            failures.append(f"{table}.{key}={value}: {run.error}")
    assert failures == []


def test_config_loader_rejects_non_finite_values_everywhere():
    for (table, key), _ in _numeric_defaults().items():
        for value in (math.nan, math.inf, -math.inf):
            with pytest.raises(ConfigError, match=re.escape(f"[{table}] {key}")):
                config_from_dict({table: {key: value}})


# --------------------------------------------------------------------------------------------
# Broken pairs CSVs
# --------------------------------------------------------------------------------------------


def test_a_broken_pairs_csv_gives_one_failed_line_per_bad_row_and_goes_on(tmp_path):
    image = vessel_image((160, 160), seed=3)
    cv2.imwrite(str(tmp_path / "a.png"), image)
    shifted = np.roll(image, (4, 6), axis=(0, 1))
    cv2.imwrite(str(tmp_path / "b.png"), shifted)
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    (tmp_path / "pairs.csv").write_text(
        "fixed,moving\n"
        "a.png\n"  # a missing column
        "a.png,missing.png\n"  # a missing image
        "broken.png,a.png\n"  # an unreadable image
        ",b.png\n"  # an empty cell
        "a.png,b.png\n"  # a good pair, after all of them
    )
    result = runner.invoke(app, ["register", "--pairs", str(tmp_path / "pairs.csv"),
                                 "--detector", "sift"])  # fmt: skip
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    rows = [json.loads(line) for line in _lines(result.stdout)]
    assert [r["status"] for r in rows] == ["failed"] * 4 + ["registered"]
    assert "row 2" in rows[0]["reason"] and "row 5" in rows[3]["reason"]
    assert "missing.png" in rows[1]["reason"] and "broken.png" in rows[2]["reason"]
    H = np.array(rows[4]["H_moving_to_fixed"])
    np.testing.assert_allclose(H[:2, 2], [-6, -4], atol=0.5)  # b is a shifted by (6, 4)


@pytest.mark.parametrize(
    ("content", "fragment"),
    [(b"", "columns fixed,moving"), (b"a,b\nx,y\n", "columns fixed,moving"),
     (b"\xff\xfe\x00bad", "cannot read pairs file")],
)  # fmt: skip
def test_an_unusable_pairs_csv_is_one_line(tmp_path, content, fragment):
    (tmp_path / "pairs.csv").write_bytes(content)
    line = _one_error_line(runner.invoke(app, ["register", "--pairs", str(tmp_path / "pairs.csv")]))
    assert fragment in line


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [(["--warp", "w.png"], "--warp"), (["--matches", "m.png"], "--matches"),
     (["a.png", "b.png"], "FIXED/MOVING")],
)  # fmt: skip
def test_options_of_one_pair_are_refused_with_pairs(tmp_path, extra, fragment):
    """--warp, --matches and FIXED MOVING name one pair's outputs: with --pairs they would be
    ignored, so the command says so instead of running."""
    (tmp_path / "pairs.csv").write_text("fixed,moving\na.png,b.png\n")
    args = ["register", "--pairs", str(tmp_path / "pairs.csv"), *extra]
    line = _one_error_line(runner.invoke(app, args))
    assert fragment in line and "--pairs" in line
    assert not (Path.cwd() / "w.png").exists() and not (Path.cwd() / "m.png").exists()


# --------------------------------------------------------------------------------------------
# Evaluate and bench: explicitly named detectors
# --------------------------------------------------------------------------------------------


@pytest.fixture
def bad_weights(tmp_path) -> Path:
    config = tmp_path / "bad_weights.toml"
    config.write_text(f'[features]\nweights = "{tmp_path / "missing.pt"}"\n')
    return config


def test_evaluate_with_a_named_detector_that_cannot_load_is_an_error(
    short_clip, tmp_path, bad_weights
):
    args = ["evaluate", str(short_clip), "--detector", "glampoints,sift", "-c", str(bad_weights),
            "--out", str(tmp_path / "ev")]  # fmt: skip
    line = _one_error_line(runner.invoke(app, args))
    assert "GLAMpoints weights file not found" in line
    assert not (tmp_path / "ev").exists()  # no table without GLAMpoints


def test_glampoints_evaluate_with_a_named_detector_that_cannot_load_is_an_error(
    tmp_path, bad_weights
):
    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), vessel_image((128, 128), seed=2))
    args = ["evaluate", str(images), "--format", "synthetic", "--detector", "glampoints",
            "-c", str(bad_weights), "--out", str(tmp_path / "ev")]  # fmt: skip
    assert "weights file not found" in _one_error_line(runner.invoke(glampoints_app, args))


def test_bench_errors_on_a_named_detector_and_skips_a_default_one(tmp_path, bad_weights):
    args = ["bench", "--detector", "glampoints", "-c", str(bad_weights), "--frames", "10",
            "--size", "120x100", "--no-rerun"]  # fmt: skip
    assert "weights file not found" in _one_error_line(runner.invoke(app, args))
    from mosaic.eval.bench import format_table, run_bench

    config = with_overrides(Config(), features={"weights": str(tmp_path / "missing.pt")})
    rows = run_bench(["glampoints", "sift"], (120, 100), 10, config, explicit=False)
    assert rows[0].name == "sift" and all(r.detector == "sift" for r in rows)
    assert format_table([]).split() == format_table(rows).splitlines()[0].split()


# --------------------------------------------------------------------------------------------
# Training: corrupt log, non-finite loss, mismatched checkpoint
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[TrainConfig, Path]:
    """A tiny finished epoch (4 images, batch 2: 2 steps) with its last.pt and metrics."""
    root = tmp_path_factory.mktemp("train")
    for name, n, seed in (("train", 4, 100), ("val", 1, 200)):
        (root / name).mkdir()
        for i in range(n):
            img = vessel_image((120, 140), seed=seed + i)
            cv2.imwrite(str(root / name / f"{i}.png"), np.dstack([img // 2, img, img // 3]))
    cfg = TrainConfig(
        data_dir=str(root / "train"), val_dir=str(root / "val"), out_dir=str(root / "run"),
        epochs=3, batch_size=2, crop=64, pairs_per_image=1, val_pairs_per_image=2,
        val_crop=64, num_threads=1, checkpoint_every=1, nms_window_px=6, max_steps=2,
    )  # fmt: skip
    train(cfg)
    return cfg, root / "run"


def _copy_run(trained, tmp_path) -> tuple[TrainConfig, Path]:
    cfg, run = trained
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    return TrainConfig(**{**vars(cfg), "out_dir": str(copy)}), copy


def _resume_args(cfg: TrainConfig, max_steps: int) -> list[str]:
    return ["train", "--data", cfg.data_dir, "--val", cfg.val_dir, "--out", cfg.out_dir,
            "--resume", "--max-steps", str(max_steps), "--epochs", "3"]  # fmt: skip


def test_a_partial_last_metrics_line_is_dropped_with_a_warning(trained, tmp_path, caplog):
    cfg, run = _copy_run(trained, tmp_path)
    metrics = run / "metrics.jsonl"
    whole = _lines(metrics.read_text())
    assert [json.loads(line)["epoch"] for line in whole] == [1]
    with metrics.open("a") as fh:
        fh.write('{"epoch": 2, "step": 4, "train_lo')  # a kill while appending
    result = runner.invoke(glampoints_app, _resume_args(cfg, 4))
    assert result.exit_code == 0, result.output
    assert any("partial last line" in r.getMessage() for r in caplog.records)
    records = [json.loads(line) for line in _lines(metrics.read_text())]
    assert [r["epoch"] for r in records] == [1, 2]  # the partial line replaced by the real one
    assert records[0] == json.loads(whole[0])


def test_a_corrupt_metrics_line_is_a_training_error(trained, tmp_path):
    cfg, run = _copy_run(trained, tmp_path)
    metrics = run / "metrics.jsonl"
    metrics.write_text("not json\n" + metrics.read_text())
    line = _one_error_line(runner.invoke(glampoints_app, _resume_args(cfg, 4)))
    assert f"{metrics} line 1 is not a JSON record" in line


def test_a_non_finite_loss_stops_training_and_keeps_the_last_good_checkpoint(
    trained, tmp_path, monkeypatch
):
    cfg, run = _copy_run(trained, tmp_path)
    before = load_checkpoint(run / "last.pt")
    real_loss = training.glampoints_loss

    def nan_loss(*args, **kwargs):
        out = real_loss(*args, **kwargs)
        return {**out, "total": out["total"] * float("nan")}

    monkeypatch.setattr(training, "glampoints_loss", nan_loss)
    line = _one_error_line(runner.invoke(glampoints_app, _resume_args(cfg, 4)))
    assert "non-finite loss at step 3 (epoch 2)" in line and "holds step 2" in line
    after = load_checkpoint(run / "last.pt")
    assert after["step"] == before["step"] == 2
    for name, tensor in before["model"].items():
        assert torch.equal(tensor, after["model"][name]) and torch.isfinite(tensor).all()


def test_a_checkpoint_that_does_not_fit_is_a_training_error(trained, tmp_path):
    cfg, run = _copy_run(trained, tmp_path)
    ckpt = load_checkpoint(run / "last.pt")
    first = next(iter(ckpt["model"]))
    ckpt["model"][first] = torch.zeros(3, 3)  # another network's layer
    torch.save(ckpt, run / "last.pt")
    line = _one_error_line(runner.invoke(glampoints_app, _resume_args(cfg, 4)))
    assert f"{run / 'last.pt'} does not fit this network" in line
