"""What pair and video evaluation share: detector names, the extractors built for them."""

from __future__ import annotations

import pytest

from mosaic.config import Config, with_overrides
from mosaic.errors import ConfigError
from mosaic.eval.common import make_extractors, parse_detectors


def test_parse_detectors():
    assert parse_detectors(None)[:3] == ["glampoints", "sift", "orb"]
    assert parse_detectors(" sift, orb,sift ") == ["sift", "orb"]
    with pytest.raises(ConfigError, match="unknown detector surf"):
        parse_detectors("sift,surf")


def test_glampoints_without_weights_is_skipped(tmp_path, caplog):
    config = with_overrides(Config(), features={"weights": str(tmp_path / "missing.pt")})
    built = make_extractors(config, ["glampoints", "sift"])
    assert list(built) == ["sift"]
    assert "skipping detector glampoints" in caplog.text
    with pytest.raises(ConfigError, match="none of the detectors"):
        make_extractors(config, ["glampoints"])
