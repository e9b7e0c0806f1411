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


def tube_axes(vertices_mm: np.ndarray, normals: np.ndarray, radius_mm: float = AXIS_RADIUS_MM,
              max_neighbours: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices (mm) and their (V, 3) unit normals -> ((V, 3) unit tube axes, (V,) axis
    spread): at each vertex the least eigenvector of its neighbours' normal scatter sum(n n^T),
    projected into the vertex's tangent plane, and that least eigenvalue over the neighbour count
    (the mean squared normal component along the axis: ~0 on a tube or a plate, larger where
    the surface bends both ways, e.g. a rib's end or a junction of a cartilage with the sternum).
    The neighbours: as many nearest vertices as lie within radius_mm of a vertex (the median over
    a sample of vertices; 16 to max_neighbours), so that bumps smaller than that do not set the
    axis whatever the mesh's resolution."""
    v = np.asarray(vertices_mm, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    tree = cKDTree(v)
    sample = v[np.linspace(0, len(v) - 1, min(len(v), 256)).astype(np.int64)]
    k = int(np.clip(np.median(tree.query_ball_point(sample, radius_mm, return_length=True)), 16, max_neighbours))
    _, nn = tree.query(v, k=min(k, len(v)), workers=-1)
    nb = n[nn]
    eigenvalues, eigenvectors = np.linalg.eigh(np.matmul(nb.transpose(0, 2, 1), nb))
    axis = eigenvectors[:, :, 0]
    axis -= (axis * n).sum(1, keepdims=True) * n
    return axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12), eigenvalues[:, 0] / nn.shape[1]


@njit(parallel=True, cache=True)
def _tube_heights(vertices, normals, axes, points, neighbours, along, across, band, min_weight,
                  max_move):  # pragma: no cover - compiled
    """(V,) height of each vertex's weighted quadric fit above it along its normal (0 where the
    patch is too light or the move exceeds max_move). neighbours: (V, k) point indices."""
    n_vert, k = neighbours.shape
    heights = np.zeros(n_vert)
    for i in prange(n_vert):
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        ax, ay, az = axes[i, 0], axes[i, 1], axes[i, 2]
        bx, by, bz = ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax  # n x axis
        ata = np.zeros((6, 6))
        atb = np.zeros(6)
        row = np.empty(6)
        total = 0.0
        for j in range(k):
            p = neighbours[i, j]
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
    moved). A patch holds the vertex's k nearest points within band_mm of its tangent plane (not
    the far wall of a rib), weighted exp(-(a/along_mm)^2 - (b/across_mm)^2) (a along the tube axis,
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
    axes = np.ascontiguousarray(axes)
    tree = tree if tree is not None else cKDTree(pts)
    _, nn = tree.query(v, k=min(k, len(pts)), workers=-1)
    nn = np.ascontiguousarray(nn.reshape(len(v), -1), dtype=np.int64)
    heights = _tube_heights(v, n, axes, pts, nn, float(along_mm), float(across_mm), float(band_mm),
                            MIN_PATCH_WEIGHT, float(max_move_mm))
    if max_axis_spread is not None:
        heights *= np.clip(2.0 - 2.0 * spread / max_axis_spread, 0.0, 1.0)
    return v + heights[:, None] * n, heights != 0.0
