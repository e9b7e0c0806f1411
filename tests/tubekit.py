"""Test geometry shared by the tube tests (test_tube_patches, test_section_quadrics)."""

from __future__ import annotations

import numpy as np


def open_tube_faces(n_theta: int, n_z: int) -> np.ndarray:
    """(F, 3) triangles of an open tube whose vertices are an (n_theta, n_z) grid, row-major (around
    it, then along it), closed around and open at both ends; outward-facing for a counter-clockwise
    theta and z pointing along the tube."""
    idx = np.arange(n_theta * n_z).reshape(n_theta, n_z)
    a, b = idx[:, :-1], idx[:, 1:]
    c, d = np.roll(a, -1, axis=0), np.roll(b, -1, axis=0)
    return np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
