"""Tube-aligned local quadrics: a mesh's vertices projected onto the noisy input along their normals.

A rib is a tube: along it the surface hardly bends; across it, it bends with the rib's ~4 mm
radius. An isotropic quadric patch must stay narrow enough for that cross-section, so on noisy,
not very dense input (20k-60k points, 1 mm noise) it averages ~13-17 points and leaves 0.2-0.26 mm
of noise, and `refine` skips such input (RefinePlan.too_noisy). A patch long along the tube and
narrow across it averages several times as many points with the same curvature error.

At each vertex the tube axis is the direction its neighbours' normals vary least along (a
cylinder's normals span the plane across its axis). The input points within a band of the
vertex's tangent plane get Gaussian weights with scale `along_mm` along the axis and `across_mm`
across it; a quadric height field h(a, b) = c0 + c1 a + c2 b + c3 a^2 + c4 ab + c5 b^2 fitted to
them by weighted least squares gives the vertex its new height c0 along the normal.

Units: millimetres throughout.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange
from scipy.spatial import cKDTree

#: a vertex moves only when its patch holds at least this much weight (the height field has 6 terms)
MIN_PATCH_WEIGHT = 6.0
#: the neighbourhood whose normals set a vertex's tube axis (mm): 3.6 mm holds the ~48 vertices the
#: bench's figures were measured with on its 1.2 mm-edge meshes (a rib's radius is ~4 mm)
AXIS_RADIUS_MM = 3.6


def cell_grid(points_mm: np.ndarray, cell_mm: float, max_cells: int = 1 << 24):
    """A uniform grid of cubic cells over (N, 3) points (mm) for radius searches in the compiled
    kernels: (lo (3,) mm, cell (mm), dims (3,), order (N,) point indices sorted by cell, starts
    (prod(dims) + 1,): cell c's points are order[starts[c]:starts[c + 1]]). The cell grows past
    cell_mm where the box would need more than max_cells cells (a far outlier)."""
    pts = np.asarray(points_mm, dtype=np.float64)
    lo = pts.min(0) - 1e-9
    extent = pts.max(0) - lo
    cell = float(cell_mm)
    while True:
        dims = np.maximum(np.ceil(extent / cell).astype(np.int64), 1)
        if int(np.prod(dims)) <= max_cells:
            break
        cell *= 1.26
    ijk = np.minimum(((pts - lo) / cell).astype(np.int64), dims - 1)
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(int(np.prod(dims)) + 1))
    return lo, cell, dims, order.astype(np.int64), starts.astype(np.int64)


def _typical_radius(queries: np.ndarray, tree: cKDTree, k: int, n_sample: int = 512) -> float:
    """The median, over up to n_sample of the (Q, 3) queries, of the distance to their k-th nearest
    point of `tree` (mm): the radius that holds about k points there."""
    sample = queries[np.linspace(0, len(queries) - 1, min(len(queries), n_sample)).astype(np.int64)]
    d, _ = tree.query(sample, k=[min(k, tree.n)], workers=-1)
    return float(np.median(d[np.isfinite(d)])) if np.isfinite(d).any() else 0.0


@njit(cache=True)
def ball_indices(points, lo, cell, dims, order, starts, centre, radius):  # pragma: no cover - compiled
    """(K,) indices of the (N, 3) points (mm; their `cell_grid`: lo, cell, dims, order, starts)
    within radius (mm) of centre (3,), in the grid's cell order. A centre beyond the grid gets the
    points of the cells it reaches, if any."""
    reach = int(np.ceil(radius / cell))
    r2 = radius * radius
    ci = int(np.floor((centre[0] - lo[0]) / cell))
    cj = int(np.floor((centre[1] - lo[1]) / cell))
    ck = int(np.floor((centre[2] - lo[2]) / cell))
    k0 = min(max(ck - reach, 0), dims[2])
    k1 = max(min(ck + reach + 1, dims[2]), k0)
    count = 0
    for a in range(max(ci - reach, 0), min(ci + reach + 1, dims[0])):
        for b in range(max(cj - reach, 0), min(cj + reach + 1, dims[1])):
            base = (a * dims[1] + b) * dims[2]
            count += starts[base + k1] - starts[base + k0]
    out = np.empty(count, dtype=np.int64)
    n = 0
    for a in range(max(ci - reach, 0), min(ci + reach + 1, dims[0])):
        for b in range(max(cj - reach, 0), min(cj + reach + 1, dims[1])):
            base = (a * dims[1] + b) * dims[2]
            for t in range(starts[base + k0], starts[base + k1]):
                p = order[t]
                dx = points[p, 0] - centre[0]
                dy = points[p, 1] - centre[1]
                dz = points[p, 2] - centre[2]
                if dx * dx + dy * dy + dz * dz <= r2:
                    out[n] = p
                    n += 1
    return out[:n]


@njit(parallel=True, cache=True)
def _normal_scatter(queries, vertices, normals, lo, cell, dims, order, starts, radius):  # pragma: no cover - compiled
    """((Q, 3, 3) sum of n n^T over the vertices within `radius` of each of the (Q, 3) queries,
    (Q,) how many). The cell grid (`cell_grid`) is of the vertices."""
    n_query = queries.shape[0]
    scatter = np.zeros((n_query, 3, 3))
    count = np.zeros(n_query)
    for i in prange(n_query):
        for p in ball_indices(vertices, lo, cell, dims, order, starts, queries[i], radius):
            for u in range(3):
                for w in range(3):
                    scatter[i, u, w] += normals[p, u] * normals[p, w]
            count[i] += 1.0
    return scatter, count


def tube_axes(vertices_mm: np.ndarray, normals: np.ndarray, radius_mm: float = AXIS_RADIUS_MM,
              min_neighbours: int = 16, at: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices (mm) and their (V, 3) unit normals -> ((V, 3) unit tube axes, (V,) axis
    spread): at each vertex the least eigenvector of its neighbours' normal scatter sum(n n^T),
    projected into the vertex's tangent plane, and that least eigenvalue over the neighbour count
    (the mean squared normal component along the axis: ~0 on a tube or a plate, larger where
    the surface bends both ways, e.g. a rib's end or a junction of a cartilage with the sternum).
    The neighbours: the vertices within radius_mm of a vertex, so that bumps smaller than that do
    not set the axis whatever the mesh's resolution; on a mesh so coarse that radius_mm holds fewer
    than min_neighbours vertices, the radius that holds that many (the median over a sample).
    at: (A,) vertex indices to return them at (all vertices' neighbours still count); None: every vertex."""
    v = np.ascontiguousarray(vertices_mm, dtype=np.float64)
    n = np.ascontiguousarray(normals, dtype=np.float64)
    if len(v) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    radius = max(float(radius_mm), _typical_radius(v, cKDTree(v), min_neighbours))
    queries = v if at is None else np.ascontiguousarray(v[at])
    scatter, count = _normal_scatter(queries, v, n, *cell_grid(v, radius), radius)
    eigenvalues, eigenvectors = np.linalg.eigh(scatter)
    axis = eigenvectors[:, :, 0]
    n = n if at is None else n[at]
    axis -= (axis * n).sum(1, keepdims=True) * n
    return axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12), eigenvalues[:, 0] / np.maximum(count, 1.0)


