"""`mosaic compare --rerun save`: the recording holds the baseline, the follow-up warped onto it
and the change map as three layers of one 2D space, read back with rerun's own chunk reader
and checked against the pictures `compare` wrote and the planted changes' truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from mosaic.cli import app
from mosaic.compare import COVERED_LEVEL
from mosaic.viz import COMPARE_LAYERS, COMPARE_ORIGIN, compare_layers
from tests.conftest import SAMPLE_IMAGE
from tests.mosaic.test_compare import followup_photograph
from tests.mosaic.test_viz import read_rrd

pytest.importorskip("rerun.chunk")
runner = CliRunner()


def layer_image(entity: dict) -> np.ndarray:
    """The pixels of a static `rr.Image` read back: (height, width, channels) uint8."""
    static = entity["static"]
    fmt = static["Image:format"][0]
    data = np.asarray(static["Image:buffer"][0], np.uint8)
    return data.reshape(fmt["height"], fmt["width"], -1)


@pytest.fixture(scope="module")
def compared(tmp_path_factory) -> dict:
    """Two photographs of one eye (the follow-up turned, relit, with three planted changes)
    compared with `--rerun save`."""
    folder = tmp_path_factory.mktemp("viz_compare")
    source = cv2.imread(str(SAMPLE_IMAGE), cv2.IMREAD_COLOR)
    base, follow, _, changes = followup_photograph(source, 0)
    cv2.imwrite(str(folder / "base.png"), base)
    cv2.imwrite(str(folder / "follow.png"), follow)
    out, rrd = folder / "out", folder / "visits.rrd"
    args = ["compare", str(folder / "base.png"), str(folder / "follow.png"), "-o", str(out)]
    result = runner.invoke(app, [*args, "--rerun", "save", "--rerun-target", str(rrd)])
    assert result.exit_code == 0, result.output
    assert f"recording: {rrd}" in result.output
    return {
        "rec": read_rrd(rrd),
        "out": out,
        "base": base,
        "changes": changes,
        "json": json.loads((out / "compare.json").read_text()),
    }


@pytest.mark.slow  # ~10 s: the pair's registration
def test_three_layers_in_one_space(compared):
    rec, base = compared["rec"], compared["base"]
    layers = {name: layer_image(rec[f"{COMPARE_ORIGIN}/{name}"]) for name in COMPARE_LAYERS}
    h, w = base.shape[:2]
    assert {k: v.shape for k, v in layers.items()} == {
        "baseline": (h, w, 3),
        "followup": (h, w, 4),
        "change": (h, w, 4),
    }
    # lossless: the baseline as given, the follow-up as written to followup_warped.png
    assert np.array_equal(layers["baseline"], base[..., ::-1])
    warped = cv2.imread(str(compared["out"] / "followup_warped.png"), cv2.IMREAD_COLOR)
    follow = layers["followup"]
    assert np.array_equal(follow[..., :3], warped[..., ::-1])
    covered = follow[..., 3] > 0
    assert 0.5 < covered.mean() < 1.0  # the turned eye leaves part of the map uncovered
    # transparent where the warp left the map empty (black fill), so the baseline shows
    empty = warped.max(axis=2) == 0
    assert empty.mean() > 0.02 and not covered[empty].mean() > 0.01
    assert warped[~covered].mean() < COVERED_LEVEL < 5 * COVERED_LEVEL < warped[covered].mean()
    # drawn bottom to top
    orders = {n: rec[f"{COMPARE_ORIGIN}/{n}"]["static"]["Image:draw_order"][0] for n in layers}
    assert orders["baseline"] < orders["followup"] < orders["change"]


@pytest.mark.slow
def test_change_layer_and_boxes_mark_the_planted_changes(compared):
    rec, regions = compared["rec"], compared["json"]["regions"]
    alpha = layer_image(rec[f"{COMPARE_ORIGIN}/change"])[..., 3]
    boxes = rec[f"{COMPARE_ORIGIN}/change/regions"]["static"]
    mins = np.asarray(boxes["Boxes2D:centers"]) - np.asarray(boxes["Boxes2D:half_sizes"])
    assert len(mins) == len(regions) >= 1
    assert np.allclose(mins, [r["bbox"][:2] for r in regions], atol=1e-3)
    opaque = alpha == 255
    for change in compared["changes"]:  # each planted change shows in the layer
        x0, y0, x1, y1 = (round(v) for v in change.bbox)
        assert opaque[y0 : y1 + 1, x0 : x1 + 1].any(), change.kind
    assert opaque.mean() < 0.05  # and little else does (measured 0.023)
    assert "Comparison" in rec["run/report"]["static"]["TextDocument:text"][0]


def test_compare_layers_alpha():
    """The pure helper: follow-up transparent off its retina, change opaque from 2x threshold."""
    base = np.full((4, 5, 3), 100, np.uint8)
    warped = np.zeros_like(base)
    warped[:, 2:] = (10, 20, 30)
    covered = warped.any(axis=2)
    change = np.array([[0, 3, 6, 9, 12]] * 4, np.float32)
    layers = compare_layers(base, warped, covered, change, threshold=6.0)
    assert layers["followup"][0, :, 3].tolist() == [0, 0, 255, 255, 255]
    assert layers["followup"][0, 2, :3].tolist() == [30, 20, 10]  # BGR -> RGB
    assert layers["change"][0, :, 3].tolist() == [0, 0, 85, 170, 255]


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--manifest", "v.csv", "--rerun", "save"], "not with --manifest"),
        (["a.png", "b.png", "--rerun", "serve", "--rerun-target", "x.rrd"], "only used with"),
        (["a.png", "b.png", "--rerun", "nope"], "unknown --rerun mode"),
    ],
)
def test_bad_viewer_arguments_of_compare_are_one_line_errors(tmp_path, args, fragment):
    result = runner.invoke(app, ["compare", *args, "-o", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    assert fragment in result.output and "Traceback" not in result.output
