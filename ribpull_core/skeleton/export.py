"""Skeleton files: skeleton.json, skeleton.glb, skeleton.obj and scene.glb (surface + skeleton).

GLB files hold the skeleton twice: as glTF LINES (mode 1, exact polylines) and as a thin triangle
tube (mode 4) for viewers that ignore line primitives. Coordinates are mm, as everywhere in RibPull
(glTF nominally uses metres; the "units": "mm" metadata and the JSON file say so).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh
from trimesh.path.entities import Line

from ribpull_core.skeleton.curves import rotation_minimizing_frames
from ribpull_core.skeleton.model import Skeleton

SKELETON_RGBA = (220, 40, 40, 255)
SURFACE_RGBA = (225, 215, 190, 160)


def skeleton_polylines(skel: Skeleton) -> list[np.ndarray]:
    """Node-id arrays of the skeleton's polylines: one per curve, plus one 2-node polyline for every
    edge no curve covers (e.g. a branch's junction)."""
    lines = [np.asarray(c.node_ids, dtype=np.int64) for c in skel.curves if len(c.node_ids) >= 2]
    covered = set()
    for ids in lines:
        covered.update(zip(ids[:-1].tolist(), ids[1:].tolist()))
        covered.update(zip(ids[1:].tolist(), ids[:-1].tolist()))
    for a, b in skel.edges.tolist():
        if (a, b) not in covered:
            lines.append(np.array([a, b], dtype=np.int64))
    return lines


def skeleton_path(skel: Skeleton) -> trimesh.path.Path3D:
    """trimesh Path3D of Line entities (one per polyline), vertices in mm."""
    lines = skeleton_polylines(skel)
    entities = [Line(points=ids) for ids in lines]
    path = trimesh.path.Path3D(entities=entities, vertices=skel.nodes_mm.copy(), process=False)
    path.colors = np.tile(np.array(SKELETON_RGBA, dtype=np.uint8), (len(entities), 1))
    path.metadata["units"] = "mm"
    return path


def tube_mesh(polyline_mm: np.ndarray, radius_mm: float = 0.6, sides: int = 8) -> trimesh.Trimesh:
    """Closed triangle tube of `radius_mm` around a polyline (m, 3) mm, with flat end caps."""
    m = len(polyline_mm)
    _, n, b = rotation_minimizing_frames(polyline_mm)
    ang = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(ang)[None, :, None] * n[:, None, :] + np.sin(ang)[None, :, None] * b[:, None, :]
    verts = (polyline_mm[:, None, :] + radius_mm * ring).reshape(-1, 3)
    ids = np.arange(m * sides).reshape(m, sides)
    j, jn = np.arange(sides), (np.arange(sides) + 1) % sides
    a0, a1, b0, b1 = ids[:-1, j], ids[:-1, jn], ids[1:, j], ids[1:, jn]
    faces = np.concatenate([np.stack([a0, a1, b1], -1), np.stack([a0, b1, b0], -1)]).reshape(-1, 3)
    c0, c1 = len(verts), len(verts) + 1
    verts = np.vstack([verts, polyline_mm[:1], polyline_mm[-1:]])
    cap0 = np.column_stack([np.full(sides, c0), ids[0, jn], ids[0, j]])
    cap1 = np.column_stack([np.full(sides, c1), ids[-1, j], ids[-1, jn]])
    return trimesh.Trimesh(verts, np.vstack([faces, cap0, cap1]), process=False)


def skeleton_tubes(skel: Skeleton, radius_mm: float = 0.6, sides: int = 8) -> trimesh.Trimesh:
    """All skeleton polylines as one thin tube mesh (mm), coloured SKELETON_RGBA."""
    parts = []
    for ids in skeleton_polylines(skel):
        pts = skel.nodes_mm[ids]
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
        if keep.sum() >= 2:
            parts.append(tube_mesh(pts[keep], radius_mm, sides))
    mesh = trimesh.util.concatenate(parts) if parts else trimesh.Trimesh()
    if len(mesh.faces):
        mesh.visual.face_colors = np.array(SKELETON_RGBA, dtype=np.uint8)
    return mesh


def skeleton_obj_text(skel: Skeleton) -> str:
    """Wavefront OBJ text: one `v x y z` per node (mm) and one `l i j k ...` per polyline (1-based)."""
    out = ["# RibPull skeleton, units: mm", f"# {len(skel.nodes_mm)} nodes, {len(skel.curves)} curves"]
    out += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in skel.nodes_mm]
    curve_names = [c.label for c in skel.curves]
    for k, ids in enumerate(skeleton_polylines(skel)):
        if k < len(curve_names):
            out.append(f"o {curve_names[k]}")
        out.append("l " + " ".join(str(int(i) + 1) for i in ids))
    return "\n".join(out) + "\n"


def skeleton_scene(skel: Skeleton, mesh_mm: trimesh.Trimesh | None = None, tube_radius_mm: float = 0.6,
                   tubes: trimesh.Trimesh | None = None) -> trimesh.Scene:
    """Scene with the skeleton as lines ("skeleton_lines") and tubes ("skeleton_tubes"), plus the
    surface ("surface") when given. tubes: `skeleton_tubes(skel, tube_radius_mm)` if already built."""
    scene = trimesh.Scene()
    if mesh_mm is not None and len(mesh_mm.faces):
        # a light copy (the arrays, not trimesh's caches); one colour for every vertex is what a
        # uniform face colour becomes in glTF anyway
        surface = trimesh.Trimesh(vertices=np.array(mesh_mm.vertices), faces=np.array(mesh_mm.faces), process=False)
        surface.visual.vertex_colors = np.array(SURFACE_RGBA, dtype=np.uint8)
        scene.add_geometry(surface, geom_name="surface")
    if len(skel.nodes_mm):
        scene.add_geometry(skeleton_path(skel), geom_name="skeleton_lines")
        if tubes is None:
            tubes = skeleton_tubes(skel, tube_radius_mm)
        if len(tubes.faces):
            scene.add_geometry(tubes, geom_name="skeleton_tubes")
    scene.metadata["units"] = "mm"
    return scene


def export_skeleton(
    skel: Skeleton, outdir, mesh_mm: trimesh.Trimesh | None = None, tube_radius_mm: float = 0.6
) -> dict[str, Path]:
    """Write skeleton.json, skeleton.glb, skeleton.obj and (when a surface mesh is given) scene.glb
    to `outdir`; returns {file name: path}."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = {
        "skeleton.json": outdir / "skeleton.json",
        "skeleton.glb": outdir / "skeleton.glb",
        "skeleton.obj": outdir / "skeleton.obj",
    }
    paths["skeleton.json"].write_text(json.dumps(skel.to_json()))
    paths["skeleton.obj"].write_text(skeleton_obj_text(skel))
    tubes = skeleton_tubes(skel, tube_radius_mm) if len(skel.nodes_mm) else None
    paths["skeleton.glb"].write_bytes(skeleton_scene(skel, None, tube_radius_mm, tubes).export(file_type="glb"))
    if mesh_mm is not None:
        paths["scene.glb"] = outdir / "scene.glb"
        paths["scene.glb"].write_bytes(skeleton_scene(skel, mesh_mm, tube_radius_mm, tubes).export(file_type="glb"))
    return paths
