"""Upright root-SIFT: normalisation, rows per point, agreement with OpenCV's SIFT, matching quality
on known-homography fundus pairs, rotation dependence."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from glampoints.descriptors import (
    _pyramid_level,
    rootsift,
    upright_rootsift,
    upright_rootsift_opencv,
)

REPO = Path(__file__).resolve().parents[2]
RETINA = REPO / "mosaic" / "data" / "retina.jpg"
LMC_VAL = REPO.parent / "shared" / "data" / "retina" / "val" / "lmc"


def test_rootsift_is_sqrt_of_l1_normalised():
    d = np.array([[1.0, 3.0, 0.0, 4.0], [0.0, 0.0, 0.0, 0.0], [2.0, 2.0, 2.0, 2.0]])
    r = rootsift(d)
    assert r.dtype == np.float32
    np.testing.assert_allclose(r[0], np.sqrt([0.125, 0.375, 0.0, 0.5]), rtol=1e-6)
    np.testing.assert_array_equal(r[1], 0.0)  # zero rows stay zero
    np.testing.assert_allclose(r[2], 0.5)
    np.testing.assert_allclose((r[[0, 2]] ** 2).sum(axis=1), 1.0, rtol=1e-6)


@pytest.mark.parametrize("describe", [upright_rootsift, upright_rootsift_opencv])
def test_one_row_per_point_in_input_order(texture, describe):
    xy = np.array([[50, 40], [120.5, 80.25], [20, 130], [150, 30]], dtype=np.float32)
    d = describe(texture, xy)
    assert d.shape == (4, 128) and d.dtype == np.float32
    np.testing.assert_allclose((d**2).sum(axis=1), 1.0, rtol=1e-5)
    d_rev = describe(texture, xy[::-1].copy())
    np.testing.assert_array_equal(d_rev, d[::-1])
    # duplicated and border points keep their rows too
    xy2 = np.array([[50, 40], [50, 40], [0, 0], [199, 159]], dtype=np.float32)
    d2 = describe(texture, xy2)
    assert d2.shape == (4, 128)
    np.testing.assert_array_equal(d2[0], d2[1])
    np.testing.assert_array_equal(d2[0], d[0])
    np.testing.assert_allclose((d2**2).sum(axis=1), 1.0, rtol=1e-5)  # corners: half a window


def test_points_outside_the_image_get_zero_rows_others_unit_rows(texture):
    h, w = texture.shape
    xy = np.array(
        [[-0.5, 50], [w - 0.5, 50], [60, -2], [60, h], [np.nan, 3], [0, 0], [w - 1, h - 1]],
        dtype=np.float32,
    )
    d = upright_rootsift(texture, xy, 10.0)
    np.testing.assert_array_equal(d[:5], 0.0)
    np.testing.assert_allclose((d[5:] ** 2).sum(axis=1), 1.0, rtol=1e-5)


def test_flat_support_gives_zero_rows_not_noise():
    img = np.full((120, 160), 90, np.uint8)
    img[:, 110:] = 200  # an edge far from the first point, next to the second
    d = upright_rootsift(img, np.array([[30, 60], [105, 60]], np.float32), 8.0)
    np.testing.assert_array_equal(d[0], 0.0)  # window (20 px) sees only flat grey
    assert abs(float((d[1] ** 2).sum()) - 1.0) < 1e-5
    # A vertical edge brighter on the right: gradients point along +x, SIFT orientation bin 0.
    assert d[1].reshape(16, 8).sum(axis=0).argmax() == 0


def test_empty_input_and_errors():
    img = np.zeros((20, 20), np.uint8)
    assert upright_rootsift(img, np.zeros((0, 2), np.float32)).shape == (0, 128)
    with pytest.raises(ValueError, match="size_px"):
        upright_rootsift(img, np.array([[5, 5]], np.float32), 0.0)
    with pytest.raises(ValueError, match="uint8"):
        upright_rootsift(img.astype(np.float32), np.array([[5, 5]], np.float32))


def test_descriptor_is_translation_invariant_but_not_rotation_invariant(texture):
    xy = np.array([[80, 70], [100, 90], [60, 100]], dtype=np.float32)
    d = upright_rootsift(texture, xy)

    def shifted(dx: int, dy: int) -> np.ndarray:
        img = np.zeros_like(texture)
        img[dy:, dx:] = texture[:-dy, :-dx]
        return upright_rootsift(img, xy + np.array([dx, dy], np.float32))

    # A shift by whole pyramid blocks (size 10 pools on 4 px blocks): the same descriptors.
    np.testing.assert_allclose(shifted(12, 8), d, atol=1e-6)
    # Any other shift moves the block grid under the points: nearly the same.
    assert ((shifted(11, 7) * d).sum(axis=1)).min() > 0.99
    # rotate the image by 90 degrees: the same physical points get different descriptors
    rot = np.ascontiguousarray(np.rot90(texture))  # (x, y) -> (y, W - 1 - x)
    w = texture.shape[1]
    xy_rot = np.stack([xy[:, 1], w - 1 - xy[:, 0]], axis=1).astype(np.float32)
    d_rot = upright_rootsift(rot, xy_rot)
    dist = np.linalg.norm(d_rot - d, axis=1)
    assert dist.min() > 0.3  # unit vectors: a rotation-invariant descriptor would give ~0


def test_per_point_sizes(texture):
    xy = np.array([[80, 70], [100, 90]], dtype=np.float32)
    small = upright_rootsift(texture, xy, 6.0)
    large = upright_rootsift(texture, xy, 20.0)
    mixed = upright_rootsift(texture, xy, np.array([6.0, 20.0], np.float32))
    np.testing.assert_array_equal(mixed[0], small[0])
    np.testing.assert_array_equal(mixed[1], large[1])
    assert np.linalg.norm(small[1] - large[1]) > 0.1  # the size sets the support region


def test_pyramid_level_keeps_cells_two_blocks_wide():
    sizes = np.array([1.0, 1.5, 2.0, 4.0, 10.0, 20.0, 1000.0])
    np.testing.assert_array_equal(_pyramid_level(1.5 * sizes), [0, 1, 1, 1, 2, 3, 5])


def _retina_crop() -> np.ndarray:
    src = cv2.imread(str(RETINA), cv2.IMREAD_GRAYSCALE)
    assert src is not None, RETINA
    return np.ascontiguousarray(src[500:850, 400:1060])  # 660x350, fundus content to the edges


@pytest.mark.parametrize("size", [2.0, 4.0, 10.0, 20.0])
def test_agrees_with_opencv_sift(size):
    """Same layout and semantics as OpenCV's upright SIFT + root-SIFT, at integer points (OpenCV
    rounds positions), inside the image and on its border."""
    img = _retina_crop()
    h, w = img.shape
    rng = np.random.default_rng(0)
    inner = rng.uniform([30, 30], [w - 30, h - 30], (150, 2))
    t = rng.uniform(0, 1, 40)
    border = np.concatenate(
        [np.stack([t * (w - 1), np.zeros(40)], 1), np.stack([np.full(40, w - 1), t * (h - 1)], 1)]
    )
    xy = np.round(np.concatenate([inner, border])).astype(np.float32)
    cos = (upright_rootsift(img, xy, size) * upright_rootsift_opencv(img, xy, size)).sum(axis=1)
    assert cos.mean() > (0.99 if size < 3 else 0.997)
    assert cos.min() > 0.97


def _homography_pair(
    src: np.ndarray, rng: np.random.Generator, out: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A crop of `src` and a view of it under rotation <= 10 deg, scale 0.9-1.1, translation
    <= 30 px (about the crop's centre), with gain and noise; returns (I1, I2, H_1_to_2)."""
    w, h = out
    cx, cy = rng.uniform(
        [w / 2 + 40, h / 2 + 40], [src.shape[1] - w / 2 - 40, src.shape[0] - h / 2 - 40]
    )
    crop = np.array([[1, 0, w / 2 - cx], [0, 1, h / 2 - cy], [0, 0, 1]], float)
    a, s = np.deg2rad(rng.uniform(-10, 10)), rng.uniform(0.9, 1.1)
    tx, ty = rng.uniform(-30, 30, 2)
    rot = np.array(
        [[s * np.cos(a), -s * np.sin(a), 0], [s * np.sin(a), s * np.cos(a), 0], [0, 0, 1]]
    )
    to_c = np.array([[1, 0, w / 2 + tx], [0, 1, h / 2 + ty], [0, 0, 1]], float)
    from_c = np.array([[1, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1]], float)
    H = to_c @ rot @ from_c
    I1 = cv2.warpPerspective(src, crop, out, flags=cv2.INTER_LINEAR)
    I2 = cv2.warpPerspective(src, H @ crop, out, flags=cv2.INTER_LINEAR)
    I2 = I2.astype(np.float32) * rng.uniform(0.85, 1.15) + rng.normal(0, 2, I2.shape)
    return I1, np.clip(I2, 0, 255).astype(np.uint8), H


