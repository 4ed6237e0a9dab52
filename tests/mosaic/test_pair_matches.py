"""`mosaic register --matches`: the pair side by side with keypoints and inlier matches drawn
(`mosaic.viz.draw_pair_matches`, `pair_matches_picture`)."""

from __future__ import annotations

import json

import cv2
import numpy as np
from typer.testing import CliRunner

from mosaic.cli import app
from mosaic.viz import draw_pair_matches
from tests.helpers import crop_pair, similarity

INLIER_BGR = (80, 210, 40)  # the viewer's inlier green, BGR


def _is_green(pixel: np.ndarray) -> bool:
    return bool(np.abs(pixel.astype(int) - INLIER_BGR).max() <= 40)


def around(image: np.ndarray, x: int, y: int, r: int = 4) -> np.ndarray:
    """The pixels of the (2r + 1)^2 patch centred on (x, y), as rows of BGR."""
    return image[y - r : y + r + 1, x - r : x + r + 1].reshape(-1, 3).astype(int)


def test_draw_pair_matches_size_keypoints_and_inlier_lines():
    fixed = np.zeros((100, 200), np.uint8)
    moving = np.zeros((120, 150, 3), np.uint8)
    xy_fixed = np.array([[20.0, 20.0], [150.0, 80.0], [100.0, 88.0]])
    xy_moving = np.array([[30.0, 90.0], [120.0, 20.0], [60.0, 60.0]])
    # match 0: fixed 0 <-> moving 0 (inlier); match 1: fixed 1 <-> moving 1 (rejected)
    out = draw_pair_matches(fixed, moving, xy_fixed, xy_moving, [0, 1], [0, 1], [True, False])
    assert out.shape == (120, 350, 3) and out.dtype == np.uint8
    # the inlier line runs from (20, 20) to (200 + 30, 90): its midpoint is green
    assert _is_green(out[55, 125])
    # the rejected match has no line: its midpoint stays black; its keypoints are red circles
    assert out[50, 235].max() == 0
    red = around(out, 150, 80)
    assert ((red[:, 2] > 150) & (red[:, 1] < 120)).any()
    assert (around(out, 200 + 120, 20)[:, 2] > 150).any()
    # an unmatched keypoint is a grey circle, and nothing of the inlier colour is near it
    grey = around(out, 100, 88)
    assert ((grey.max(axis=1) - grey.min(axis=1) < 10) & (grey.min(axis=1) > 80)).any()
    assert not any(_is_green(px) for px in grey)
    # no match is an inlier: no line at all between the images
    out = draw_pair_matches(fixed, moving, xy_fixed, xy_moving, [0, 1], [0, 1], [False, False])
    assert not _is_green(out[55, 125])


def test_register_matches_writes_the_side_by_side_picture(fundus, tmp_path):
    H_b_to_a = similarity(-6.0, 0.95, -20.0, 10.0, center=(240, 160))
    a, b = crop_pair(fundus, H_b_to_a, origin=(500, 450), size=(480, 320))
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), b)
    out = tmp_path / "matches.png"
    args = ["register", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--detector", "sift"]
    result = CliRunner().invoke(app, [*args, "--json", "--matches", str(out)])
    assert result.exit_code == 0, result.output
    n_inliers = json.loads(result.stdout)["n_inliers"]
    picture = cv2.imread(str(out))
    assert picture.shape == (320, 960, 3)
    # inlier lines cross from one image into the other: green pixels in a band around the seam
    seam = picture[:, 470:490].reshape(-1, 3).astype(int)
    green = (np.abs(seam - INLIER_BGR).max(axis=1) <= 40).sum()
    assert n_inliers >= 20 and green >= 20
    # a missing output folder is a user error before any work
    result = CliRunner().invoke(app, [*args, "--matches", str(tmp_path / "no" / "m.png")])
    assert result.exit_code == 2 and "error:" in result.output
