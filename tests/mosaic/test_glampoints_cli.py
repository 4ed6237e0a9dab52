"""The `glampoints` command line, driven through typer's CliRunner: export never writes over
the shipped weights, bench runs in the app's precision (issue 40)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch
from typer.testing import CliRunner

import glampoints.detector
from glampoints.detector import DEFAULT_WEIGHTS, GlamPoints, load_weights
from mosaic.glampoints_cli import app

runner = CliRunner()


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_export_needs_an_output_and_never_writes_over_the_shipped_weights(tmp_path):
    """Without -o: a usage error (before, the shipped weights were the default output); an
    output that is the shipped weights, however spelt or linked: one line, exit 2. The
    checkpoint is missing on purpose: a refusal that did not hold could not write either."""
    shipped = _digest(DEFAULT_WEIGHTS)
    missing = str(tmp_path / "missing.pt")
    result = runner.invoke(app, ["export", missing])
    assert result.exit_code == 2 and "Missing option '-o' / '--output'" in result.output
    (tmp_path / "link.pt").symlink_to(DEFAULT_WEIGHTS)
    spelt = DEFAULT_WEIGHTS.parent / ".." / DEFAULT_WEIGHTS.parent.name / DEFAULT_WEIGHTS.name
    for output in (DEFAULT_WEIGHTS, spelt, tmp_path / "link.pt"):
        result = runner.invoke(app, ["export", missing, "-o", str(output)])
        assert result.exit_code == 2, result.output
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), result.output
        assert "is the weights shipped in the package" in lines[0]
    assert _digest(DEFAULT_WEIGHTS) == shipped


def test_export_writes_the_weights_of_a_checkpoint(tmp_path):
    state, _ = load_weights(DEFAULT_WEIGHTS)
    checkpoint = tmp_path / "best.pt"
    torch.save({"model": state, "config": {}}, checkpoint)
    out = tmp_path / "exported.pt"
    result = runner.invoke(app, ["export", str(checkpoint), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == str(out)
    assert GlamPoints.from_pretrained(out) is not None


def test_bench_runs_in_the_precision_the_app_would_and_says_which():
    """The default is the app's `auto` (bfloat16 where the CPU has it in hardware), resolved
    as the app does and printed; a named precision runs as named."""
    auto = "bfloat16" if glampoints.detector.cpu_has_native_bfloat16() else "float32"
    size = ["--width", "64", "--height", "64", "--repeats", "1"]
    result = runner.invoke(app, ["bench", *size])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(f"64x64 {auto} (auto), "), result.stdout
    result = runner.invoke(app, ["bench", *size, "--precision", "float32"])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("64x64 float32, "), result.stdout
    result = runner.invoke(app, ["bench", *size, "--precision", "half"])
    assert result.exit_code == 2 and result.output.startswith("error: precision must be one of")
