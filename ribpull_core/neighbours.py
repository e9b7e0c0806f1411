"""The distance from every point of a cloud to its k-th nearest neighbour, on a cell grid.

Neural-Pull's local scale (`methods.base.knn_sigma`) is the distance to the 51st point; scipy's
cKDTree finds all 51 for each of a label map's 105k boundary points (~0.6-0.9 s). Here each point
lists the points within a radius that holds about k of them (`tube_patches.ball_indices` over a
`tube_patches.cell_grid`) and takes their k-th smallest distance, exact wherever at least k lie in
that radius; the few points that have fewer ask the kd-tree. Distances are computed as the kd-tree
computes them (squared coordinate differences summed over the axes in order, then the root), so
the values are its values bit for bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange
from scipy.spatial import cKDTree

from .tube_patches import _typical_radius, ball_indices, cell_grid

#: the search radius over the median k-th neighbour distance: most points find k within it
RADIUS_OVER_MEDIAN = 1.5


def kth_neighbour_distance(points: np.ndarray, k: int, tree: cKDTree | None = None) -> np.ndarray:
    """(N,) float64 distance from each of (N, 3) `points` to its k-th nearest point of them (the
    point itself is the first, at 0), in the points' units: what `tree.query(points, k=[k])`
    returns, bit for bit. tree: a kd-tree of `points` (made here when not given)."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    k = int(min(k, len(pts)))
    tree = tree if tree is not None else cKDTree(pts)
    radius = RADIUS_OVER_MEDIAN * _typical_radius(pts, tree, k)
    if not radius > 0:
        return tree.query(pts, k=[k], workers=-1)[0][:, 0]
    out = _kth_within(pts, *cell_grid(pts, 0.5 * radius), radius, k)
    short = np.flatnonzero(~np.isfinite(out))  # fewer than k within the radius: the kd-tree
    if len(short):
        out[short] = tree.query(pts[short], k=[k], workers=-1)[0][:, 0]
    return out


@njit(parallel=True, cache=True)
def _kth_within(points, lo, cell, dims, order, starts, radius, k):  # pragma: no cover - compiled
    """(N,) the k-th smallest distance from each point to the points within `radius` of it (their
    `cell_grid`: lo, cell, dims, order, starts); inf where fewer than k lie within it."""
    out = np.empty(points.shape[0])
    for i in prange(points.shape[0]):
        idx = ball_indices(points, lo, cell, dims, order, starts, points[i], radius)
        if idx.shape[0] < k:
            out[i] = np.inf
            continue
        d2 = np.empty(idx.shape[0])
        for t in range(idx.shape[0]):
            p = idx[t]
            e0 = points[i, 0] - points[p, 0]
            e1 = points[i, 1] - points[p, 1]
            e2 = points[i, 2] - points[p, 2]
            d2[t] = e0 * e0 + e1 * e1 + e2 * e2
        out[i] = np.sqrt(np.partition(d2, k - 1)[k - 1])
    return out
