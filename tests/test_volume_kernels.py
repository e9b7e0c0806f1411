"""The compiled voxel-volume kernels against the numpy / scipy code they stand for."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from ribpull_core.volume_kernels import mark_offsets, within_l1


def test_mark_offsets_is_the_numpy_stencil_loop_with_clipping():
    rng = np.random.default_rng(5)
    shape = np.array([9, 7, 5], dtype=np.int64)
    cells = rng.integers(-1, 10, size=(40, 3)).astype(np.int64)  # some outside: clipped onto the faces
    offsets = np.array(list(np.ndindex(3, 3, 3)), dtype=np.int64) - 1
    want = np.zeros(shape, dtype=bool)
    for off in offsets:
        c = np.clip(cells + off, 0, shape - 1)
        want[c[:, 0], c[:, 1], c[:, 2]] = True
    got = mark_offsets(shape, cells, offsets)
    assert got.shape == tuple(shape) and got.dtype == bool
    np.testing.assert_array_equal(got, want)
    assert not mark_offsets(shape, np.zeros((0, 3), np.int64), offsets).any()


@pytest.mark.parametrize("shape, fill", [((20, 17, 13), 0.05), ((20, 17, 13), 0.4), ((1, 5, 3), 0.3), ((30, 24, 18), 0.002)])
def test_within_l1_is_the_repeated_cross_dilation(shape, fill):
    rng = np.random.default_rng(6)
    mask = rng.random(shape) < fill
    for radius in (1, 3, 8):
        np.testing.assert_array_equal(within_l1(mask, radius), ndimage.binary_dilation(mask, iterations=radius))
    assert not within_l1(np.zeros(shape, bool), 8).any()