@njit(parallel=True, cache=True)
def _tube_heights(vertices, normals, axes, points, lo, cell, dims, order, starts, radius, along, across, band,
                  min_weight, max_move):  # pragma: no cover - compiled
    """(V,) height of each vertex's weighted quadric fit above it along its normal (0 where the
    patch is too light or the move exceeds max_move). The patch: the points within `radius` of
    the vertex (the points' `cell_grid`: lo, cell, dims, order, starts)."""
    n_vert = vertices.shape[0]
    heights = np.zeros(n_vert)
    for i in prange(n_vert):
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        ax, ay, az = axes[i, 0], axes[i, 1], axes[i, 2]
        bx, by, bz = ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax  # n x axis
        ata = np.zeros((6, 6))
        atb = np.zeros(6)
        row = np.empty(6)
        total = 0.0
        for p in ball_indices(points, lo, cell, dims, order, starts, vertices[i], radius):
            dx = points[p, 0] - vertices[i, 0]
            dy = points[p, 1] - vertices[i, 1]
            dz = points[p, 2] - vertices[i, 2]
            h = dx * nx + dy * ny + dz * nz
            if abs(h) >= band:
                continue
            a = (dx * ax + dy * ay + dz * az) / along
            b = (dx * bx + dy * by + dz * bz) / across
            w = np.exp(-(a * a + b * b))
            if w < 1e-6:
                continue
            total += w
            # the height field in units of (along, across): the same fit, better conditioned
            row[0], row[1], row[2], row[3], row[4], row[5] = 1.0, a, b, a * a, a * b, b * b
            for r in range(6):
                atb[r] += w * row[r] * h
                for c in range(6):
                    ata[r, c] += w * row[r] * row[c]
        if total < min_weight:
            continue
        for r in range(6):
            ata[r, r] += 1e-9 * total
        c0 = np.linalg.solve(ata, atb)[0]
        if abs(c0) < max_move:
            heights[i] = c0
    return heights


