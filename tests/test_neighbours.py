"""k-th neighbour distances on a cell grid against the kd-tree's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ribpull_core.methods.base import knn_sigma
from ribpull_core.neighbours import kth_neighbour_distance


@pytest.mark.parametrize("n, k", [(4000, 51), (300, 9), (20, 20)])
def test_kth_neighbour_distance_is_the_kd_trees(n, k):
    rng = np.random.default_rng(8)
    # a sheet with a dense blob and two far strays: some points ask the kd-tree (too few in the radius)
    pts = np.r_[np.c_[rng.random((n, 2)) * 50, 0.1 * rng.normal(size=n)], rng.normal(size=(n // 10, 3)) * 0.2,
                [[500.0, 0, 0], [0, -300.0, 40]]]
    want = cKDTree(pts).query(pts, k=[k], workers=-1)[0][:, 0]
    np.testing.assert_array_equal(kth_neighbour_distance(pts, k), want)


def test_knn_sigma_is_the_distance_to_the_kth_other_point():
    pts = np.arange(10, dtype=np.float64)[:, None] * np.array([[1.0, 0, 0]])
    np.testing.assert_array_equal(knn_sigma(pts, k=2), [2, 1, 1, 1, 1, 1, 1, 1, 1, 2])
    np.testing.assert_array_equal(knn_sigma(pts[:3], k=50), [2, 1, 2])  # k capped at n - 1
