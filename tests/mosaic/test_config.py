from pathlib import Path

import pytest

from mosaic.config import Config, load_config, with_overrides
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
        ("[features]\ndetect_scale = 1.5\n", "detect_scale must be <= 1"),
        ("[features]\ndetect_scale = 0\n", "detect_scale must be > 0"),
        ("[features]\ndevice = 'gpu'\n", "device must be one of cpu, cuda"),
        ("[pipeline]\noverlap = 'yes'\n", "overlap must be bool"),
        ("[preprocess]\nmax_side_px = 10\n", r"max_side_px must be 0 \(off\) or >= 64"),
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
