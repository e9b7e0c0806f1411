"""Surface refinement: the field's mesh vertices moved onto the input points' local quadric patches.

The field cannot bend on a scale finer than its finest grid cell (about one sampling gap), so its
zero level set is a smoothed version of the sampled surface. After meshing, every vertex is
projected onto a moving-least-squares surface of the input points (`quadrics`), patches of a
fixed physical radius: large enough to average the sample noise over ~10-60 points, smaller than a
rib's cross-section so that a patch stays on one side of the bone. The mesh's connectivity (and so
its components, holes and watertightness) is the field's; only vertex positions change. A vertex
moves onto the patches only when that is at most `max_shift_gaps` sampling gaps away: farther, a
patch there does not describe the surface (between two nearby structures, or a bump of the field
the points do not support). Those vertices are then faired (`fair_vertices`): moved to the smooth
(thin-plate) surface that joins the projected vertices around them, instead of being left where
the field put them; a field bump a few mm high otherwise set the mesh's Hausdorff distance.

Units: millimetres throughout (the input's own frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from .config import RefineConfig, SectionQuadricConfig, TubePatchConfig
from .curvature_bias import normal_noise_mm, remove_noise_bias, restore_smoothing_bias
from .pointcloud import sampling_gap
from .quadrics import LocalQuadrics, fit_local_quadrics, pca_normals, project_onto_blended_quadrics


def patch_size(points_mm: np.ndarray, config: RefineConfig, tree: cKDTree, probe: np.ndarray) -> tuple[int, float]:
    """(N, 3) input points in mm -> (k, r): the neighbour count of a patch and the median distance
    (mm) from a probe point (indices `probe`) to its k-th neighbour. k is the count within
    config.radius_mm, at least config.min_neighbours (noise is averaged over that many samples) and
    at most config.max_neighbours."""
    kmax = int(min(config.max_neighbours, len(points_mm) - 1))
    dist = np.median(tree.query(points_mm[probe], k=kmax + 1, workers=-1)[0], axis=0)  # dist[0] = 0 (itself)
    k = int(np.clip(np.searchsorted(dist, config.radius_mm, side="right") - 1, config.min_neighbours, kmax))
    return k, float(dist[k])


@dataclass
class RefinePlan:
    """Whether an input gets refined, decided before the fit (so the fit can be scheduled for it).

    neighbours: points per patch; patch_radius_mm: median distance to the farthest of them;
    patch_residual_mm: median RMS distance of the points from their patches (sample noise plus
    misfit), over a probe of the points; reason: why the input is not refined (None: it is);
    too_noisy: it is not refined because of its noise (not its sparsity), so its mesh gets the
    noise-bias flow instead (`refine_vertices`)."""

    neighbours: int
    patch_radius_mm: float
    patch_residual_mm: float
    reason: str | None = None
    too_noisy: bool = False

    @property
    def applies(self) -> bool:
        """Both the radius and the residual are within the config's bounds."""
        return self.reason is None

    def summary(self) -> dict:
        return {"neighbours": self.neighbours, "patch_radius_mm": round(self.patch_radius_mm, 3),
                "patch_residual_mm": round(self.patch_residual_mm, 4), "applied": self.applies,
                **({"reason": self.reason} if self.reason else {})}


