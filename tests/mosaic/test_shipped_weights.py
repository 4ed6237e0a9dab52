"""The shipped GLAMpoints weights against SIFT, with the same descriptor, matcher and RANSAC.

The paper's headline: GLAMpoints registers more pairs acceptably than SIFT (slit lamp 68 % vs
50 %, FIRE 94.8 % vs 61.2 %). Checked on synthetic pairs from the validation split (18 retinal
images of several modalities); skipped where the shared data is absent: the single shipped
sample image is too few pairs of one healthy eye to rank detectors. Measured with the shipped
weights and the photographs' 6 px descriptor (`photo_descriptor_size_px`) for GLAMpoints:
55.6 % vs SIFT's 55.0 % of these 180 pairs (at the video frames' 9 px 52.8 %, at the former
10 px 51.1 %: see the model card). So near each other, which one is ahead depends on the CPU
and precision; the test claims what a paired test on these pairs can tell: GLAMpoints is not
worse than SIFT beyond the pairs' noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from glampoints.detector import DEFAULT_WEIGHTS
from mosaic.config import Config
from mosaic.eval.datasets import load_synthetic
from mosaic.eval.pair_eval import run_pair_evaluation
from mosaic.features import FeatureExtractor
from mosaic.pairs import register_pair
from tests.conftest import SHARED_DATA
from tests.helpers import corner_error, crop_pair, similarity

pytestmark = pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason="no shipped weights")


VAL = SHARED_DATA / "retina" / "val" / "lmc"


def not_worse_beyond_noise(ours: np.ndarray, theirs: np.ndarray, z: float = 2.0) -> bool:
    """Whether paired successes `ours` are not below `theirs` by more than `z` standard errors
    of the paired difference (McNemar: only the pairs where the two disagree carry it)."""
    n = len(ours)
    discordant = int(np.sum(ours != theirs))
    difference = (int(ours.sum()) - int(theirs.sum())) / n
    return difference >= -z * max(np.sqrt(discordant), 1.0) / n


def test_the_paired_rule_tells_a_worse_detector_from_an_equal_one():
    """The rule above: equal rates pass; 20 points fewer of 180 fail; 3 points fewer, with 17
    pairs where the two disagree (either way), pass."""
    rng = np.random.default_rng(0)
    theirs = rng.random(180) < 0.55
    flipped = np.flatnonzero(theirs)
    assert not_worse_beyond_noise(theirs.copy(), theirs)
    worse = theirs.copy()
    worse[flipped[:36]] = False  # 20 points fewer
    assert not not_worse_beyond_noise(worse, theirs)
    slightly = theirs.copy()
    slightly[flipped[:10]] = False
    slightly[np.flatnonzero(~theirs)[:7]] = True
    assert not_worse_beyond_noise(slightly, theirs)


@pytest.mark.slow
@pytest.mark.both_precisions
@pytest.mark.skipif(not VAL.is_dir(), reason="validation split not available")
def test_glampoints_registers_as_many_pairs_as_sift_within_the_noise(tmp_path):
    # 10 pairs per image (180 pairs): fewer, and the noise covers any difference
    dataset = load_synthetic(VAL, seed=0, pairs_per_image=10)
    results, summary = run_pair_evaluation(
        dataset, Config(), ["glampoints", "sift"], tmp_path / "out"
    )
    ok = {
        name: np.array([r.status == "acceptable" for r in results if r.detector == name])
        for name in ("glampoints", "sift")
    }
    assert len(ok["glampoints"]) == len(ok["sift"]) >= 100
    assert not_worse_beyond_noise(ok["glampoints"], ok["sift"]), summary
    assert {r["detector"]: r["true_positives"] for r in summary}["glampoints"] > 0


@pytest.mark.both_precisions
def test_shipped_weights_register_a_known_pair_to_a_fraction_of_a_pixel(fundus):
    """The fast suite's check of the shipped weights themselves: a known similarity between
    two 400x300 views of the sample image (measured: 434 inliers, 0.07 px corner error with a
    homography, 0.46 px with the similarity auto chooses)."""
    H_true = similarity(6.0, 1.06, 18, -11, center=(200, 150))
    fixed, moving = crop_pair(fundus, H_true, (450, 500), (400, 300))
    config = Config()
    extractor = FeatureExtractor(config.features)
    assert extractor.detector.name == "glampoints" and config.features.weights == ""
    errors = {}
    for model in ("auto", "homography"):
        registration = register_pair(fixed, moving, config, extractor, model)
        assert registration.ok and registration.n_inliers >= 200, registration
        errors[model] = corner_error(registration.H_moving_to_fixed, H_true, (400, 300))
    assert errors["homography"] < 0.3 and errors["auto"] < 1.0, errors
