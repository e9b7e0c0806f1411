"""Curvature-proportional offsets of a fitted surface, and their removal by mean-curvature flow.

Two inputs put a surface off its truth in proportion to its mean curvature H ((k1 + k2) / 2):

- Noise. Samples of a curved surface with isotropic noise of std sigma (mm) lie, on average,
  sigma^2 * H outside it (on a rib of radius R that is sigma^2 / 2R): the tangential part of each
  sample's noise lifts it off the curve. A surface fitted to them inherits the offset; on the
  bench's 60k points / 1 mm phantom the field's mesh sat ~0.12 mm outside the truth.
  `remove_noise_bias` flows it inward.
- Smoothing. A label map's boundary points are placed where the mask, blurred by a Gaussian (and
  by the voxel's own box), crosses 0.5 (`pointcloud.mask_boundary_cloud`). Blurring an indicator is
  a heat flow, whose 0.5 level set moves like a mean-curvature flow for t = variance / 2: inward by
  2 H t on a convex rib. On the 1.5 mm phantom map the refined mesh sat 0.075 mm inside the truth,
  0.16 mm where a rib's cross-section is most curved. `restore_smoothing_bias` moves it back out.

The flow dx/dt = Laplace-Beltrami(x) = -2 H n moves a surface inward by 2 H t, in proportion to
the curvature that made the offset; it also smooths the bumps a few mm across that the fit did not
average out.

Units: millimetres throughout (the input's own frame); t in mm^2.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .quadrics import HEIGHT_FIELD_TERMS


def normal_noise_mm(patch_residual_mm: float, neighbours: int) -> float:
    """The sample noise's std along the normal (mm), from the RMS residual of k-point quadric
    patches (refine.RefinePlan): a least-squares fit of HEIGHT_FIELD_TERMS (6) parameters keeps (k - 6) / k of the
    noise's variance in its residuals. On the bench's 60k points / 1 mm noise phantom: residual
    0.806 mm over 17 points -> 1.00 mm. At a coarser sampling the patches' misfit of the curvature
    adds to it (20k / 1 mm: 0.94 mm over 13 -> 1.28 mm)."""
    k = max(int(neighbours), HEIGHT_FIELD_TERMS + 1)
    return float(patch_residual_mm) * float(np.sqrt(k / (k - HEIGHT_FIELD_TERMS)))


def cotangent_laplacian(vertices_mm: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, sp.dia_matrix]:
    """(L, M) of a triangle mesh: (V, V) cotangent Laplacian L (positive semi-definite: x^T L x is
    the Dirichlet energy of the piecewise-linear x, whatever the triangles' angles; L x = 2 H n A at a
    vertex of area A) and (V, V) lumped mass M (a third of each adjacent triangle's area, mm^2),
    from (V, 3) vertices_mm and (F, 3) faces. Degenerate triangles add nothing.

    Why not robust_laplacian.mesh_laplacian (intrinsic Delaunay): on a 1.5 mm label map's
    177k-vertex mesh it took 1.5-3.2 s against 0.5 s here, and the backward-Euler step that uses L
    needs no maximum principle (M + t L is positive definite either way; the obtuse triangles'
    negative weights only make single vertices overshoot, by far less than the flow's 0.1 mm)."""
    verts = np.asarray(vertices_mm, dtype=np.float64)
    tri = np.asarray(faces, dtype=np.int64)
    n = len(verts)
    corners = verts[tri]  # (F, 3 corners, 3)
    double_area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    safe = np.where(double_area > 0, double_area, np.inf)
    rows, cols, weights = [], [], []
    for k in range(3):  # the angle at corner k faces the edge (k+1, k+2): weight cot / 2 on that edge
        i, j = tri[:, (k + 1) % 3], tri[:, (k + 2) % 3]
        a, b = corners[:, (k + 1) % 3] - corners[:, k], corners[:, (k + 2) % 3] - corners[:, k]
        half_cot = 0.5 * np.einsum("ij,ij->i", a, b) / safe
        rows += [i, j]
        cols += [j, i]
        weights += [half_cot, half_cot]
    w = sp.csr_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    laplacian = (sp.diags(np.asarray(w.sum(axis=1)).ravel()) - w).tocsr()
    mass = np.bincount(tri.ravel(), weights=np.repeat(double_area / 6.0, 3), minlength=n)
    return laplacian, sp.diags(mass)


def flow_step(vertices_mm: np.ndarray, faces: np.ndarray, time_mm2: float):
    """The implicit (backward Euler) mean-curvature flow step of length time_mm2 on a mesh, as a
    function (V, 3) -> (V, 3) that applies (M + t L)^-1 M, with L and M the `cotangent_laplacian`
    and mass matrix at (V, 3) vertices_mm and (F, 3) faces. Applied to the vertices it
    flows them; applied to any per-vertex field it smooths that field over the surface. For
    time_mm2 <= 0 or an empty mesh: the identity (a copy)."""
    verts = np.asarray(vertices_mm, dtype=np.float64)
    if time_mm2 <= 0 or len(verts) == 0:
        return lambda values: np.array(values, dtype=np.float64)
    laplacian, mass = mesh_laplacian(verts, np.asarray(faces, dtype=np.int64))
    solve = sla.splu((mass + time_mm2 * laplacian).tocsc())
    return lambda values: solve.solve(mass @ values)


#: the Laplacian `flow_step` uses (benchmarks/laplacian_ab.py swaps in robust_laplacian's)
mesh_laplacian = cotangent_laplacian


def mean_curvature_flow(vertices_mm: np.ndarray, faces: np.ndarray, time_mm2: float) -> np.ndarray:
    """(V, 3) vertices (mm) and (F, 3) triangles -> (V, 3) vertices after one `flow_step` of
    length time_mm2: (M + t L) x' = M x. Implicit, so any t is stable; for small t each vertex
    moves 2 H t along its inward normal."""
    verts = np.asarray(vertices_mm, dtype=np.float64)
    return flow_step(verts, faces, time_mm2)(verts)


def reverse_curvature_flow(vertices_mm: np.ndarray, faces: np.ndarray, time_mm2: float) -> np.ndarray:
    """(V, 3) vertices (mm) and (F, 3) triangles -> (V, 3) vertices moved by the reverse of a
    mean-curvature flow of length time_mm2: outward by 2 H t. A backward flow amplifies every bump
    (it is ill-posed), so the displacement is measured by the stable forward step instead, d =
    step(x) - x (-2 H t n, and minus the mesh's finest bumps), smoothed by the same step (which
    takes those bumps out of it), and subtracted: x' = x - step(d)."""
    verts = np.asarray(vertices_mm, dtype=np.float64)
    step = flow_step(verts, faces, time_mm2)
    return verts - step(step(verts) - verts)


def remove_noise_bias(vertices_mm: np.ndarray, faces: np.ndarray, sigma_mm: float,
                      factor: float = 1.0) -> tuple[np.ndarray, dict]:
    """Post-process of a mesh fitted to points with normal noise sigma_mm (mm): the
    `mean_curvature_flow` for t = factor * sigma^2 / 2 (factor 1: the offset sigma^2 H exactly).
    Returns ((V, 3) vertices in mm, a summary for metrics.json)."""
    time_mm2 = factor * float(sigma_mm) ** 2 / 2.0
    out = mean_curvature_flow(vertices_mm, faces, time_mm2)
    return out, {"sigma_mm": round(float(sigma_mm), 4), **_flow_summary(vertices_mm, out, time_mm2)}


def restore_smoothing_bias(vertices_mm: np.ndarray, faces: np.ndarray, smoothing_time_mm2: float,
                           factor: float = 1.0) -> tuple[np.ndarray, dict]:
    """Post-process of a mesh fitted to points that lie on a smoothed surface, the input's surface
    after a mean-curvature flow of smoothing_time_mm2 (`pointcloud.boundary_smoothing_time_mm2`):
    the `reverse_curvature_flow` for factor x that time. Returns ((V, 3) vertices in mm, a summary
    for metrics.json)."""
    time_mm2 = factor * float(smoothing_time_mm2)
    out = reverse_curvature_flow(vertices_mm, faces, time_mm2)
    return out, _flow_summary(vertices_mm, out, time_mm2)


def _flow_summary(before_mm: np.ndarray, after_mm: np.ndarray, time_mm2: float) -> dict:
    """{flow_time_mm2, mean_shift_mm} of a flow that moved (V, 3) vertices before_mm to after_mm."""
    shift = np.linalg.norm(np.asarray(after_mm) - np.asarray(before_mm, dtype=np.float64), axis=1)
    return {"flow_time_mm2": round(time_mm2, 4), "mean_shift_mm": round(float(shift.mean()), 4) if len(shift) else 0.0}
