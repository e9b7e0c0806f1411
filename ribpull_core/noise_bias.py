"""Noise bias of a surface fitted to noisy points, and its removal by mean-curvature flow.

Samples of a curved surface with isotropic noise of std sigma (mm) lie, on average, sigma^2 * H
outside it (H: the mean curvature, (k1 + k2) / 2; on a rib of radius R that is sigma^2 / 2R): the
tangential part of each sample's noise lifts it off the curve. A surface fitted to them inherits
the offset, and on the bench's 60k points / 1 mm phantom the field's mesh sat ~0.12 mm outside
the truth. The flow dx/dt = Laplace-Beltrami(x) = -2 H n moves a surface inward by 2 H t, so a
flow for t = sigma^2 / 2 takes that offset off, in proportion to the curvature that made it; it
also smooths the noise bumps of the fitted surface (a few mm across) that it did not average out.

Units: millimetres throughout (the input's own frame); t in mm^2.
"""

from __future__ import annotations

import numpy as np
import robust_laplacian
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


def mean_curvature_flow(vertices_mm: np.ndarray, faces: np.ndarray, time_mm2: float) -> np.ndarray:
    """(V, 3) vertices (mm) and (F, 3) triangles -> (V, 3) vertices after one implicit (backward
    Euler) step of mean-curvature flow of length time_mm2: (M + t L) x' = M x, with L and M the
    cotangent Laplacian and mass matrix of robust_laplacian (intrinsic Delaunay, so sliver
    triangles of marching cubes do not give negative weights). Implicit, so any t is stable; for
    small t each vertex moves 2 H t along its inward normal."""
    verts = np.asarray(vertices_mm, dtype=np.float64)
    if time_mm2 <= 0 or len(verts) == 0:
        return verts.copy()
    laplacian, mass = robust_laplacian.mesh_laplacian(verts, np.asarray(faces, dtype=np.int64))
    solve = sla.splu((mass + time_mm2 * laplacian).tocsc())
    return solve.solve(mass @ verts)


def remove_noise_bias(vertices_mm: np.ndarray, faces: np.ndarray, sigma_mm: float,
                      factor: float = 1.0) -> tuple[np.ndarray, dict]:
    """Post-process of a mesh fitted to points with normal noise sigma_mm (mm): the
    `mean_curvature_flow` for t = factor * sigma^2 / 2 (factor 1: the offset sigma^2 H exactly).
    Returns ((V, 3) vertices in mm, a summary for metrics.json)."""
    time_mm2 = factor * float(sigma_mm) ** 2 / 2.0
    out = mean_curvature_flow(vertices_mm, faces, time_mm2)
    shift = np.linalg.norm(out - np.asarray(vertices_mm, dtype=np.float64), axis=1)
    return out, {"sigma_mm": round(float(sigma_mm), 4), "flow_time_mm2": round(time_mm2, 4),
                 "mean_shift_mm": round(float(shift.mean()), 4) if len(shift) else 0.0}
