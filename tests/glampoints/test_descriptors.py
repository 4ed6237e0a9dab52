"""Upright root-SIFT: normalisation, one row per point in order, rotation dependence."""

from __future__ import annotations

import numpy as np

from glampoints.descriptors import rootsift, upright_rootsift


def test_rootsift_is_sqrt_of_l1_normalised():
    d = np.array([[1.0, 3.0, 0.0, 4.0], [0.0, 0.0, 0.0, 0.0], [2.0, 2.0, 2.0, 2.0]])
    r = rootsift(d)
    assert r.dtype == np.float32
    np.testing.assert_allclose(r[0], np.sqrt([0.125, 0.375, 0.0, 0.5]), rtol=1e-6)
    np.testing.assert_array_equal(r[1], 0.0)  # zero rows stay zero
    np.testing.assert_allclose(r[2], 0.5)
    np.testing.assert_allclose((r[[0, 2]] ** 2).sum(axis=1), 1.0, rtol=1e-6)


def test_one_row_per_point_in_input_order(texture):
    xy = np.array([[50, 40], [120.5, 80.25], [20, 130], [150, 30]], dtype=np.float32)
    d = upright_rootsift(texture, xy)
    assert d.shape == (4, 128) and d.dtype == np.float32
    np.testing.assert_allclose((d**2).sum(axis=1), 1.0, rtol=1e-5)
    d_rev = upright_rootsift(texture, xy[::-1].copy())
    np.testing.assert_array_equal(d_rev, d[::-1])
    # duplicated and border points keep their rows too
    xy2 = np.array([[50, 40], [50, 40], [0, 0], [199, 159]], dtype=np.float32)
    d2 = upright_rootsift(texture, xy2)
    assert d2.shape == (4, 128)
    np.testing.assert_array_equal(d2[0], d2[1])
    np.testing.assert_array_equal(d2[0], d[0])


def test_empty_input():
    img = np.zeros((20, 20), np.uint8)
    assert upright_rootsift(img, np.zeros((0, 2), np.float32)).shape == (0, 128)


def test_descriptor_is_translation_invariant_but_not_rotation_invariant(texture):
    xy = np.array([[80, 70], [100, 90], [60, 100]], dtype=np.float32)
    d = upright_rootsift(texture, xy)
    # integer shift of the image and the points: identical descriptors
    shifted = np.zeros_like(texture)
    shifted[7:, 11:] = texture[:-7, :-11]
    d_shift = upright_rootsift(shifted, xy + np.array([11, 7], np.float32))
    np.testing.assert_allclose(d_shift, d, atol=1e-6)
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
