"""Where a mesh's error lies against a true surface, by how close the surface is to a voxel axis:
signed distance (mm, + where the truth lies outside the mesh) at area-uniform truth samples, to the
mesh's nearest of `--mesh-samples` samples, along that sample's face normal; binned by the truth
normal's largest component (1: parallel to a voxel face, 0.577: diagonal to all three).

    .venv/bin/python benchmarks/error_by_orientation.py TRUTH.ply MESH.ply [MESH.ply ...]

e.g. a `ribpull bench --plan sweep -o DIR` run's DIR/cases/phantom-s0-mask1.5mm-pv/truth_mesh.ply
against DIR/runs/phantom-s0-mask1.5mm-pv-seed0__sparseocc_default/artifacts/mesh.ply and the
mc_taubin run's mesh.ply (docs/benchmarks.md, "Where the 1.5 mm map's error is").
"""

from __future__ import annotations

import argparse

import numpy as np
import trimesh
from scipy.spatial import cKDTree

BINS = ((0.577, 0.7), (0.7, 0.8), (0.8, 0.9), (0.9, 0.97), (0.97, 1.01))


def signed_errors(truth: trimesh.Trimesh, mesh: trimesh.Trimesh, points: np.ndarray, mesh_samples: int) -> np.ndarray:
    """(N,) signed distance (mm) of (N, 3) truth points to `mesh` along its normals, + outside it."""
    q, face = trimesh.sample.sample_surface(mesh, mesh_samples, seed=4)
    _, i = cKDTree(q).query(points, workers=-1)
    return np.einsum("ij,ij->i", points - q[i], mesh.face_normals[face[i]])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("truth")
    ap.add_argument("meshes", nargs="+")
    ap.add_argument("--samples", type=int, default=300_000, help="truth samples")
    ap.add_argument("--mesh-samples", type=int, default=4_000_000, help="samples on each mesh")
    args = ap.parse_args()
    truth = trimesh.load(args.truth, process=False)
    points, face = trimesh.sample.sample_surface(truth, args.samples, seed=3)
    alignment = np.abs(truth.face_normals[face]).max(axis=1)
    for path in args.meshes:
        s = signed_errors(truth, trimesh.load(path, process=False), points, args.mesh_samples)
        print(f"{path}: signed mean {s.mean():+.4f} mm, mean |error| {np.abs(s).mean():.4f} mm")
        for lo, hi in BINS:
            m = (alignment >= lo) & (alignment < hi)
            print(f"  largest normal component [{lo:.2f}, {min(hi, 1.0):.2f}): {m.mean():5.1%} of the surface, "
                  f"signed {s[m].mean():+.4f}, |error| {np.abs(s[m]).mean():.4f} mm")


if __name__ == "__main__":
    main()