def _sift_points(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    kps = cv2.SIFT_create(nfeatures=500, contrastThreshold=0.01).detect(img, None)
    xy = cv2.KeyPoint_convert(kps).astype(np.float32)
    sizes = np.minimum(np.array([k.size for k in kps], np.float32), 20.0)
    _, first = np.unique(np.round(xy, 2), axis=0, return_index=True)  # one per location
    return xy[first], sizes[first]


def _true_positives(describe, pairs, fixed_size: float | None) -> int:
    """Brute-force cross-checked matches within 3 px of the true position, over `pairs`."""
    total = 0
    matcher = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True)
    for I1, I2, H in pairs:
        (p1, s1), (p2, s2) = _sift_points(I1), _sift_points(I2)
        if fixed_size is not None:
            s1 = s2 = fixed_size
        matches = matcher.match(describe(I1, p1, s1), describe(I2, p2, s2))
        i = np.array([m.queryIdx for m in matches])
        j = np.array([m.trainIdx for m in matches])
        proj = cv2.perspectiveTransform(p1[i][None].astype(np.float64), H)[0]
        total += int((np.linalg.norm(proj - p2[j], axis=1) <= 3.0).sum())
    return total


def _pairs(paths_and_counts, out) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(1)
    pairs = []
    for src, n in paths_and_counts:
        pairs += [_homography_pair(src, rng, out) for _ in range(n)]
    return pairs


