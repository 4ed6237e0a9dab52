import dataclasses
import math
import re
import typing
from pathlib import Path

import pytest

from mosaic.config import (
    RANGES,
    Config,
    config_from_dict,
    for_photographs,
    load_config,
    value_range,
    with_overrides,
)
from mosaic.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]


def test_sample_config_equals_defaults():
    assert load_config(REPO / "sample_config.toml") == Config()


def test_missing_keys_take_defaults(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[registration]\nreproj_threshold_px = 5\n")
    config = load_config(path)
    assert config.registration.reproj_threshold_px == 5.0
    assert config.features == Config().features


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("[registration]\nreproj_treshold_px = 3.0\n", "reproj_treshold_px"),
        ("[registraton]\nmethod = 'ransac'\n", "registraton"),
        ("[compose]\nblend = 'poisson'\n", "blend"),
        ("[pipeline]\nstep = 0\n", "step"),
        ("[matching]\ncross_check = 1\n", "cross_check"),
        ("[features]\nmax_keypoints = 'many'\n", "max_keypoints"),
        ("[features]\ndetect_scale = 1.5\n", r"detect_scale must be in \[0.1, 1\], got 1.5"),
        ("[features]\ndetect_scale = 0\n", r"detect_scale must be in \[0.1, 1\]"),
        ("[features]\ndetect_scale = nan\n", r"detect_scale must be a finite number in \[0.1, 1\]"),
        ("[features]\ndescriptor_size_px = inf\n", "descriptor_size_px must be a finite num"),
        ("[registration]\nreproj_threshold_px = nan\n", "reproj_threshold_px must be a finite"),
        ("[registration]\nconfidence = 1.5\n", r"confidence must be in \(0, 1\), got 1.5"),
        ("[features]\nmax_keypoints = nan\n", r"max_keypoints must be an integer in \[1, 100000\]"),
        ("[features]\ndevice = 'gpu'\n", "device must be one of cpu, cuda"),
        ("[pipeline]\noverlap = 'yes'\n", "overlap must be one of auto, on, off, got 'yes'"),
        ("[pipeline]\noverlap = true\n", "overlap must be one of auto, on, off, got bool True"),
        ("[preprocess]\nmax_side_px = 10\n", r"max_side_px must be 0 \(off\) or in \[64, 32768\]"),
        ("[features]\nprecision = 'half'\n", "precision must be one of float32"),
        ("not toml [", "not valid TOML"),
        ("", "empty"),
    ],
)
def test_invalid_config_names_the_problem(tmp_path, text, fragment):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=fragment):
        load_config(path)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.toml")


def test_overrides_are_validated():
    config = with_overrides(Config(), pipeline={"on_failure": "stop"})
    assert config.pipeline.on_failure == "stop"
    with pytest.raises(ConfigError, match="on_failure"):
        with_overrides(Config(), pipeline={"on_failure": "ignore"})


def _numeric_keys():
    for table, cls in typing.get_type_hints(Config).items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if hints[f.name] in (int, float):
                yield table, f.name, hints[f.name]


@pytest.mark.parametrize(("table", "key", "kind"), list(_numeric_keys()))
def test_every_numeric_key_rejects_non_finite_negative_and_out_of_range_values(table, key, kind):
    """NaN, inf and negative values are errors that name the key and its range; 0 only where
    its range (or "0: off") holds it; the default always lies inside."""
    allowed = value_range(table, key)
    message = rf"\[{table}\] {key} must be .*{re.escape(str(allowed))}, got"
    for value in (math.nan, math.inf, -math.inf, -1, -0.5):
        with pytest.raises(ConfigError, match=message):
            config_from_dict({table: {key: value}})
    if 0 in allowed:
        assert getattr(getattr(config_from_dict({table: {key: 0}}), table), key) == 0
    else:
        with pytest.raises(ConfigError, match=message):
            config_from_dict({table: {key: 0}})
    assert getattr(getattr(Config(), table), key) in allowed
    if math.isfinite(allowed.high):
        with pytest.raises(ConfigError, match=message):
            config_from_dict({table: {key: allowed.high + 1}})


@pytest.mark.parametrize(("table", "key", "kind"), list(_numeric_keys()))
def test_every_numeric_key_has_its_own_bounded_range(table, key, kind):
    """No key falls back to the open default: each has a finite upper bound (issue 40: values
    past what OpenCV and numpy take were accepted and ended a run mid-way)."""
    assert (table, key) in RANGES
    assert math.isfinite(RANGES[table, key].high)


def test_range_text():
    assert str(value_range("registration", "confidence")) == "in (0, 1)"
    assert str(value_range("features", "extra_scale")) == "0 (off) or in [0.1, 1]"
    assert str(value_range("pipeline", "step")) == "in [1, 1000000]"
    assert str(value_range("registration", "perspective_prior")) == "0 (off) or in [0.0001, 1]"
    assert 1 not in value_range("registration", "confidence")
    assert math.nan not in value_range("compose", "feather_px")


@pytest.mark.parametrize("value", [1.0, 1.5, 0.0])
def test_ransac_confidence_is_a_probability_below_one(value):
    with pytest.raises(ConfigError, match=r"\[registration\] confidence"):
        config_from_dict({"registration": {"confidence": value}})
    assert config_from_dict({"registration": {"confidence": 0.99}}).registration.confidence == 0.99


def test_photographs_are_described_at_their_own_size():
    """Photograph pairs use `photo_descriptor_size_px` where video uses `descriptor_size_px`;
    nothing else changes."""
    config = with_overrides(Config(), features={"photo_descriptor_size_px": 5.0})
    photos = for_photographs(config)
    assert config.features.descriptor_size_px == 9.0
    assert photos.features.descriptor_size_px == 5.0
    assert dataclasses.replace(photos.features, descriptor_size_px=9.0) == config.features
    assert photos.registration == config.registration and photos.pipeline == config.pipeline