def project_onto_tube_patches(vertices_mm: np.ndarray, normals: np.ndarray, points_mm: np.ndarray,
                              along_mm: float, across_mm: float, k: int = 160, band_mm: float = 2.5,
                              max_move_mm: float = 2.0, tree: cKDTree | None = None,
                              max_axis_spread: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices (mm) with (V, 3) unit normals, (N, 3) input points (mm) -> ((V, 3) vertices
    moved along their normals onto their tube-aligned quadric of the points, (V,) bool: which
    moved). A patch holds the points within band_mm of the vertex's tangent plane (not the far wall
    of a rib) inside the ball that holds about k points (its radius: the median over the vertices
    of their k-th nearest point's distance), weighted exp(-(a/along_mm)^2 - (b/across_mm)^2) (a along the tube axis,
    b across it); a vertex stays where its patch weighs less than MIN_PATCH_WEIGHT or the move would
    exceed max_move_mm. tree: a kd-tree of points_mm to reuse.
    max_axis_spread: where given, a vertex whose `tube_axes` spread is above it is not a tube's
    and stays; from half of it up the move fades out linearly (no seam where the tube ends)."""
    v = np.ascontiguousarray(vertices_mm, dtype=np.float64)
    n = np.ascontiguousarray(normals, dtype=np.float64)
    pts = np.ascontiguousarray(points_mm, dtype=np.float64)
    if len(v) == 0 or len(pts) == 0:
        return v.copy(), np.zeros(len(v), dtype=bool)
    axes, spread = tube_axes(v, n)
    weight = np.ones(len(v)) if max_axis_spread is None else np.clip(2.0 - 2.0 * spread / max_axis_spread, 0.0, 1.0)
    active = np.flatnonzero(weight > 0)  # a vertex the gate holds still needs no patch
    heights = np.zeros(len(v))
    if len(active):
        tree = tree if tree is not None else cKDTree(pts)
        # the ball that holds about k points where the mesh lies (not k nearest per vertex: a radius
        # search on a cell grid costs a fraction of a kd-tree's k-nearest query)
        radius = _typical_radius(v[active], tree, k)
        if radius > 0:
            heights[active] = _tube_heights(np.ascontiguousarray(v[active]), np.ascontiguousarray(n[active]),
                                            np.ascontiguousarray(axes[active]), pts, *cell_grid(pts, radius), radius,
                                            float(along_mm), float(across_mm), float(band_mm), MIN_PATCH_WEIGHT,
                                            float(max_move_mm))
    heights *= weight
    return v + heights[:, None] * n, heights != 0.0
