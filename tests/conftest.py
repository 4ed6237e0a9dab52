"""Shared fixtures: the shipped CC0 fundus image and known-homography pairs made from it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
SAMPLE_IMAGE = REPO / "mosaic" / "data" / "retina.jpg"


@pytest.fixture(scope="session")
def fundus() -> np.ndarray:
    """The shipped fundus photograph, BGR uint8 (1411x1411)."""
    image = cv2.imread(str(SAMPLE_IMAGE), cv2.IMREAD_COLOR)
    assert image is not None
    return image