@pytest.mark.parametrize("fixed_size", [10.0, None], ids=["size10", "sift-sizes"])
def test_matches_as_well_as_opencv_on_fundus_pairs(fixed_size):
    """Known-homography pairs from the shipped fundus image (660x350): at least as many true
    positives as OpenCV's SIFT descriptor, within 2% (measured: -0.4% to +0.1%)."""
    src = cv2.resize(
        cv2.imread(str(RETINA), cv2.IMREAD_GRAYSCALE),
        None,
        fx=0.6,
        fy=0.6,
        interpolation=cv2.INTER_AREA,
    )
    pairs = _pairs([(src, 4)], (660, 350))
    new = _true_positives(upright_rootsift, pairs, fixed_size)
    ref = _true_positives(upright_rootsift_opencv, pairs, fixed_size)
    assert ref > 800  # the pairs are matchable at all
    assert new >= 0.98 * ref, (new, ref)


def test_matches_as_well_as_opencv_on_lmc_images():
    paths = sorted(LMC_VAL.glob("*_a.jpg"))[:3]
    if not paths:
        pytest.skip(f"no real retina data under {LMC_VAL}")
    srcs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths]
    pairs = _pairs([(s, 1) for s in srcs], (400, 300))
    new = _true_positives(upright_rootsift, pairs, 10.0)
    ref = _true_positives(upright_rootsift_opencv, pairs, 10.0)
    assert ref > 100
    assert new >= 0.96 * ref, (new, ref)
