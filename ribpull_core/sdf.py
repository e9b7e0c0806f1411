"""Signed distance in mm from a fitted occupancy field and its mesh (the paper's occupancy -> SDF step).

|SDF| is the distance to the reconstructed surface (the marching-cubes mesh, in mm); the sign comes
from the field (inside_score > level => inside => negative). Volumes are written as NIfTI so they
overlay the input in 3D Slicer; `query_field` answers point queries for the service.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import nibabel as nib
import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from .config import SdfConfig
from .errors import JobCanceled
from .frame import UnitFrame
from .mesh import inside_scores
from .methods.base import FittedField
from .metrics import morton_order
from .pointcloud import PointCloud

#: voxels processed per chunk (bounds memory: ~100 bytes per voxel in flight)
CHUNK = 1 << 20


# --- the grid --------------------------------------------------------------------------------------

def sdf_grid_for(cloud: PointCloud, frame: UnitFrame, config: SdfConfig) -> tuple[tuple[int, int, int], np.ndarray]:
    """The grid of the SDF volume: (shape (3,), affine (4, 4) voxel index -> mm).

    NIfTI inputs (cloud.nifti_affine set): the input volume's own grid, so the SDF overlays it; if
    config.voxel_mm is set, or the grid has more than config.max_voxels voxels, every s-th voxel
    along each axis is kept (integer stride s, the kept voxel centres are input voxel centres).
    Other inputs: an axis-aligned grid over the input bounding box ± config.padding_mm, spacing
    config.voxel_mm (default: longest side of the unpadded box / 128, the frame's 2·half_extent_mm),
    coarsened until the grid has at most config.max_voxels voxels.
    """
    max_vox = int(config.max_voxels)
    if cloud.nifti_affine is not None and cloud.nifti_shape is not None:
        aff = np.asarray(cloud.nifti_affine, dtype=np.float64)
        shape = np.asarray(cloud.nifti_shape[:3], dtype=np.int64)
        spacing = np.linalg.norm(aff[:3, :3], axis=0)
        stride = 1
        if config.voxel_mm:
            stride = max(1, round(float(config.voxel_mm) / float(spacing.min())))
        while np.prod(-(-shape // stride)) > max_vox:
            stride += 1
        new_shape = tuple(int(n) for n in -(-shape // stride))
        new_aff = aff.copy()
        new_aff[:3, :3] = aff[:3, :3] * stride
        return new_shape, new_aff
    lo, hi = cloud.bbox_mm
    lo = lo - config.padding_mm
    hi = hi + config.padding_mm
    ext = hi - lo
    spacing = float(config.voxel_mm) if config.voxel_mm else 2.0 * frame.half_extent_mm / 128.0
    if not spacing > 0:
        raise ValueError(f"SDF voxel size must be positive, got {spacing}")
    shape = np.ceil(ext / spacing).astype(np.int64) + 1
    while np.prod(shape) > max_vox:
        spacing *= (np.prod(shape) / max_vox) ** (1 / 3) * 1.001
        shape = np.ceil(ext / spacing).astype(np.int64) + 1
    aff = np.eye(4)
    aff[:3, :3] *= spacing
    aff[:3, 3] = lo
    return tuple(int(n) for n in shape), aff


def voxel_centers_mm(shape: tuple[int, int, int], affine: np.ndarray, start: int = 0, stop: int | None = None) -> np.ndarray:
    """(M, 3) mm coordinates of flat (C-order) voxel indices start..stop of a grid."""
    stop = int(np.prod(shape)) if stop is None else stop
    ijk = np.stack(np.unravel_index(np.arange(start, stop), shape), -1).astype(np.float64)
    return ijk @ affine[:3, :3].T + affine[:3, 3]


# --- unsigned distance to a mesh ---------------------------------------------------------------------

class SurfaceDistance:
    """Fast unsigned distance (mm) from any points to a triangle mesh in mm.

    A kd-tree over dense surface samples is fast only close to the surface: at points roughly
    equidistant from much of it (the centre of the thorax, anything far away) a nearest-neighbour
    search visits most of the samples. So:
    - a closest-point grid (spacing `grid_mm`, default longest side of the mesh box / 128, covering
      the mesh box ± `margin` × its longest side and `cover_mm` if given) stores, at nodes near the
      surface, the exact closest point on the triangle of the node's nearest sample; the other nodes
      take the closest point of the nearest near node (EDT feature transform), improved by two
      relaxation sweeps over the 6 axis neighbours;
    - a point inside the grid gets the smallest distance to the stored closest points of its cell's
      8 nodes; within 3 cells of the surface also the exact distance to the triangle of its nearest
      sample (kd-tree, fast there); outside the grid, a kd-tree over 8192 samples (slow-case proof)
      refined by the triangle of the sample found.

    Accuracy: always an upper bound of the true distance (a distance to a point on the mesh). Near
    the surface exact unless the nearest sample is not on the closest triangle (error then below the
    sample spacing sqrt(area / n_samples)); farther out the closest-point propagation errs by a
    fraction of a grid cell, more where two parts of the surface are almost equally near (up to ~2%
    of the distance). Measured, 1M samples: 75 mm sphere, grid 1.17 mm, points in ±110 mm: mean
    0.03 mm, max 0.43 mm (within 3 mm of the surface: mean 0.004 mm, max 0.23 mm); 12 thin tori
    ("ribs", tube radius 5 mm), grid 1.8 mm, points in ±160 mm: mean 0.1 mm, max 1.1 mm (at 56 mm).
    Build once (seconds), call many times.
    """

    relax_sweeps = 2
    relax_offsets = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))

    def __init__(
        self,
        mesh_mm: trimesh.Trimesh,
        n_samples: int = 1_000_000,
        seed: int = 0,
        grid_mm: float | None = None,
        cover_mm: tuple[np.ndarray, np.ndarray] | None = None,
        max_nodes: int = 8_000_000,
        margin: float = 0.1,
    ):
        if len(mesh_mm.faces) == 0:
            raise ValueError("cannot measure distances to an empty mesh")
        pts, fidx = trimesh.sample.sample_surface(mesh_mm, int(n_samples), seed=seed)
        faces = np.asarray(mesh_mm.faces)
        vface = np.empty(len(mesh_mm.vertices), dtype=np.int64)
        for j in range(3):
            vface[faces[:, j]] = np.arange(len(faces))
        used = np.zeros(len(mesh_mm.vertices), dtype=bool)
        used[faces.ravel()] = True
        self.points = np.concatenate([np.asarray(pts, dtype=np.float64), mesh_mm.vertices[used]])
        self.face_of = np.concatenate([np.asarray(fidx, dtype=np.int64), vface[used]])
        o = morton_order(self.points)  # spatially sorted: much faster kd-tree
        self.points, self.face_of = self.points[o], self.face_of[o]
        self.triangles = np.asarray(mesh_mm.triangles, dtype=np.float64)
        self.tree = cKDTree(self.points)
        sub = np.random.default_rng(seed).choice(len(self.points), min(8192, len(self.points)), replace=False)
        self.coarse_index = sub
        self.coarse_tree = cKDTree(self.points[sub])
        self.spacing_mm = math.sqrt(float(mesh_mm.area) / max(1, len(self.points)))
        self.bounds_mm = np.asarray(mesh_mm.bounds, dtype=np.float64)
        ext = float((self.bounds_mm[1] - self.bounds_mm[0]).max())
        lo = self.bounds_mm[0] - margin * ext
        hi = self.bounds_mm[1] + margin * ext
        if cover_mm is not None:
            lo = np.minimum(lo, np.asarray(cover_mm[0], dtype=np.float64))
            hi = np.maximum(hi, np.asarray(cover_mm[1], dtype=np.float64))
        g = float(grid_mm) if grid_mm else max(ext / 128.0, 1e-6)
        while np.prod(np.ceil((hi - lo) / g) + 1) > max_nodes:
            g *= 1.1
        self.grid_mm = g
        self.origin = lo
        self.nodes = np.ceil((hi - lo) / g).astype(np.int64) + 1
        self._build_grid()

    def _nearest_surface_point(self, p: np.ndarray) -> np.ndarray:
        """(M, 3) mm near the surface -> (M, 3) closest point on the triangle of the nearest sample."""
        _, i = self.tree.query(p, k=1, workers=-1)
        return trimesh.triangles.closest_point(self.triangles[self.face_of[i]], p)

    def _build_grid(self) -> None:
        shape = tuple(int(n) for n in self.nodes)
        near = np.zeros(shape, dtype=bool)
        c = np.floor((self.points - self.origin) / self.grid_mm).astype(np.int64)
        c = np.clip(c, 0, self.nodes - 2)
        for off in np.ndindex(2, 2, 2):
            near[c[:, 0] + off[0], c[:, 1] + off[1], c[:, 2] + off[2]] = True
        near = ndimage.binary_dilation(near, structure=ndimage.generate_binary_structure(3, 3))
        idx = np.argwhere(near)
        cp = np.zeros(shape + (3,), dtype=np.float32)
        for s in range(0, len(idx), CHUNK):
            ii = idx[s : s + CHUNK]
            cp[ii[:, 0], ii[:, 1], ii[:, 2]] = self._nearest_surface_point(self.origin + ii * self.grid_mm)
        ind = ndimage.distance_transform_edt(~near, return_distances=False, return_indices=True)
        cp = cp[ind[0], ind[1], ind[2]]
        del ind
        axes = [self.origin[k] + np.arange(shape[k]) * self.grid_mm for k in range(3)]
        node = np.stack(np.meshgrid(*axes, indexing="ij"), -1).astype(np.float32)
        best = ((node - cp) ** 2).sum(-1)
        for _ in range(self.relax_sweeps):  # a neighbour's closest point may be closer: take it
            for o in self.relax_offsets:
                dst = tuple(slice(max(0, -k), n - max(0, k)) for k, n in zip(o, shape))
                src = tuple(slice(max(0, k), n - max(0, -k)) for k, n in zip(o, shape))
                cand = cp[src]
                dc = ((node[dst] - cand) ** 2).sum(-1)
                better = dc < best[dst]
                best[dst][better] = dc[better]
                cp[dst][better] = cand[better]
        self.cp_grid = cp

    def __call__(self, points_mm: np.ndarray) -> np.ndarray:
        """(N, 3) mm -> (N,) float64 unsigned distance in mm."""
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(p))
        step = CHUNK // 4
        for s in range(0, len(p), step):
            out[s : s + step] = self._distance(p[s : s + step])
        return out

    def _distance(self, p: np.ndarray) -> np.ndarray:
        f = (p - self.origin) / self.grid_mm
        ingrid = np.all((f >= 0) & (f <= self.nodes - 1), axis=1)
        c = np.clip(np.floor(f).astype(np.int64), 0, self.nodes - 2)
        d = np.full(len(p), np.inf)
        for off in np.ndindex(2, 2, 2):
            cp = self.cp_grid[c[:, 0] + off[0], c[:, 1] + off[1], c[:, 2] + off[2]]
            np.minimum(d, np.linalg.norm(p - cp, axis=1), out=d)
        near = np.flatnonzero(ingrid & (d < 3.0 * self.grid_mm))
        if len(near):
            cp = self._nearest_surface_point(p[near])
            d[near] = np.minimum(d[near], np.linalg.norm(p[near] - cp, axis=1))
        far = np.flatnonzero(~ingrid)
        if len(far):
            _, i = self.coarse_tree.query(p[far], k=1, workers=-1)
            tri = self.triangles[self.face_of[self.coarse_index[i]]]
            cp = trimesh.triangles.closest_point(tri, p[far])
            d[far] = np.minimum(d[far], np.linalg.norm(p[far] - cp, axis=1))
        return d

    def outside_bounds(self, points_mm: np.ndarray) -> np.ndarray:
        """(N,) bool: outside the mesh's bounding box (so outside the closed mesh)."""
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        return np.any(p < self.bounds_mm[0], axis=1) | np.any(p > self.bounds_mm[1], axis=1)


# --- signed distance ---------------------------------------------------------------------------------

def signed_distance_volume(
    mesh_mm: trimesh.Trimesh,
    field: FittedField,
    frame: UnitFrame,
    shape: tuple[int, int, int],
    affine: np.ndarray,
    n_samples: int = 1_000_000,
    votes: int = 16,
    seed: int = 0,
    grid_mm: float | None = None,
    should_cancel: Callable[[], bool] | None = None,
) -> np.ndarray:
    """(shape) float32 signed distance in mm at the voxel centres (affine: voxel -> mm), negative inside.

    |value| = `SurfaceDistance` to mesh_mm (see its accuracy; its closest-point grid has spacing
    grid_mm, default the smallest voxel spacing but at least the mesh's longest side / 256, and
    covers the volume). Sign: inside_score > field.level.
    The network is only queried where it matters: voxels within 1.5 voxel diagonals of the surface
    get the field's own sign; the other voxels form connected regions (6-connectivity) that cannot
    cross the surface, and each takes the majority sign of the field at up to `votes` random voxels
    of it. Voxels outside the mesh's bounding box are outside (the mesh is closed at its meshing
    box, and a field is not trusted outside the box it was meshed in). should_cancel() is checked
    between chunks of work (raises JobCanceled).
    """
    shape = tuple(int(n) for n in shape)
    n = int(np.prod(shape))
    corners = np.array(list(np.ndindex(2, 2, 2)), dtype=np.float64) * (np.array(shape) - 1)
    corners = corners @ affine[:3, :3].T + affine[:3, 3]
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    if grid_mm is None:
        grid_mm = max(float(spacing.min()), float((mesh_mm.bounds[1] - mesh_mm.bounds[0]).max()) / 256.0)
    dist = SurfaceDistance(
        mesh_mm, n_samples=n_samples, seed=seed, grid_mm=grid_mm, margin=0.0,
        cover_mm=(corners.min(0), corners.max(0)),
    )
    band = 1.5 * float(np.linalg.norm(spacing))
    absd = np.empty(n, dtype=np.float32)
    outbox = np.empty(n, dtype=bool)
    for s in range(0, n, CHUNK):
        if should_cancel is not None and should_cancel():
            raise JobCanceled("canceled")
        p = voxel_centers_mm(shape, affine, s, min(n, s + CHUNK))
        absd[s : s + len(p)] = dist(p)
        outbox[s : s + len(p)] = dist.outside_bounds(p)
    inside = np.zeros(n, dtype=bool)
    level = float(field.level)

    def field_inside(flat_idx: np.ndarray) -> np.ndarray:
        out = np.empty(len(flat_idx), dtype=bool)
        for s in range(0, len(flat_idx), CHUNK):
            ijk = np.stack(np.unravel_index(flat_idx[s : s + CHUNK], shape), -1).astype(np.float64)
            p = ijk @ affine[:3, :3].T + affine[:3, 3]  # voxel centres, mm
            out[s : s + len(p)] = inside_scores(field, frame.to_unit(p), should_cancel=should_cancel) > level
        return out

    near = np.flatnonzero((absd <= band) & ~outbox)
    inside[near] = field_inside(near)

    far = (absd > band).reshape(shape)
    labels, n_lab = ndimage.label(far)
    if n_lab:
        flat = labels.ravel()
        decided = np.zeros(n_lab + 1, dtype=bool)
        decided[np.unique(flat[outbox & (flat > 0)])] = True  # touches outside the box: outside
        decided[0] = True
        cand = np.flatnonzero(~decided[flat])
        if len(cand):
            rng = np.random.default_rng(seed)
            cand = cand[rng.permutation(len(cand))]
            lab = flat[cand]
            order = np.argsort(lab, kind="stable")
            cand, lab = cand[order], lab[order]
            first = np.searchsorted(lab, lab, side="left")
            pick = (np.arange(len(lab)) - first) < votes
            vi = field_inside(cand[pick])
            n_in = np.bincount(lab[pick], weights=vi, minlength=n_lab + 1)
            n_all = np.bincount(lab[pick], minlength=n_lab + 1)
            comp_inside = n_in * 2 > n_all
            sel = ~decided[flat]
            inside[sel] = comp_inside[flat[sel]]
    sdf = np.where(inside, -absd, absd).astype(np.float32)
    return sdf.reshape(shape)


def write_nifti(path: str | Path, volume: np.ndarray, affine: np.ndarray) -> Path:
    """Write a float32 volume (mm values) as NIfTI-1 with qform = sform = affine (scanner, mm)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    aff = np.asarray(affine, dtype=np.float64)
    img = nib.Nifti1Image(np.asarray(volume, dtype=np.float32), aff)
    img.header.set_xyzt_units(xyz="mm")
    img.set_qform(aff, code=1)
    img.set_sform(aff, code=1)
    nib.save(img, str(path))
    return path


# --- point queries -----------------------------------------------------------------------------------

def query_field(
    field: FittedField,
    frame: UnitFrame,
    points_mm: np.ndarray,
    mesh_mm: trimesh.Trimesh | SurfaceDistance | None = None,
) -> dict[str, np.ndarray]:
    """Evaluate the field at (N, 3) mm points.

    Returns "occupancy" (N,) probability of being inside, "U" (N,) margin uncertainty p_in - p_out,
    "inside" (N,) bool (inside_score > level) and, when mesh_mm (a mesh in mm, or a prebuilt
    `SurfaceDistance` to reuse across calls) is given, "sdf_mm" (N,) signed distance in mm (negative
    inside; sign from the field, but outside the mesh's bounding box always positive, as in
    `signed_distance_volume`).
    """
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    ev = field.evaluate(frame.to_unit(p))
    out = {
        "occupancy": ev["occupancy"],
        "U": ev["U"],
        "inside": ev["inside_score"] > float(field.level),
    }
    if mesh_mm is not None:
        if isinstance(mesh_mm, SurfaceDistance):
            dist = mesh_mm
        else:  # a light one; build a SurfaceDistance once and pass it when querying repeatedly
            ext = float((mesh_mm.bounds[1] - mesh_mm.bounds[0]).max())
            dist = SurfaceDistance(mesh_mm, n_samples=200_000, grid_mm=max(ext / 64.0, 1e-6))
        d = dist(p)
        neg = out["inside"] & ~dist.outside_bounds(p)
        out["sdf_mm"] = np.where(neg, -d, d)
    return out
