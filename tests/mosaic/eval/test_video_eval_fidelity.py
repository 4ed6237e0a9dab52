"""`mosaic evaluate` scores the mosaic against the source photograph (issue 16): columns,
the oracle computed once per video, a missing source, `--no-fidelity`."""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from mosaic.cli import app as mosaic_app
from mosaic.config import Config
from mosaic.eval.fidelity import mean_mosaic_fidelity
from mosaic.eval.video_eval import fidelity_reference, run_video_evaluation, source_path
from mosaic.io import sample_image_path
from mosaic.runner import reread_frames
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from mosaic.synthetic.truth import gt_path_for

runner = CliRunner()
COLUMNS = ("fidelity", "good_area", "oracle_fidelity", "oracle_good_area")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """Eight clean 240x160 frames with exact ground truth, as a folder of PNGs."""
    root = tmp_path_factory.mktemp("fidelity_videos")
    params = SynthParams(n_frames=8, size=(240, 160), seed=5, nuisances=False, max_step_px=6.0)
    write_synthetic_video(sample_image_path(), root / "clip", params)
    return root / "clip"


def _copy_with_source(clip, folder, source: str | None):
    """A copy of the clip whose ground truth names `source` alone (None: the key removed)."""
    folder.mkdir()
    video = folder / "clip"
    shutil.copytree(clip, video)
    gt = json.loads(gt_path_for(clip).read_text())
    del gt["source_absolute"]
    if source is None:
        del gt["source"]
    else:
        gt["source"] = source
    gt_path_for(video).write_text(json.dumps(gt))
    return video


def test_evaluate_reports_fidelity_next_to_the_oracle(clip, tmp_path, caplog):
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="mosaic.eval.video_eval"):
        results, _ = run_video_evaluation([clip], Config(), ["sift"], out)
    assert [r.detector for r in results] == ["sift/keyframes", "sift/chain"]
    oracles = [m for m in caplog.messages if m.startswith("oracle of")]
    assert len(oracles) == 1  # once per video, shared by both strategies
    keyframes = results[0]
    assert 0.6 < keyframes.oracle_fidelity <= 1.0 and 0.5 < keyframes.oracle_good_area <= 1.0
    assert results[1].oracle_fidelity == keyframes.oracle_fidelity
    # A clean video registers to well under a pixel: the mosaic is as good as the oracle.
    assert keyframes.fidelity > keyframes.oracle_fidelity - 0.05
    assert 0.5 < keyframes.good_area <= 1.0

    # The same frames, each placed 4 px off its true place (sigma), score clearly lower.
    reference = fidelity_reference(clip, Config())
    assert reference is not None and reference.oracle.fidelity == keyframes.oracle_fidelity
    rng = np.random.default_rng(2)
    G0_inv = np.linalg.inv(reference.truth[0])
    misposed = {}
    for i, G in enumerate(reference.truth):
        dx, dy = rng.normal(0.0, 4.0, 2)
        misposed[i] = G0_inv @ G @ np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1.0]])
    frames = reread_frames(clip, 1, 0)()
    bad = mean_mosaic_fidelity(frames, misposed, reference.truth, reference.source)
    assert bad.fidelity < keyframes.oracle_fidelity - 0.15

    with (out / "videos.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert all(float(rows[0][c]) > 0 for c in COLUMNS)
    with (out / "video_summary.csv").open() as fh:
        mean = next(csv.DictReader(fh))
    assert all(float(mean[c]) > 0 for c in COLUMNS)
    document = json.loads((out / "video_evaluation.json").read_text())
    assert document["videos"][0]["oracle_fidelity"] == pytest.approx(keyframes.oracle_fidelity)
    assert document["summary"][0]["fidelity"] == pytest.approx(keyframes.fidelity)


def test_relative_source_is_found_beside_the_ground_truth(clip, tmp_path):
    video = _copy_with_source(clip, tmp_path / "rel", "photo.jpg")
    shutil.copy(sample_image_path(), tmp_path / "rel" / "photo.jpg")
    assert source_path(gt_path_for(video)) == tmp_path / "rel" / "photo.jpg"
    assert fidelity_reference(video, Config()) is not None


def test_missing_source_gives_nan_and_one_warning(clip, tmp_path, caplog):
    video = _copy_with_source(clip, tmp_path / "gone", "no/such/photo.jpg")
    with caplog.at_level(logging.WARNING, logger="mosaic.eval.video_eval"):
        results, _ = run_video_evaluation([video], Config(), ["sift"], tmp_path / "out")
    warnings = [m for m in caplog.messages if "no fidelity scores" in m]
    assert len(warnings) == 1 and "photo.jpg" in warnings[0]
    for r in results:
        assert r.has_ground_truth and r.accurate_fraction == 1.0  # the rest is scored
        assert all(math.isnan(getattr(r, c)) for c in COLUMNS)
    unnamed = _copy_with_source(clip, tmp_path / "unnamed", None)
    assert source_path(gt_path_for(unnamed)) is None
    assert fidelity_reference(unnamed, Config()) is None


def test_no_fidelity_option(clip, tmp_path):
    out = tmp_path / "out"
    args = ["evaluate", str(clip), "--detector", "sift", "--strategy", "keyframes"]
    result = runner.invoke(mosaic_app, [*args, "--no-fidelity", "--out", str(out)])
    assert result.exit_code == 0, result.output
    document = json.loads((out / "video_evaluation.json").read_text())
    assert all(document["videos"][0][c] is None for c in COLUMNS)  # nan in JSON
    assert document["meta"]["fidelity"] is False
    assert "oracle fid" in result.output  # the column is there, empty
