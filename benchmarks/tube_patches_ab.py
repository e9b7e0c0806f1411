"""A lead for sparse, noisy points (not in the pipeline): a mesh's vertices projected onto local
quadrics of the input fitted over tube-aligned neighbourhoods, long along a rib and narrow across it.

A rib is a tube: along it the surface hardly bends, across it it bends with the rib's ~4 mm radius.
An isotropic patch must stay narrow (the cross-section's curvature), so at 20k points / 1 mm noise
it averages ~13 points and leaves ~0.26 mm of noise (the refinement is skipped there). A patch
`along_mm` long and `across_mm` wide averages several times as many points with the same
curvature error. The tube axis at a vertex is the least eigenvector of its 48 nearest vertices'
normal scatter (a cylinder's normals span the plane across its axis).

    .venv/bin/python benchmarks/tube_patches_ab.py
    .venv/bin/python benchmarks/tube_patches_ab.py --cases 20000:1.0 --shapes 10,2.5 7,2.5

Rows: the baseline (screened Poisson); the `default` mesh; for each ALONG,ACROSS shape (mm) the
default's mesh projected, then the baseline's mesh projected (a surface with the right topology).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import abkit
import numpy as np
from scipy.spatial import cKDTree

DEFAULT_CASES = ("20000:1.0", "10000:1.0")


def tube_axes(vertices: np.ndarray, normals: np.ndarray, k: int = 48) -> np.ndarray:
    """(V, 3) unit vectors: at each vertex the direction its k nearest vertices' normals (V, 3)
    vary least along, projected into the vertex's tangent plane (a tube's axis)."""
    _, nn = cKDTree(vertices).query(vertices, k=min(k, len(vertices)), workers=-1)
    nb = normals[nn]
    axis = np.linalg.eigh(np.matmul(nb.transpose(0, 2, 1), nb))[1][:, :, 0]
    axis -= (axis * normals).sum(1, keepdims=True) * normals
    return axis / (np.linalg.norm(axis, axis=1, keepdims=True) + 1e-12)


def project_on_tube_patches(mesh, points_mm: np.ndarray, along_mm: float, across_mm: float, k: int = 160,
                            band_mm: float = 2.5, chunk: int = 20_000):
    """A copy of `mesh` (mm) whose vertices are moved along their normals onto a quadric height
    field of the input points (N, 3) mm: the k nearest points within band_mm of the tangent plane,
    Gaussian-weighted with scale along_mm along the tube axis and across_mm across it. A vertex
    whose patch holds less than 6 points' weight, or whose move exceeds 2 mm, stays."""
    import trimesh

    v, n = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.vertex_normals, dtype=np.float64)
    axis = tube_axes(v, n)
    across = np.cross(n, axis)
    pts = np.asarray(points_mm, dtype=np.float64)
    _, nn = cKDTree(pts).query(v, k=min(k, len(pts)), workers=-1)
    out = v.copy()
    for s in range(0, len(v), chunk):
        sl = slice(s, min(s + chunk, len(v)))
        d = pts[nn[sl]] - v[sl, None]
        a = (d * axis[sl, None]).sum(-1)
        b = (d * across[sl, None]).sum(-1)
        h = (d * n[sl, None]).sum(-1)
        wt = np.exp(-(a / along_mm) ** 2 - (b / across_mm) ** 2) * (np.abs(h) < band_mm)
        basis = np.stack([np.ones_like(a), a, b, a * a, a * b, b * b], -1)
        basis_wt = (basis * wt[..., None]).transpose(0, 2, 1)
        coef = np.linalg.solve(basis_wt @ basis + 1e-6 * np.eye(6), basis_wt @ h[..., None])[..., 0]
        move = np.where((wt.sum(1) > 6) & (np.abs(coef[:, 0]) < 2.0), coef[:, 0], 0.0)
        out[sl] = v[sl] + move[:, None] * n[sl]
    return trimesh.Trimesh(out, mesh.faces, process=False)


def main() -> None:
    from ribpull_core.io import load_point_cloud

    ap = abkit.case_arguments(__doc__, DEFAULT_CASES)
    ap.add_argument("--shapes", nargs="+", default=["7,2.5", "10,2.5", "10,3"],
                    help="ALONG,ACROSS Gaussian scales of a patch in mm")
    args = ap.parse_args()
    print(abkit.TABLE_HEADER)
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.cases:
            case = abkit.bench_case(spec, Path(tmp))
            baseline = abkit.baseline_for(case)
            default_mesh, seconds = abkit.fit_default(Path(case.input_path), Path(tmp) / case.name)
            points = load_point_cloud(Path(case.input_path)).points
            runs = [baseline, ("default", default_mesh, seconds)]
            for shape in args.shapes:
                along, across = (float(x) for x in shape.split(","))
                for name, mesh in (("default", default_mesh), ("baseline", baseline[1])):
                    t = time.perf_counter()
                    projected = project_on_tube_patches(mesh, points, along, across)
                    runs.append((f"{name} on {along:g} x {across:g} mm tube patches", projected, time.perf_counter() - t))
            abkit.print_runs(spec, case, runs, args.samples)


if __name__ == "__main__":
    main()
