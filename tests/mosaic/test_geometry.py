"""Points and transforms (`mosaic.geometry`) against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from mosaic.geometry import corner_error, relative_homographies


def test_corner_error_and_relative_homographies():
    T = np.array([[1, 0, 3.0], [0, 1, 4.0], [0, 0, 1]])
    assert corner_error(T, np.eye(3), (100, 50)) == pytest.approx(5.0)
    G = [np.diag([2.0, 2.0, 1.0]), np.diag([2.0, 2.0, 1.0]) @ T]
    rel = relative_homographies(G)
    np.testing.assert_allclose(rel[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rel[1], T, atol=1e-12)
