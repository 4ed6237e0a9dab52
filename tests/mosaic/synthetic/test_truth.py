"""The ground-truth file of a synthetic video: its name beside the video, and reading it back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mosaic.errors import InputError
from mosaic.synthetic.truth import gt_path_for, load_ground_truth


def test_ground_truth_file_is_named_after_the_video(tmp_path):
    assert gt_path_for(tmp_path / "clip.mp4") == tmp_path / "clip.gt.json"
    assert gt_path_for(tmp_path / "clip.AVI") == tmp_path / "clip.gt.json"
    assert gt_path_for(tmp_path / "frames") == tmp_path / "frames.gt.json"  # a frame folder
    assert gt_path_for(tmp_path / "frames.v1") == tmp_path / "frames.v1.gt.json"


def test_malformed_or_missing_ground_truth(tmp_path):
    bad = tmp_path / "bad.gt.json"
    bad.write_text(json.dumps({"frames": [{"index": 1, "H_frame_to_source": np.eye(3).tolist()}]}))
    with pytest.raises(InputError, match="malformed"):
        load_ground_truth(bad)
    bad.write_text("{not json")
    with pytest.raises(InputError, match="malformed"):
        load_ground_truth(bad)
    with pytest.raises(InputError, match="not found"):
        load_ground_truth(tmp_path / "absent.gt.json")
