"""The ground-truth file of a synthetic video: its name beside the video, reading it back, and
the source photograph it names."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mosaic.errors import InputError
from mosaic.io import sample_image_path
from mosaic.synthetic.synth import SynthParams, write_synthetic_video
from mosaic.synthetic.truth import gt_path_for, load_ground_truth, source_path


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


def test_a_set_moved_with_its_photographs_still_names_them(tmp_path, monkeypatch):
    """The ground truth records the source relative to its own folder: a set copied
    elsewhere together with its photographs, and read from any folder, finds them (the
    fidelity needs them); one copied without them finds them where they were (the absolute
    path beside); a truth that names it relative to where `synth` ran (files written
    before) is still read from there."""
    photos, videos = tmp_path / "a" / "photos", tmp_path / "a" / "videos"
    photos.mkdir(parents=True)
    videos.mkdir()
    shutil.copy(sample_image_path(), photos / "eye.jpg")
    monkeypatch.chdir(tmp_path / "a")  # synth run from here, with relative paths
    params = SynthParams(n_frames=2, size=(96, 64), seed=1)
    gt_file = write_synthetic_video(Path("photos/eye.jpg"), Path("videos/v.mp4"), params)
    assert json.loads((videos / "v.gt.json").read_text())["source"] == "../photos/eye.jpg"
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    monkeypatch.chdir(tmp_path)
    moved = tmp_path / "b" / "videos" / "v.gt.json"
    assert source_path(moved).resolve() == (tmp_path / "b" / "photos" / "eye.jpg").resolve()
    old = json.loads(moved.read_text())
    old["source"] = "photos/eye.jpg"  # relative to where synth ran (tmp_path / "b")
    del old["source_absolute"]  # not written then
    moved.write_text(json.dumps(old))
    monkeypatch.chdir(tmp_path / "b")
    assert source_path(moved) == Path("photos/eye.jpg") and gt_file.name == "v.gt.json"
    # the set moved without its photographs: the absolute path recorded beside finds them
    shutil.copytree(tmp_path / "a" / "videos", tmp_path / "c")
    assert source_path(tmp_path / "c" / "v.gt.json") == (photos / "eye.jpg").resolve()
