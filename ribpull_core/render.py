"""preview.png: the mesh and the skeleton from the front and the side (matplotlib Agg, no display).

Views assume the input's frame is patient RAS (x left->right, y posterior->anterior, z up), which is
how nibabel reads NIfTI inputs; for other inputs they are simply the +y and +x views with z up.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

MAX_FACES = 60_000
MESH_RGB = np.array([0.86, 0.82, 0.74])  # bone
SKELETON_RGB = (0.85, 0.1, 0.1)
#: (title, elevation, azimuth) of the two views: anterior (camera on +y, the front in RAS) and lateral (+x)
VIEWS = (("anterior", 0.0, 90.0), ("lateral", 0.0, 0.0))


def _row_keys(rows: np.ndarray) -> np.ndarray:
    """(n, 3) non-negative ints -> (n,) int64 keys in the rows' lexicographic order."""
    span = rows.max(0).astype(np.int64) + 1 if len(rows) else np.ones(3, dtype=np.int64)
    return (rows[:, 0] * span[1] + rows[:, 1]) * span[2] + rows[:, 2]


def _unique_inverse(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inverse (n,), first index of each unique key (u,)), unique keys in sorted order: what
    np.unique(..., return_index=True, return_inverse=True) gives, by one stable argsort (much faster
    than np.unique on rows)."""
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    new = np.r_[True, sk[1:] != sk[:-1]] if len(sk) else np.zeros(0, dtype=bool)
    inv = np.empty(len(keys), dtype=np.int64)
    inv[order] = np.cumsum(new) - 1
    return inv, order[new]


def cluster_decimate(vertices: np.ndarray, faces: np.ndarray, max_faces: int = MAX_FACES) -> tuple[np.ndarray, np.ndarray]:
    """Vertex-clustering decimation: (V, 3), (F, 3) -> at most ~max_faces faces (same units).

    Vertices are merged per cubic cell (cell size from the area per wanted face), faces that collapse
    are dropped. Crude but fast and shape-preserving at preview scale.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) <= max_faces:
        return vertices, faces
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    cell = math.sqrt(2.0 * area / max_faces) if area > 0 else 1.0
    v, f = vertices, faces
    for _ in range(8):
        key = np.floor((vertices - vertices.min(0)) / cell).astype(np.int64)
        inv, _ = _unique_inverse(_row_keys(key))  # cell number per vertex, cells in lexicographic order
        fc = inv[faces]
        fc = fc[(fc[:, 0] != fc[:, 1]) & (fc[:, 1] != fc[:, 2]) & (fc[:, 0] != fc[:, 2])]
        _, first = _unique_inverse(_row_keys(np.sort(fc, axis=1)))
        f = fc[np.sort(first)]  # keep each face's winding
        n_new = int(inv.max()) + 1
        v = np.zeros((n_new, 3))
        np.add.at(v, inv, vertices)
        v /= np.bincount(inv, minlength=n_new)[:, None]
        if len(f) <= max_faces:
            break
        cell *= math.sqrt(len(f) / max_faces) * 1.05
    return v, f


def _shade(normals: np.ndarray, view_dir: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """(F, 3) unit normals -> (F, 3) colours: ambient + two-sided Lambert from the camera side."""
    lam = np.abs(normals @ view_dir)
    return np.clip(rgb[None, :] * (0.35 + 0.65 * lam[:, None]), 0, 1)


def render_preview(
    path,
    mesh_mm: trimesh.Trimesh | None,
    polylines_mm: list[np.ndarray] | None = None,
    title: str = "",
) -> Path:
    """Write a 1200×600 px PNG with anterior and lateral orthographic views; returns the path.

    mesh_mm: the surface (mm), decimated to <= MAX_FACES faces for drawing (semi-transparent when a
    skeleton is drawn too). polylines_mm: skeleton curves, each (K, 3) mm, drawn on top in red.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    polylines = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in (polylines_mm or []) if len(p) >= 2]
    pts = []
    v = f = fn = None
    if mesh_mm is not None and len(mesh_mm.faces):
        v, f = cluster_decimate(mesh_mm.vertices, mesh_mm.faces)
        tri = v[f]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
        pts.append(v)
    pts.extend(polylines)

    fig = Figure(figsize=(12, 6), dpi=100)
    FigureCanvasAgg(fig)
    if title:
        fig.suptitle(title, fontsize=12)
    if pts:
        allp = np.concatenate(pts)
        lo, hi = allp.min(0), allp.max(0)
        centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6) * 1.02
    for k, (name, elev, azim) in enumerate(VIEWS):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d", computed_zorder=False)
        ax.set_proj_type("ortho")
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(name)
        if not pts:
            ax.text2D(0.5, 0.5, "nothing to show", transform=ax.transAxes, ha="center")
            continue
        if f is not None:
            e, a = math.radians(elev), math.radians(azim)
            view_dir = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
            alpha = 0.55 if polylines else 1.0
            coll = Poly3DCollection(tri, facecolors=_shade(fn, view_dir, MESH_RGB), edgecolors="none",
                                    linewidths=0, alpha=alpha, zorder=1)
            ax.add_collection3d(coll)
        if polylines:
            segs = np.concatenate([np.stack([p[:-1], p[1:]], 1) for p in polylines])
            ax.add_collection3d(Line3DCollection(segs, colors=[SKELETON_RGB], linewidths=1.6, zorder=2))
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1, 1, 1), zoom=1.3)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.93, wspace=0)
    fig.savefig(path, dpi=100, facecolor="white")
    return path
