"""Shared fixtures: the shipped CC0 fundus image and known-homography pairs made from it."""

from __future__ import annotations

import zlib
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


# --- the machine the numbers come from ------------------------------------------------------
# GLAMpoints' score map differs in its last bits between CPUs (oneDNN picks other kernels and
# summation orders) and a lot between float32 and bfloat16; NMS, matching and RANSAC turn such
# differences into other keypoints, other inliers, other poses. A threshold on such a result is
# a claim about the method only if it holds across them. `--precision` forces the precision
# that `[features] precision = "auto"` resolves to; `--score-noise EPS` multiplies every score
# map by (1 + EPS * N(0, 1)) with a fixed seed, standing in for another CPU's arithmetic
# (`--score-noise 1e-4 --score-seed K`: a different machine per K). Tests marked
# `both_precisions` run once in each precision whatever the options say.

PRECISIONS = ("float32", "bfloat16")


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("retina-mosaic")
    group.addoption(
        "--precision",
        choices=("auto", *PRECISIONS),
        default="auto",
        help="what [features] precision = 'auto' resolves to (default: as on this CPU)",
    )
    group.addoption(
        "--score-noise",
        type=float,
        default=0.0,
        help="relative noise on GLAMpoints' score maps, standing in for another CPU",
    )
    group.addoption("--score-seed", type=int, default=0, help="the seed of --score-noise")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "both_precisions: a GLAMpoints figure, run once in float32 and in bfloat16"
    )


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if metafunc.definition.get_closest_marker("both_precisions"):
        metafunc.parametrize("_auto_precision", PRECISIONS, indirect=True)


@pytest.fixture(autouse=True)
def _auto_precision(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The precision "auto" resolves to in this test: the marker's parameter, else
    `--precision`, else this CPU's."""
    import glampoints.detector

    choice = getattr(request, "param", None) or request.config.getoption("--precision")
    if choice != "auto":
        monkeypatch.setattr(
            glampoints.detector, "cpu_has_native_bfloat16", lambda: choice == "bfloat16"
        )
    noise = request.config.getoption("--score-noise")
    if noise:
        original = glampoints.detector.GlamPoints.score_map
        seed = request.config.getoption("--score-seed")

        def noisy(self: glampoints.detector.GlamPoints, image: np.ndarray) -> np.ndarray:
            # a function of the image, as a CPU's arithmetic is: the same image twice, the
            # same map (tests that compare two paths over one image stay meaningful)
            s = original(self, image)
            rng = np.random.default_rng([seed, zlib.crc32(np.ascontiguousarray(image))])
            return s * (1 + noise * rng.standard_normal(s.shape, np.float32))

        monkeypatch.setattr(glampoints.detector.GlamPoints, "score_map", noisy)
    return choice
