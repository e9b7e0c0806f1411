"""Spatial order and nearest neighbours: a Z-order (Morton) sort, and the distance from every
point of a cloud to its k-th nearest neighbour on a cell grid.

Kd-tree work on points in Z order shares the tree's paths and leaves in the cache: a tree built on
sorted points (`sdf.SurfaceDistance`), or queries in no spatial order asked along the curve and
put back (`pointcloud.distance_to_points`: 400k random free-space points of the sternum label map
against its 120k boundary points 0.79 -> 0.65 s in alternated runs, the sort included, the same distances).

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


@njit(inline="always")
def _spread_bits(x):  # pragma: no cover - compiled
    """The 10 low bits of x spaced two zero bits apart (bit b moves to bit 3b)."""
    x = x & 0x3FF
    x = (x | (x << 16)) & 0x30000FF
    x = (x | (x << 8)) & 0x300F00F
    x = (x | (x << 4)) & 0x30C30C3
    return (x | (x << 2)) & 0x9249249


@njit(parallel=True, cache=True)
def _morton_codes(p, lo, ext):  # pragma: no cover - compiled
    """(N,) int64 Z-order codes of (N, 3) float64 points: each axis cut into 1024 cells of ext / 1024
    from lo (3,), its cell index's bits interleaved. One pass instead of numpy's ~20 full-array
    temporaries (1.2M SDF samples ~0.3 s -> ~0.01 s), the same codes."""
    out = np.empty(p.shape[0], dtype=np.int64)
    for q in prange(p.shape[0]):
        code = np.int64(0)
        for a in range(3):
            c = np.int64((p[q, a] - lo[a]) / ext * 1023.999)
            code |= _spread_bits(min(max(c, 0), 1023)) << a
        out[q] = code
    return out


def morton_order(points: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N,) permutation sorting points along a Z-order curve (1024 cells per axis).

    Kd-tree builds and queries on spatially sorted points are several times faster (cache locality:
    0.8 s instead of 5.2 s for 1M x 1M surface samples here)."""
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0, dtype=np.int64)
    ext = max(float(np.ptp(p, axis=0).max()), 1e-300)
    # code x 2^32 + index: unique keys, so one plain sort gives the stable argsort's order (codes
    # have 30 bits; ~3x faster than argsort(kind="stable") on 1.2M codes)
    keys = (_morton_codes(p, p.min(axis=0), ext) << 32) | np.arange(len(p), dtype=np.int64)
    keys.sort()
    return keys & 0xFFFFFFFF


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
