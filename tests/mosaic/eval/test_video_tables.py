"""Video evaluation's results: the paired comparison of methods and of runs, the tables,
CSV / JSON files, and the precision warning."""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from mosaic.cli import app as mosaic_app
from mosaic.errors import InputError
from mosaic.eval.video_tables import (
    VideoResult,
    compare_methods,
    format_video_tables,
    load_video_results,
    summarize_videos,
    warn_of_precisions,
    write_video_outputs,
)


def _video_result(detector: str, **values) -> VideoResult:
    base = dict.fromkeys(
        ("registered_fraction", "accurate_fraction", "mean_error_px", "median_error_px"), 1.0
    )
    base.update(max_error_px=1.0, drift_px_per_frame=0.0, mean_inliers=50.0, fps=10.0)
    counts = dict(frames=10, registered=10, failed=0, skipped=0, frames_until_failure=10)
    return VideoResult(
        detector=detector,
        video=f"/videos/{detector.replace('/', '_')}.mp4",
        has_ground_truth=True,
        frames_until_failure_pipeline=10,
        **counts,
        **{**base, **values},
    )


def test_methods_are_compared_paired_over_the_same_videos(tmp_path):
    """12 videos that differ widely (accurate 0.2-1.0); sift is better on each by ~0.05, orb
    better on half and worse on half by 0.2. Pairing over videos puts sift's interval tight
    around its gain, orb's around 0."""
    rng = np.random.default_rng(3)
    base = rng.uniform(0.2, 0.8, 12)
    gain = 0.05 + rng.normal(0.0, 0.01, 12)
    results = []
    for i in range(12):
        video = f"/videos/v{i}.mp4"
        for method, accurate, error, until in (
            ("glampoints/keyframes", base[i], 5.0, 6),
            ("sift/keyframes", base[i] + gain[i], 4.0, 5),
            ("orb/keyframes", base[i] + (0.2 if i % 2 else -0.2), 5.0, 6),
        ):
            run = _video_result(method, accurate_fraction=accurate, mean_error_px=error)
            results.append(dataclasses.replace(run, video=video, frames_until_failure=until))
    results.append(_video_result("sift/keyframes"))  # a video the first method did not run
    sift, orb = compare_methods(results)
    assert sift["method"] == "sift/keyframes" and sift["against"] == "glampoints/keyframes"
    assert sift["videos"] == 12 and orb["videos"] == 12
    assert sift["accurate_fraction"] == pytest.approx(gain.mean())
    low, high = sift["accurate_fraction_low"], sift["accurate_fraction_high"]
    assert 0.04 < low < gain.mean() < high < 0.06  # the videos' own spread does not widen it
    assert sift["mean_error_px"] == pytest.approx(-1.0)
    assert sift["mean_error_px_low"] == pytest.approx(-1.0) == sift["mean_error_px_high"]
    assert sift["until_failure_share"] == pytest.approx(-0.1)
    assert orb["accurate_fraction"] == 0.0
    assert orb["accurate_fraction_low"] < -0.05 and orb["accurate_fraction_high"] > 0.05
    assert compare_methods(results) == compare_methods(results)  # seeded: the same each run

    text = format_video_tables(results, summarize_videos(results))
    assert "Paired over the same videos: mean difference [95 % bootstrap interval" in text
    line = next(x for x in text.splitlines() if x.startswith("sift/keyframes") and "[" in x)
    assert f"{gain.mean():+.3f} [{low:+.3f}, {high:+.3f}]" in line
    assert "-1.00 [-1.00, -1.00]" in line and "-0.000" not in text
    write_video_outputs(results, summarize_videos(results), tmp_path)
    with (tmp_path / "video_differences.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["method"] for r in rows] == ["sift/keyframes", "orb/keyframes"]
    assert float(rows[0]["accurate_fraction_low"]) == pytest.approx(low)
    document = json.loads((tmp_path / "video_evaluation.json").read_text())
    assert document["differences"][1]["method"] == "orb/keyframes"


def test_a_run_is_compared_with_an_earlier_one_video_by_video(tmp_path):
    """`--against`: the earlier run's results read back from its folder; each method paired
    with itself there over the videos both hold, matched by file name (the earlier run was
    started from another folder)."""
    before, after = [], []
    for i in range(6):
        run = _video_result("sift/keyframes", accurate_fraction=0.5 + 0.05 * i)
        before.append(dataclasses.replace(run, video=f"old/place/v{i}.mp4", quality_rho=math.nan))
        if i < 5:  # the last video is not in the new run
            better = dataclasses.replace(run, accurate_fraction=run.accurate_fraction + 0.1)
            after.append(dataclasses.replace(better, video=f"v{i}.mp4"))
    write_video_outputs(before, summarize_videos(before), tmp_path / "before")
    previous = load_video_results(tmp_path / "before")
    assert [r.video for r in previous] == [r.video for r in before]
    assert math.isnan(previous[0].quality_rho)  # JSON's null back to nan
    [row] = compare_methods(after, previous)
    assert row["against"] == "sift/keyframes (previous run)" and row["videos"] == 5
    assert row["accurate_fraction"] == pytest.approx(0.1)
    assert row["accurate_fraction_low"] == pytest.approx(0.1)
    text = format_video_tables(after, summarize_videos(after), previous)
    assert "sift/keyframes (previous run)" in text and "+0.100 [+0.100, +0.100]" in text

    with pytest.raises(InputError, match="not the output of `mosaic evaluate`"):
        load_video_results(tmp_path / "nothing here")
    bad = tmp_path / "bad.json"
    bad.write_text('{"videos": [{"detector": "x"}]}')
    with pytest.raises(InputError, match=r"bad\.json"):
        load_video_results(bad)
    result = CliRunner().invoke(
        mosaic_app, ["evaluate", str(tmp_path), "--against", str(tmp_path / "nothing here")]
    )
    assert result.exit_code == 2 and "not the output of `mosaic evaluate`" in result.output


def test_one_method_has_nothing_to_compare(tmp_path):
    results = [_video_result("sift/chain")]
    assert compare_methods(results) == []
    assert "paired" not in format_video_tables(results, summarize_videos(results))
    write_video_outputs(results, summarize_videos(results), tmp_path)
    assert not (tmp_path / "video_differences.csv").exists()
    assert json.loads((tmp_path / "video_evaluation.json").read_text())["differences"] == []


def test_video_tables_and_files_carry_step_errors_and_models(tmp_path):
    results = [
        _video_result(
            "sift/chain",
            step_median_px=1.0,
            step_p90_px=3.0,
            model_counts={"similarity": 8, "affine": 1, "homography": 0},
            quality_rho=-0.8,
            bad_frames=4.0,
            bad_caught=0.5,
            good_flagged=0.1,
        ),
        _video_result(
            "sift/chain",
            step_median_px=2.0,
            step_p90_px=5.0,
            model_counts={"similarity": 6, "homography": 3},
            quality_rho=-0.6,
            bad_frames=0.0,  # nothing to catch: bad_caught stays nan
            good_flagged=0.0,
        ),
        _video_result("orb/chain"),  # an older report: no references to score, no models
    ]
    summary = summarize_videos(results)
    sift, orb = summary
    assert sift["step_median_px"] == 1.5 and sift["step_p90_px"] == 4.0
    assert sift["model_similarity"] == 7.0 and sift["model_affine"] == 0.5
    assert sift["model_homography"] == 1.5 and sift["model_translation"] == 0.0
    assert math.isnan(orb["step_median_px"]) and orb["model_similarity"] == 0.0
    assert sift["quality_rho"] == pytest.approx(-0.7) and sift["bad_frames"] == 2.0
    assert sift["bad_caught"] == 0.5 and sift["good_flagged"] == pytest.approx(0.05)
    assert math.isnan(orb["quality_rho"]) and math.isnan(orb["bad_caught"])

    text = format_video_tables(results, summary)
    assert "step med px" in text and "step p90 px" in text
    assert "sim 8 / aff 1" in text and "sim 6 / hom 3" in text
    assert "sim 7.0 / aff 0.5 / hom 1.5" in text  # the mean over videos
    assert "quality rho" in text and "bad caught" in text and "good flagged" in text
    assert "-0.70" in text and "0.05" in text

    write_video_outputs(results, summary, tmp_path)
    with (tmp_path / "videos.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["step_p90_px"] for r in rows] == ["3", "5", ""]
    assert [r["model_similarity"] for r in rows] == ["8", "6", "0"]
    assert [r["model_translation"] for r in rows] == ["0", "0", "0"]
    assert [r["quality_rho"] for r in rows] == ["-0.8", "-0.6", ""]
    assert [r["bad_caught"] for r in rows] == ["0.5", "", ""]
    assert [r["good_flagged"] for r in rows] == ["0.1", "0", ""]
    assert "model_counts" not in rows[0] and "step_errors" not in rows[0]
    with (tmp_path / "video_summary.csv").open() as fh:
        assert next(csv.DictReader(fh))["model_homography"] == "1.5"
    document = json.loads((tmp_path / "video_evaluation.json").read_text())
    assert document["videos"][1]["model_counts"] == {"similarity": 6, "homography": 3}
    assert document["videos"][2]["model_counts"] == {}
    assert document["summary"][0]["step_median_px"] == 1.5
    assert document["summary"][0]["bad_caught"] == 0.5
    assert document["videos"][1]["bad_caught"] is None  # nan in JSON


def test_a_comparison_across_precisions_is_said(tmp_path, caplog):
    """GLAMpoints in float32 and in bfloat16 differ by tenths on single videos: a run compared
    with an earlier one in the other precision says so; the precision survives the JSON."""
    run = _video_result("glampoints/keyframes")
    before = [dataclasses.replace(run, precision="float32")]
    write_video_outputs(before, summarize_videos(before), tmp_path / "before")
    previous = load_video_results(tmp_path / "before")
    assert previous[0].precision == "float32"
    with caplog.at_level(logging.WARNING, logger="mosaic.eval.video_tables"):
        warn_of_precisions([dataclasses.replace(run, precision="float32")], previous)
        assert not caplog.records
        warn_of_precisions([dataclasses.replace(run, precision="bfloat16")], previous)
    assert "in bfloat16 here and in float32 in the earlier run" in caplog.text
