"""`mosaic bench`: variants in one run, every frame accounted for, table and JSON output."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from mosaic.cli import app
from mosaic.config import Config, with_overrides
from mosaic.eval.bench import (
    format_build_table,
    format_table,
    profile_pipeline,
    run_bench,
    run_build_bench,
)


def test_bench_runs_every_variant_on_the_same_video():
    rows = run_bench(["sift"], size=(400, 280), n_frames=14, scales=[0.75, 0.5])
    names = [r.name for r in rows]
    assert names == [
        "sift",
        "sift (scale 0.75)",
        "sift (scale 0.5)",
        "sift (overlap)",
        "sift (no overlap)",
    ]
    for r in rows:
        assert r.frames == 14
        assert r.registered >= 13, r  # an easy synthetic video: (almost) everything registers
        assert r.fps > 0 and r.frame_ms[0] <= r.frame_ms[1]  # median <= p90
        assert r.stage_ms["detect"][0] > 0 and r.stage_ms["compose"][0] > 0
    # 14 frames are too few for the overlap trial (auto): undecided; the fixed variants as set
    assert [r.overlap for r in rows] == [None, None, None, True, False]
    table = format_table(rows).splitlines()
    assert table[0].split()[:3] == ["variant", "decode", "preprocess"]
    assert len(table) == 1 + len(rows)
    sift_line = table[1].split()
    assert sift_line[0] == "sift" and sift_line[-4] == "1.00"  # the reference's own ratio
    assert [line.split()[-1] for line in table[1:]] == ["-", "-", "-", "on", "off"]


def test_bench_cli_json_and_bad_scales():
    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "bench",
            "--size",
            "200x140",
            "--frames",
            "12",
            "--detector",
            "sift",
            "--scales",
            "0.5",
            "--no-rerun",
            "--no-build",
            "--json",
        ],
    )
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert [r["name"] for r in data["rows"]] == [
        "sift",
        "sift (scale 0.5)",
        "sift (overlap)",
        "sift (no overlap)",
    ]
    assert data["environment"]["cpu_count"] >= 1
    res = runner.invoke(app, ["bench", "--scales", "2", "--no-rerun"])
    assert res.exit_code == 2 and "--scales" in res.stderr and "Traceback" not in res.output


def test_profile_names_the_pipeline_stages():
    text = profile_pipeline("sift", size=(240, 180), n_frames=10, top=400)  # a busy machine
    assert "tottime" in text
    # the hot functions of a SIFT frame are there: detection, description, matching, motion
    for name in ("detect", "_cell_histograms", "match_descriptors", "estimate_motion"):
        assert name in text, text


def test_bench_measures_glampoints_in_the_other_precision_where_the_cpu_has_bfloat16(
    monkeypatch,
):
    import mosaic.eval.bench as bench

    monkeypatch.setattr(bench, "native_bfloat16", lambda: True)
    for default, other in (("auto", "float32"), ("float32", "bfloat16")):
        config = with_overrides(Config(), features={"precision": default})
        rows = run_bench(["glampoints"], size=(240, 160), n_frames=6, config=config)
        names = [r.name for r in rows]
        assert names == [
            "glampoints",
            f"glampoints ({other})",
            "glampoints (overlap)",
            "glampoints (no overlap)",
        ]
        assert all(r.frames == 6 and r.registered >= 5 for r in rows), rows
    monkeypatch.setattr(bench, "native_bfloat16", lambda: False)
    names = [r.name for r in run_bench(["glampoints"], (240, 160), 4)]
    assert names == ["glampoints", "glampoints (overlap)", "glampoints (no overlap)"]


def test_the_whole_build_is_timed_from_the_start_to_the_written_mosaic():
    """The whole-build row: a realistic video built as `mosaic build` builds it (re-render,
    mosaic and report written); its wall clock holds the streaming and the final passes, and
    the rates are the frames over each."""
    row = run_build_bench("sift", size=(400, 300), n_frames=16)
    assert row.frames == 16 and row.registered >= 8, row  # realistic: blur, rim, vignetting
    assert 0 < row.streaming_s < row.wall_s and row.final_s > 0, row
    assert abs(row.whole_fps * row.wall_s - 16) < 1e-6
    assert row.whole_fps < row.streaming_fps
    table = format_build_table([row]).splitlines()
    assert table[0].split()[:3] == ["whole", "build", "frames"] and len(table) == 2
    assert table[1].split()[-1] == f"{row.whole_fps / row.streaming_fps:.2f}"
    res = CliRunner().invoke(
        app,
        ["bench", "--size", "320x240", "--frames", "12", "--detector", "sift", "--scales", "",
         "--no-rerun", "--json"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    (build,) = json.loads(res.stdout)["builds"]
    assert build["name"] == "sift (mosaic build)" and build["frames"] == 12
    assert build["wall_s"] > build["streaming_s"] > 0
