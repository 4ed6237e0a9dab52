"""Dataset loaders (FIRE, HPatches / Oxford, synthetic) against fixtures with known ground truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from glampoints.metrics import warp_points
from mosaic.errors import InputError
from mosaic.eval.datasets import detect_format, open_dataset
from tests.helpers import crop_pair, similarity

FIRE_SIZE = 320  # "full resolution" of the fixture (real FIRE: 2912)

# name -> H_2_to_1 (image 2 is warped from image 1's crop); None: image 2 shows no retina
FIRE_PAIRS: dict[str, np.ndarray | None] = {
    "S01": similarity(3.0, 1.0, 6.0, -4.0, center=(FIRE_SIZE / 2, FIRE_SIZE / 2)),
    "P01": similarity(-8.0, 1.06, -18.0, 12.0, center=(FIRE_SIZE / 2, FIRE_SIZE / 2)),
    "A01": None,
}


def make_fire_fixture(root: Path, fundus: np.ndarray, n_points: int = 10) -> dict[str, np.ndarray]:
    """A tiny dataset in FIRE's layout; returns each pair's control points (x1 y1 x2 y2)."""
    (root / "Images").mkdir(parents=True)
    (root / "Ground Truth").mkdir()
    rng = np.random.default_rng(7)
    truth = {}
    for name, H_2_to_1 in FIRE_PAIRS.items():
        if H_2_to_1 is None:
            a = fundus[450 : 450 + FIRE_SIZE, 450 : 450 + FIRE_SIZE]
            b = np.full_like(a, 90)  # featureless: registration must fail
            H_2_to_1 = np.eye(3)
        else:
            a, b = crop_pair(fundus, H_2_to_1, (450, 450), (FIRE_SIZE, FIRE_SIZE))
        xy1 = rng.uniform(40, FIRE_SIZE - 40, (n_points, 2))
        xy2 = warp_points(np.linalg.inv(H_2_to_1), xy1).astype(np.float64)
        points = np.hstack([xy1, xy2])
        cv2.imwrite(str(root / "Images" / f"{name}_1.jpg"), a, [cv2.IMWRITE_JPEG_QUALITY, 95])
        cv2.imwrite(str(root / "Images" / f"{name}_2.jpg"), b, [cv2.IMWRITE_JPEG_QUALITY, 95])
        np.savetxt(root / "Ground Truth" / f"control_points_{name}_1_2.txt", points, fmt="%.4f")
        truth[name] = points
    return truth


def test_fire_layout(tmp_path, fundus):
    truth = make_fire_fixture(tmp_path / "FIRE", fundus)
    assert detect_format(tmp_path / "FIRE") == "fire"
    dataset = open_dataset(tmp_path / "FIRE")
    assert dataset.format == "fire"
    assert len(dataset) == 3
    pairs = {p.name: p for p in dataset}
    assert {name: p.category for name, p in pairs.items()} == {"A01": "A", "P01": "P", "S01": "S"}
    for name, pair in pairs.items():
        assert pair.H_1_to_2 is None
        np.testing.assert_allclose(pair.control_points, truth[name], atol=1e-4)
        assert pair.image1.shape == pair.image2.shape == (FIRE_SIZE, FIRE_SIZE, 3)


def test_fire_errors_name_the_problem(tmp_path, fundus):
    make_fire_fixture(tmp_path / "FIRE", fundus)
    (tmp_path / "FIRE" / "Images" / "P01_1.jpg").unlink()
    with pytest.raises(InputError, match="P01"):
        open_dataset(tmp_path / "FIRE", "fire")
    (tmp_path / "empty" / "Images").mkdir(parents=True)
    (tmp_path / "empty" / "Ground Truth").mkdir()
    with pytest.raises(InputError, match="control_points"):
        open_dataset(tmp_path / "empty", "fire")
    with pytest.raises(InputError, match="not found"):
        open_dataset(tmp_path / "missing")
    with pytest.raises(InputError, match="unknown dataset format"):
        open_dataset(tmp_path / "FIRE", "kitti")


def _write_sequence(folder: Path, image: np.ndarray, oxford: bool) -> np.ndarray:
    """Images 1 and 2 of a sequence, image 2 = image 1 under a known H_1_to_2 (returned)."""
    folder.mkdir(parents=True)
    H = np.array([[1.02, 0.05, 3.0], [-0.04, 0.99, -2.0], [1e-5, 2e-5, 1.0]])
    h, w = image.shape[:2]
    warped = cv2.warpPerspective(image, H, (w, h))
    stem, suffix = ("img", ".ppm") if oxford else ("", ".png")
    cv2.imwrite(str(folder / f"{stem}1{suffix}"), image)
    cv2.imwrite(str(folder / f"{stem}2{suffix}"), warped)
    name = "H1to2p" if oxford else "H_1_2"
    np.savetxt(folder / name, 2.0 * H)  # a scaled matrix is the same homography
    return H


def test_hpatches_and_oxford_layouts(tmp_path, fundus):
    small = cv2.resize(fundus[400:700, 400:700], (120, 100))
    H_v = _write_sequence(tmp_path / "hp" / "v_retina", small, oxford=False)
    H_graf = _write_sequence(tmp_path / "hp" / "graf", small, oxford=True)
    (tmp_path / "hp" / "graf" / "README.txt").write_text("not an image")
    assert detect_format(tmp_path / "hp") == "hpatches"
    pairs = {p.name: p for p in open_dataset(tmp_path / "hp")}
    assert sorted(pairs) == ["graf/img1-img2", "v_retina/1-2"]
    np.testing.assert_allclose(pairs["v_retina/1-2"].H_1_to_2, H_v, atol=1e-12)
    np.testing.assert_allclose(pairs["graf/img1-img2"].H_1_to_2, H_graf, atol=1e-12)
    assert pairs["v_retina/1-2"].category == "v"
    assert pairs["graf/img1-img2"].category == "graf"
    # a single sequence folder is a dataset too
    assert [p.name for p in open_dataset(tmp_path / "hp" / "graf", "hpatches")] == [
        "graf/img1-img2"
    ]
    (tmp_path / "hp" / "v_retina" / "H_1_2").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(InputError, match="3x3"):
        list(open_dataset(tmp_path / "hp", "hpatches"))


def test_synthetic_pairs_are_reproducible(tmp_path, fundus):
    folder = tmp_path / "bases"
    folder.mkdir()
    for i, y in enumerate((300, 600)):
        cv2.imwrite(str(folder / f"b{i}.png"), fundus[y : y + 300, 400:700])
    assert detect_format(folder) == "synthetic"
    first = list(open_dataset(folder, "synthetic", seed=3, pairs_per_image=2))
    again = list(open_dataset(folder, seed=3, pairs_per_image=2))
    other = list(open_dataset(folder, seed=4, pairs_per_image=2))
    assert [p.name for p in first] == ["b0#0", "b0#1", "b1#0", "b1#1"]
    for a, b, c in zip(first, again, other, strict=True):
        np.testing.assert_array_equal(a.H_1_to_2, b.H_1_to_2)
        np.testing.assert_array_equal(a.image2, b.image2)
        assert not np.allclose(a.H_1_to_2, c.H_1_to_2)
        assert a.image1.shape == (256, 256, 3)
        assert np.isclose(a.H_1_to_2[2, 2], 1.0)
    with pytest.raises(InputError, match="no images"):
        open_dataset(tmp_path, "synthetic")
