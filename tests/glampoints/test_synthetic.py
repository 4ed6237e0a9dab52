"""Synthetic pairs: homography ranges, landmark correspondence, augmentation, determinism."""

from __future__ import annotations

import cv2
import numpy as np

from glampoints.metrics import failure_reason, warp_points
from glampoints.synthetic import (
    HomographyRanges,
    augment,
    fixed_pairs,
    green_clahe,
    make_pair,
    random_homography,
)
from tests.glampoints.conftest import vessel_image


def test_homography_ranges_defaults_are_the_papers():
    r = HomographyRanges()
    assert r.scale == (0.7, 1.3)
    assert r.perspective == (1e-6, 8e-4)
    assert r.max_translation_px == 100
    assert r.shear == 0.2
    assert r.max_rotation_deg == 25


def test_random_homography_is_centred_and_bounded():
    shape = (400, 600)
    c = np.array([[299.5, 199.5]])
    for seed in range(200):
        g = random_homography(np.random.default_rng(seed), shape)
        assert failure_reason(g, 100) is None  # never a flip or an extreme scale
        # about the centre, perspective/scale/shear/rotation leave it fixed: only translation
        shift = warp_points(g, c)[0] - c[0]
        assert np.all(np.abs(shift) <= 100.0 + 1e-3)
        # local scale at the centre (numerical Jacobian): scale 0.7-1.3 times shear 0.8-1.2
        dx, dy = np.array([0.5, 0.0]), np.array([0.0, 0.5])
        J = np.stack(
            [
                (warp_points(g, c + dx) - warp_points(g, c - dx))[0],
                (warp_points(g, c + dy) - warp_points(g, c - dy))[0],
            ],
            axis=1,
        )
        s = np.linalg.svd(J, compute_uv=False)
        assert s[-1] > 0.7 * 0.8 - 1e-3 and s[0] < 1.3 * 1.2 + 1e-3


def test_zero_ranges_give_identity():
    r = HomographyRanges(
        scale=(1, 1), perspective=(0, 0), max_translation_px=0, shear=0, max_rotation_deg=0
    )
    g = random_homography(np.random.default_rng(0), (100, 100), r)
    np.testing.assert_allclose(g, np.eye(3), atol=1e-12)


def _blob_centre(img: np.ndarray) -> np.ndarray | None:
    """Intensity-weighted centroid of the bright blob around the maximum, or None."""
    y, x = np.unravel_index(np.argmax(img), img.shape)
    if img[y, x] < 200 or not (8 <= x < img.shape[1] - 8 and 8 <= y < img.shape[0] - 8):
        return None
    win = img[y - 8 : y + 9, x - 8 : x + 9].astype(np.float64)
    win = np.maximum(win - 20.0, 0.0)
    gy, gx = np.mgrid[-8:9, -8:9]
    return np.array([x + (gx * win).sum() / win.sum(), y + (gy * win).sum() / win.sum()])


def test_make_pair_maps_a_landmark_onto_itself():
    base = np.full((420, 460), 20, np.uint8)
    cv2.circle(base, (231, 207), 4, 255, -1, lineType=cv2.LINE_AA)
    base = cv2.GaussianBlur(base, (0, 0), 1.5)
    checked = 0
    for seed in range(40):
        I1, I2, H = make_pair(base, np.random.default_rng(seed), crop=256)
        assert I1.shape == I2.shape == (256, 256) and I1.dtype == np.uint8
        p1, p2 = _blob_centre(I1), _blob_centre(I2)
        if p1 is None or p2 is None:
            continue
        err = np.linalg.norm(warp_points(H, p1[None])[0] - p2)
        assert err < 1.0, (seed, err)
        checked += 1
    assert checked >= 10


def test_make_pair_crops_overlap_substantially():
    base = vessel_image((480, 560), seed=1)
    grid = np.stack(np.meshgrid(np.arange(0, 256, 8), np.arange(0, 256, 8)), -1).reshape(-1, 2)
    fractions = []
    for seed in range(30):
        _, _, H = make_pair(base, np.random.default_rng(seed))
        q = warp_points(H, grid)
        inside = (q >= 0).all(1) & (q <= 255).all(1)
        fractions.append(inside.mean())
    assert np.mean(fractions) > 0.5
    assert np.min(fractions) > 0.2


def test_augment_subset_and_determinism():
    img = vessel_image((64, 80), seed=2)
    np.testing.assert_array_equal(augment(img, np.random.default_rng(0), p=0, p_inverse=0), img)
    np.testing.assert_array_equal(
        augment(img, np.random.default_rng(0), p=0, p_inverse=1), 255 - img
    )
    a = augment(img, np.random.default_rng(5), p=1)
    b = augment(img, np.random.default_rng(5), p=1)
    assert a.dtype == np.uint8 and a.shape == img.shape
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - img).mean() > 2


def test_fixed_pairs_are_deterministic():
    imgs = [vessel_image((300, 320), seed=s) for s in range(2)]
    p1 = fixed_pairs(imgs, seed=7, n_per_image=2, crop=64)
    p2 = fixed_pairs(imgs, seed=7, n_per_image=2, crop=64)
    p3 = fixed_pairs(imgs, seed=8, n_per_image=2, crop=64)
    assert len(p1) == 4
    for a, b in zip(p1, p2, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
    assert not np.array_equal(p1[0][2], p3[0][2])


def test_green_clahe_uses_the_green_channel():
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 255, size=(40, 50, 3), dtype=np.uint8)
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
    np.testing.assert_array_equal(green_clahe(bgr), clahe.apply(np.ascontiguousarray(bgr[..., 1])))
    np.testing.assert_array_equal(green_clahe(bgr[..., 0]), clahe.apply(bgr[..., 0].copy()))


def test_jpeg_augmentation_is_opt_in_and_leaves_8x8_blocks():
    rng_image = np.random.default_rng(4)
    image = cv2.GaussianBlur(rng_image.integers(0, 256, (128, 128), dtype=np.uint8), (0, 0), 2)
    # off (the default): nothing extra is drawn, the other changes are exactly as before
    np.testing.assert_array_equal(
        augment(image, np.random.default_rng(9)), augment(image, np.random.default_rng(9), p_jpeg=0)
    )
    plain = augment(image, np.random.default_rng(9), p=0.0, p_inverse=0.0)
    jpeg = augment(image, np.random.default_rng(9), p=0.0, p_inverse=0.0, p_jpeg=1.0)
    assert not np.array_equal(plain, jpeg)

    def step_at_block_edges(x):  # mean |horizontal step| across 8-px block edges vs inside
        d = np.abs(np.diff(x.astype(np.float32), axis=1))
        return d[:, 7::8].mean() / d.mean()

    assert step_at_block_edges(jpeg) > step_at_block_edges(plain) + 0.1
