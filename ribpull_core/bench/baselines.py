"""The classical baselines of `ribpull bench`, as plain functions (mm in, trimesh in mm out):
screened Poisson on points with flood-fill-oriented normals, marching cubes on a label mask (plain,
and followed by Taubin smoothing: `mc_taubin`), and voxel thinning of a solid (skeletons).
"""

from __future__ import annotations

import numpy as np

from .common import SKELETON_BENCHMARK

POISSON_DEPTH = 8  # octree depth of screened Poisson (2^8 cells over ~1.1x the longest side: ~1.2 mm;
#                    depth 9 measured no better on the 20k-point phantom and ~1.7x slower)
#: Taubin smoothing passes of the `mc_taubin` baseline (trimesh's default lambda = nu = 0.5; what a
#: 3D Slicer user gets from "marching cubes + smoothing")
TAUBIN_ITERATIONS = 20


def flood_fill_normals(points_mm: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of unoriented points (mm): PCA over 16 neighbours, oriented towards the
    flood-filled empty space (the orientation RibPull's default preset derives from the data)."""
    from ..frame import UnitFrame
    from ..methods.sparseocc import oriented_normals, outside_mask

    pu = UnitFrame.fit(points_mm).to_unit(points_mm)
    outside, _, spacing, origin = outside_mask(pu)
    return oriented_normals(pu, outside, spacing, origin)


def poisson_mesh(points_mm: np.ndarray, normals: np.ndarray, depth: int = POISSON_DEPTH):
    """Screened Poisson surface (pymeshlab) of oriented points; mm in, trimesh in mm out."""
    import pymeshlab
    import trimesh

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points_mm, dtype=np.float64),
                               v_normals_matrix=np.ascontiguousarray(normals, dtype=np.float64)))
    ms.generate_surface_reconstruction_screened_poisson(depth=int(depth), preclean=True)
    out = ms.current_mesh()
    return trimesh.Trimesh(out.vertex_matrix(), out.face_matrix(), process=True)


def volume_marching_cubes(mask: np.ndarray, affine: np.ndarray, taubin_iterations: int = 0):
    """Marching cubes at 0.5 on a binary volume (nonzero = inside) in voxel index space, padded by one
    empty voxel so the surface closes; vertices mapped to mm through the 4x4 voxel -> mm affine (so
    the spacing of each axis, and any rotation, is respected), faces oriented outwards. With
    taubin_iterations > 0, that many passes of Taubin smoothing (trimesh.smoothing.filter_taubin,
    default lambda / nu) in mm. Returns a trimesh in mm."""
    import trimesh
    from skimage.measure import marching_cubes

    padded = np.pad(np.asarray(mask) != 0, 1).astype(np.float32)
    verts, faces, _, _ = marching_cubes(padded, level=0.5)
    mesh = trimesh.Trimesh(trimesh.transform_points(verts - 1.0, np.asarray(affine, dtype=np.float64)), faces,
                           process=True)
    if mesh.volume < 0:
        mesh.invert()
    if taubin_iterations:
        trimesh.smoothing.filter_taubin(mesh, iterations=int(taubin_iterations))
    return mesh


def mask_marching_cubes(cloud, taubin_iterations: int = 0):
    """volume_marching_cubes of a label map's selected voxels: the cloud's voxel centres (a PointCloud
    loaded from NIfTI) put back on their grid through the inverse affine. Returns a trimesh in mm."""
    from ..pointcloud import mask_voxel_indices

    ijk = mask_voxel_indices(cloud)  # ValueError unless the cloud comes from a NIfTI label map
    mask = np.zeros(np.asarray(cloud.nifti_shape), dtype=bool)
    mask[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return volume_marching_cubes(mask, cloud.nifti_affine, taubin_iterations)


def load_skeleton_benchmark():
    """benchmarks/skeleton_phantom.py as a module (for its `voxel_skeleton` baseline)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("ribpull_benchmarks_skeleton_phantom", SKELETON_BENCHMARK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def voxel_thinning_skeleton(vol: np.ndarray, affine: np.ndarray):
    """Voxel-thinning skeleton (benchmarks/skeleton_phantom.voxel_skeleton) of a label volume whose
    voxels map to mm through `affine`."""
    return load_skeleton_benchmark().voxel_skeleton(vol, affine)
