"""Medial curves of ribs: Laplacian contraction (paper eq. 3-4), curve graph, labels, export, metrics.

Public API:
    SkeletonConfig, RibCurve, Skeleton          data types (model.py)
    laplacian_contraction(points_mm, config)    paper eq. 3-4, per connected cluster (contraction.py)
    skeletonize(points_mm, ...)                 points -> Skeleton (extract.py)
    skeleton_from_mesh(mesh_mm, n_points, ...)  closed mesh -> Skeleton (extract.py)
    export_skeleton(skel, outdir, mesh_mm)      json / glb / obj / scene.glb (export.py)
    skeleton_metrics(skel, true_centerlines)    distances, coverage, topology, labels (metrics.py)
"""

from ribpull_core.skeleton.contraction import laplacian_contraction
from ribpull_core.skeleton.export import export_skeleton
from ribpull_core.skeleton.extract import skeleton_from_mesh, skeletonize
from ribpull_core.skeleton.metrics import skeleton_metrics
from ribpull_core.skeleton.model import RibCurve, Skeleton, SkeletonConfig

__all__ = [
    "RibCurve",
    "Skeleton",
    "SkeletonConfig",
    "export_skeleton",
    "laplacian_contraction",
    "skeleton_from_mesh",
    "skeleton_metrics",
    "skeletonize",
]