def plan_refinement(points_mm: np.ndarray, config: RefineConfig, tree: cKDTree | None = None,
                    n_probe: int = 4000) -> RefinePlan:
    """(N, 3) input points in mm -> the RefinePlan, from patches at a strided probe of at most
    ~n_probe points. Inputs too sparse (a patch's points spread farther than config.max_radius_mm:
    such a patch spans the rib's curvature and would flatten it) or too noisy for their density (the
    points' RMS distance off their patches over sqrt(k), the noise a patch of k of them keeps, is
    more than config.max_patch_noise_mm: such patches would put back noise the field smoothed out)
    are not refined."""
    pts = np.asarray(points_mm, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(pts)
    probe = np.arange(0, len(pts), max(1, len(pts) // n_probe))
    k, radius = patch_size(pts, config, tree, probe)
    residual = float(np.median(fit_local_quadrics(pts, k=k, tree=tree, at=probe).residual))
    reason, too_noisy = None, False
    if radius > config.max_radius_mm:
        reason = f"input too sparse: {k} points span {radius:.1f} mm, over the {config.max_radius_mm} mm a patch may cover"
    elif residual / np.sqrt(k) > config.max_patch_noise_mm:
        reason, too_noisy = (f"input too noisy: the points lie {residual:.2f} mm (RMS) off their patches, which "
                             f"leaves {residual / np.sqrt(k):.2f} mm in a patch of {k}, over {config.max_patch_noise_mm} mm"), True
    return RefinePlan(k, radius, residual, reason, too_noisy)


def terrace_weights(points_mm: np.ndarray, face_axis: np.ndarray, affine: np.ndarray, weight: float,
                    tree: cKDTree | None = None) -> np.ndarray:
    """(N,) weights of a label map's boundary points (mm; face_axis (N,): the voxel axis of each
    point's face, `PointCloud.face_axis`; affine: the map's 4x4 voxel -> mm) in the refinement's
    patches: `weight` for a point on a terrace, 1 for the others.

    Where a surface runs nearly along a voxel face, a partial-volume map draws it as terraces: faces
    across the voxel axis nearest the surface normal, each only saying that the surface lies within
    half a voxel of it, joined by risers (faces along the other axes), which sit where the surface
    crosses the height of a voxel centre. A terrace point is one whose face axis is the axis nearest
    its local (PCA) normal. Down-weighting them lets the risers set the height: on the bench's
    partial-volume maps (benchmarks/terrace_ab.py, 1M samples, CD-L1 / HD mm) weight 0.3 against
    1: 1.5 mm 0.2455 / 0.93 against 0.2473 / 0.95; 0.75 x 0.75 x 2.5 mm 0.2524 / 1.18 against
    0.2596 / 1.21; sternum map 0.2663 / 1.42 against 0.2678 / 1.38 (weight 0.5: between the two)."""
    pts = np.asarray(points_mm, dtype=np.float64)
    normals = pca_normals(pts, tree=tree)
    a = np.asarray(affine, dtype=np.float64)[:3, :3]
    dominant = np.abs(normals @ (a / np.linalg.norm(a, axis=0))).argmax(axis=1)  # in unit voxel axes
    return np.where(dominant == np.asarray(face_axis), float(weight), 1.0)


def point_weights_of(cloud, config: RefineConfig, tree: cKDTree | None = None) -> np.ndarray | None:
    """The refinement's per-point weights for a PointCloud: `terrace_weights` for a label map's
    boundary points (config.terrace_weight), None (all equal) for other inputs or weight 1."""
    if cloud.face_axis is None or cloud.nifti_affine is None or config.terrace_weight == 1.0:
        return None
    return terrace_weights(cloud.points, cloud.face_axis, cloud.nifti_affine, config.terrace_weight, tree)


def refinement_patches(points_mm: np.ndarray, plan: RefinePlan,
                       point_weights: np.ndarray | None = None) -> tuple[cKDTree, LocalQuadrics]:
    """(kd-tree of the (N, 3) points in mm, their quadric patches of plan.neighbours points, the
    points weighted by point_weights (N,) if given): what `refine_vertices` projects the vertices
    onto. It depends on the input alone, so the pipeline makes it while the field trains."""
    pts = np.asarray(points_mm, dtype=np.float64)
    tree = cKDTree(pts)
    return tree, fit_local_quadrics(pts, k=plan.neighbours, tree=tree, point_weights=point_weights)


def refine_vertices(vertices_mm: np.ndarray, points_mm: np.ndarray, config: RefineConfig,
                    plan: RefinePlan | None = None, tree: cKDTree | None = None,
                    faces: np.ndarray | None = None, smoothing_time_mm2: float = 0.0,
                    patches: LocalQuadrics | None = None,
                    point_weights: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """(V, 3) mesh vertices and (N, 3) input points, both mm -> ((V, 3) refined vertices in mm, a
    summary for metrics.json). plan: the input's `plan_refinement` (made here when not given); where
    it does not apply the vertices come back unchanged, and the summary says why, except that an
    input too noisy to refine (plan.too_noisy) gets its noise bias removed when the faces are given
    (`curvature_bias.remove_noise_bias` for config.noise_flow_factor; summary "noise_flow"). faces: the
    mesh's (F, 3) triangles; with them (and config.fair_order > 0) the vertices that did not move
    onto the patches are faired between those that did (`fair_vertices`). smoothing_time_mm2: the
    points lie on a smoothed surface (PointCloud.boundary_smoothing_mm2, a label map's); with the
    faces the refined vertices are moved back out by config.smoothing_bias_factor x that
    (`curvature_bias.restore_smoothing_bias`; summary "smoothing_bias"). patches (with `tree`):
    `refinement_patches` of the points under `plan`, made beforehand (made here when not given,
    with the points weighted by point_weights (N,) if given, e.g. `point_weights_of`)."""
    pts = np.asarray(points_mm, dtype=np.float64)
    verts = np.asarray(vertices_mm, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(pts)
    plan = plan if plan is not None else plan_refinement(pts, config, tree)
    if len(verts) == 0:
        return verts, plan.summary()
    if not plan.applies:
        summary = plan.summary()
        if faces is None:
            return verts, summary
        if plan.too_noisy and config.noise_flow_factor > 0:
            # noise the patches cannot average: the offset it puts on a curved fit is taken off
            sigma = normal_noise_mm(plan.patch_residual_mm, plan.neighbours)
            verts, summary["noise_flow"] = remove_noise_bias(verts, faces, sigma, config.noise_flow_factor)
            if config.tube.along_mm > 0:
                # then the noise a narrow isotropic patch cannot average, over patches long along the rib
                verts, summary["tube_patches"] = _onto_tube_patches(verts, faces, pts, config.tube, tree)
        if config.section.along_mm > 0:
            # then over windows that hold the rib's whole cross-section (too noisy or too sparse input)
            verts, summary["section_quadrics"] = _onto_section_quadrics(verts, faces, pts, config.section)
        return verts, summary
    gap = sampling_gap(pts, k=1, tree=tree)  # median nearest-neighbour distance
    patches = patches if patches is not None else fit_local_quadrics(pts, k=plan.neighbours, tree=tree,
                                                                     point_weights=point_weights)
    projected = project_onto_blended_quadrics(verts, patches, tree, blend=config.blend)
    shift = np.linalg.norm(projected - verts, axis=1)
    moved = shift <= config.max_shift_gaps * gap
    out = np.where(moved[:, None], projected, verts)
    n_faired = 0
    if faces is not None and config.fair_order > 0 and not moved.all():
        out, n_faired = fair_vertices(out, faces, ~moved, order=config.fair_order)
    summary = {**plan.summary(), **_moved_summary(shift, moved), "faired_vertices": int(n_faired)}
    section = config.section
    if (faces is not None and smoothing_time_mm2 == 0 and section.along_mm > 0 and section.refined_patch_radius_mm is not None
            and plan.patch_radius_mm > section.refined_patch_radius_mm):
        # a point cloud whose patches had to stretch to hold their points (~20k on a ribcage): a
        # window around the rib's whole cross-section holds several times as many
        out, summary["section_quadrics"] = _onto_section_quadrics(out, faces, pts, section)
    if faces is not None and smoothing_time_mm2 > 0 and config.label_map_tube.along_mm > 0:
        # a label map's: the voxel staircase the round patches leave, averaged along the rib (all
        # boundary points count alike here: that is how benchmarks/label_map_tube_ab.py measured it)
        out, summary["tube_patches"] = _onto_tube_patches(out, faces, pts, config.label_map_tube, tree)
    if faces is not None and smoothing_time_mm2 > 0 and config.smoothing_bias_factor > 0:
        # the patches follow points on a smoothed surface: its inward offset is taken off
        out, summary["smoothing_bias"] = restore_smoothing_bias(out, faces, smoothing_time_mm2, config.smoothing_bias_factor)
    return out, summary


def _onto_tube_patches(vertices_mm: np.ndarray, faces: np.ndarray, points_mm: np.ndarray, config: TubePatchConfig,
                       tree: cKDTree) -> tuple[np.ndarray, dict]:
    """(V, 3) vertices (mm) of a mesh with (F, 3) faces moved onto tube-aligned quadrics of the (N, 3)
    points (mm) (`tube_patches.project_onto_tube_patches` under config), and a summary."""
    import trimesh

    from .tube_patches import project_onto_tube_patches

    normals = trimesh.Trimesh(vertices_mm, faces, process=False).vertex_normals
    out, moved = project_onto_tube_patches(vertices_mm, normals, points_mm, config.along_mm, config.across_mm,
                                           k=config.neighbours, max_move_mm=config.max_move_mm, tree=tree,
                                           max_axis_spread=config.max_axis_spread)
    shift = np.linalg.norm(out - vertices_mm, axis=1)
    return out, {"along_mm": config.along_mm, "across_mm": config.across_mm, **_moved_summary(shift, moved)}


def _onto_section_quadrics(vertices_mm: np.ndarray, faces: np.ndarray, points_mm: np.ndarray,
                           config: SectionQuadricConfig) -> tuple[np.ndarray, dict]:
    """(V, 3) vertices (mm) of a mesh with (F, 3) faces moved onto section quadrics of the (N, 3)
    points (mm) (`section_quadrics.project_onto_section_quadrics` under config), with Taubin
    smoothing before and after each pass, and a summary."""
    import trimesh

    from .section_quadrics import project_onto_section_quadrics

    mesh = trimesh.Trimesh(np.array(vertices_mm, dtype=np.float64), faces, process=False)
    moved = np.zeros(len(mesh.vertices), dtype=bool)
    for _ in range(config.passes):
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=config.smoothing_iterations)
        projected, moved = project_onto_section_quadrics(
            mesh.vertices, mesh.vertex_normals, points_mm, config.along_mm, config.across_mm, config.centre_spacing_mm,
            config.min_points, config.reweightings, config.robust_mm, config.robust_noise_factor, config.max_move_mm)
        mesh = trimesh.Trimesh(projected, faces, process=False)
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=config.smoothing_iterations)
    out = np.asarray(mesh.vertices)
    shift = np.linalg.norm(out - vertices_mm, axis=1)
    return out, {"along_mm": config.along_mm, "across_mm": config.across_mm, "passes": config.passes,
                 **_moved_summary(shift, moved)}


def _moved_summary(shift_mm: np.ndarray, moved: np.ndarray) -> dict:
    """{moved_fraction, mean_shift_mm} for metrics.json: of (V,) vertex shifts (mm), which (V,) moved."""
    return {"moved_fraction": round(float(moved.mean()), 4) if len(moved) else 0.0,
            "mean_shift_mm": round(float(shift_mm[moved].mean()), 4) if moved.any() else 0.0}


def uniform_laplacian(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(F, 3) triangles over n_vertices -> (n, n) graph Laplacian D - A of the mesh's edges (each
    vertex's degree on the diagonal, -1 per neighbour)."""
    f = np.asarray(faces, dtype=np.int64)
    i, j = f.ravel(), f[:, [1, 2, 0]].ravel()  # every half-edge, both ways below
    adjacency = sp.coo_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n_vertices, n_vertices)).tocsr()
    adjacency.data[:] = 1.0  # an edge shared by two faces was summed twice
    return (sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency).tocsr()


def fair_vertices(vertices_mm: np.ndarray, faces: np.ndarray, free: np.ndarray, order: int = 2) -> tuple[np.ndarray, int]:
    """(V, 3) vertices (mm), (F, 3) faces and (V,) bool `free` -> ((V, 3) vertices with the free ones
    faired, how many were). The free vertices solve L^order x = 0 (L: `uniform_laplacian`) with the
    other vertices held where they are: order 1 is a membrane (harmonic) fill, order 2 a thin-plate
    (biharmonic) fill that also continues the surrounding surface's slope. A connected patch of free
    vertices that no held vertex reaches through the stencil (a whole free component) is left as it is."""
    verts = np.asarray(vertices_mm, dtype=np.float64)
    free = np.asarray(free, dtype=bool)
    lap = uniform_laplacian(faces, len(verts))
    idx = np.flatnonzero(free)
    lap_free = lap[idx]
    rows = lap_free if order == 1 else lap_free @ lap  # the stencil's rows at the free vertices only
    n_patches, patch = connected_components(abs(lap_free[:, idx]), directed=False)
    anchored = np.zeros(n_patches, dtype=bool)
    anchored[patch[np.asarray(abs(rows[:, ~free]).sum(axis=1)).ravel() > 0]] = True
    keep = anchored[patch]
    if not keep.any():
        return verts.copy(), 0
    rows = rows[keep]
    try:
        solve = splu(rows[:, idx[keep]].tocsc())
    except RuntimeError:  # a singular stencil (a degenerate, e.g. non-manifold, patch): leave them
        return verts.copy(), 0
    # everything else is held: the fixed vertices, and free ones of unanchored patches where they are
    others = np.setdiff1d(np.arange(len(verts)), idx[keep], assume_unique=True)
    out = verts.copy()
    out[idx[keep]] = solve.solve(-(rows[:, others] @ verts[others]))
    return out, int(keep.sum())
