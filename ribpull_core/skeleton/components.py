"""Input checks and the split of a ribcage point cloud into connected clusters (one per rib).

Ribs are separate bones a few mm apart; contracting them one by one guarantees that the Laplacian
never links two ribs, and it is faster (many small solves instead of one big one).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ribpull_core.errors import RibPullInputError


def validate_points(points_mm: np.ndarray, min_points: int = 50) -> np.ndarray:
    """Check a point array and return it as contiguous (N, 3) float64 mm.

    Raises RibPullInputError with code ``bad_parameter`` (wrong shape), ``non_finite`` (NaN/inf),
    ``too_few_points`` or ``degenerate`` (all points on a line or a plane: no tube to skeletonize).
    """
    p = np.asarray(points_mm, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise RibPullInputError(
            "bad_parameter", f"points must be an (N, 3) array of x, y, z in mm; got shape {p.shape}"
        )
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise RibPullInputError(
            "non_finite",
            f"{int(bad.sum())} of {len(p)} points have NaN or infinite coordinates "
            f"(first at row {int(np.argmax(bad))}); remove them before skeletonizing",
        )
    n_unique = len(np.unique(p, axis=0)) if len(p) else 0
    if n_unique < min_points:
        raise RibPullInputError(
            "too_few_points",
            f"skeletonization needs at least {min_points} distinct points; got {n_unique}",
        )
    centred = p - p.mean(axis=0)
    sv = np.linalg.svd(centred[:: max(1, len(p) // 20000)], compute_uv=False)
    if sv[0] <= 0 or sv[1] / sv[0] < 1e-6:
        raise RibPullInputError(
            "degenerate", "all points lie on one line: a skeleton needs a surface around a volume"
        )
    if sv[2] / sv[0] < 1e-6:
        raise RibPullInputError(
            "degenerate", "all points lie in one plane: a skeleton needs a surface around a volume"
        )
    return np.ascontiguousarray(p)


def auto_link_mm(points_mm: np.ndarray, factor: float = 2.5, cap_mm: float = 5.0) -> float:
    """Linking distance (mm) for `find_components`: factor x the median distance from a point to its
    3rd nearest neighbour, capped at `cap_mm` (keep it below the gap between adjacent ribs)."""
    d, _ = cKDTree(points_mm).query(points_mm, k=4)
    spacing = float(np.median(d[:, 3]))
    return float(min(factor * spacing, cap_mm))


def find_components(
    points_mm: np.ndarray,
    link_mm: float,
    labels: np.ndarray | None = None,
    min_component_points: int = 40,
) -> np.ndarray:
    """(N,) int component id per point (-1 = dropped as isolated noise), ids 0..C-1 by size.

    Two points are in one component when a chain of points, consecutive ones closer than `link_mm`
    (and, when `labels` are given, all with the same label), joins them. Components smaller than
    `min_component_points` are merged into the nearest big component if it is within 2 x link_mm
    (and has the same label), else dropped.
    """
    n = len(points_mm)
    tree = cKDTree(points_mm)
    pairs = tree.query_pairs(r=link_mm, output_type="ndarray")
    if labels is not None and len(pairs):
        pairs = pairs[labels[pairs[:, 0]] == labels[pairs[:, 1]]]
    g = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    sizes = np.bincount(comp)
    big = sizes[comp] >= min_component_points
    out = np.where(big, comp, -1)
    if big.any() and (~big).any():
        big_idx = np.flatnonzero(big)
        big_tree = cKDTree(points_mm[big_idx])
        small_ids = np.unique(comp[~big])
        for c in small_ids:
            members = np.flatnonzero(comp == c)
            d, j = big_tree.query(points_mm[members], k=1)
            best = int(np.argmin(d))
            target = big_idx[j[best]]
            if d[best] <= 2.0 * link_mm and (labels is None or labels[target] == labels[members[0]]):
                out[members] = out[target]
    # renumber by decreasing size
    ids, counts = np.unique(out[out >= 0], return_counts=True)
    order = ids[np.argsort(-counts, kind="stable")]
    remap = np.full(comp.max() + 1 if len(comp) else 1, -1, dtype=np.int64)
    remap[order] = np.arange(len(order))
    res = np.full(n, -1, dtype=np.int64)
    res[out >= 0] = remap[out[out >= 0]]
    return res
