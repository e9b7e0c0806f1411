"""`skeletonize`: surface points (mm) -> one medial curve per rib (the skeleton stage's entry point).

Steps: validate -> split into connected clusters (per input label when labels are given) ->
Laplacian contraction of each cluster (paper eq. 3-4) -> ball sampling, tree, longest path ->
refinement on the original points (ellipse recentring, smoothing, end caps) -> radius, length,
curvature -> names (input labels, else geometry) -> `Skeleton`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ribpull_core.errors import RibPullInputError
from ribpull_core.quadrics import pca_normals
from ribpull_core.skeleton import curves as cv
from ribpull_core.skeleton.components import auto_link_mm, find_components, validate_points
from ribpull_core.skeleton.contraction import laplacian_contraction
from ribpull_core.skeleton.labels import geometric_labels, label_name, majority_label, orient_head_first
from ribpull_core.skeleton.model import RibCurve, Skeleton, SkeletonConfig

DistanceFn = Callable[[np.ndarray], np.ndarray]
Progress = Callable[[float, str], None]


def surface_distance_fn(points_mm: np.ndarray, normals: np.ndarray | None = None, k: int = 8) -> DistanceFn:
    """Distance (mm) from query points to the surface the samples `points_mm` lie on.

    Returns f(q (Q, 3)) -> (Q,): the mean of the 3 smallest distances from q to the tangent planes
    of its k nearest samples (normals given or PCA-estimated), capped by the nearest-sample
    distance. For a point inside a convex section every plane distance bounds the true distance
    from above and the smallest ones are accurate even where samples are a few mm apart (phantom,
    20k points: bias +0.01 mm); sample noise of std s biases it low by about 0.7 s.
    """
    tree = cKDTree(points_mm)
    nrm = pca_normals(points_mm, k=10) if normals is None else normals
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    kk = int(min(k, len(points_mm)))

    def f(q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64).reshape(-1, 3)
        d, idx = tree.query(q, k=kk)
        d = d.reshape(len(q), -1)
        idx = idx.reshape(len(q), -1)
        plane = np.sort(np.abs(np.einsum("qkj,qkj->qk", q[:, None, :] - points_mm[idx], nrm[idx])), axis=1)
        return np.minimum(d[:, 0], plane[:, : min(3, kk)].mean(axis=1))

    return f


def refine_curve(
    poly_mm: np.ndarray,
    surface_mm: np.ndarray,
    config: SkeletonConfig,
    extend: tuple[bool, bool] = (True, True),
    dist_fn: DistanceFn | None = None,
    area_mm2: np.ndarray | None = None,
) -> np.ndarray:
    """Contracted path (m, 3) -> medial polyline at config.step_mm on the surface points (N, 3).

    Alternates end adjustment (ray to the cap, back off by the local radius: the fitted sections'
    minor semi-axis near the end, else dist_fn) and ellipse recentring (curves.recentre_polyline;
    area_mm2 (N,) weights its centroid fallback), with Gaussian smoothing in between.
    """
    step = config.step_mm
    poly = cv.resample_polyline(poly_mm, step)
    poly = cv.smooth_polyline(poly, config.path_smooth_sigma_mm, step)
    minor = np.full(len(poly), np.nan)
    major = np.full(len(poly), np.nan)
    major_dir = np.zeros((len(poly), 3))

    def end_sections(poly, minor, major, major_dir):
        """Per end: (minor radius, major semi-axis, major direction) from the fitted sections 1-8 mm
        from that end, else the distance function."""
        out = []
        for sl in (slice(0, None), slice(None, None, -1)):
            p, mn, mj, md = poly[sl], minor[sl], major[sl], major_dir[sl]
            s = cv.arc_length(p)
            near = (s > 1.0) & (s < 8.0) & np.isfinite(mn)
            if near.any():
                k = np.flatnonzero(near)[np.argsort(mn[near])[len(mn[near]) // 2]]  # median node
                out.append((float(mn[k]), float(mj[k]), md[k]))
                continue
            band = (s > 1.0) & (s < 8.0)
            if dist_fn is not None:
                r = float(np.median(dist_fn(p[band]))) if band.any() else float(dist_fn(p[:1])[0])
            else:
                r = 3.0
            out.append((r, None, None))
        return out

    def ends(poly, minor, major, major_dir):
        (r0, a0, d0), (r1, a1, d1) = end_sections(poly, minor, major, major_dir)
        return cv.adjust_ends(poly, surface_mm, r0, r1, step, extend=extend, sections=((a0, d0), (a1, d1)))

    for _ in range(max(1, config.recentre_iterations)):
        if config.extend_ends:
            poly = ends(poly, minor, major, major_dir)
        poly, minor, major, major_dir = cv.recentre_polyline(
            poly, surface_mm, step, config.recentre_sigma_mm, area_mm2
        )
        poly = cv.smooth_polyline(poly, config.smooth_sigma_mm, step)
    if config.extend_ends:
        poly = ends(poly, minor, major, major_dir)
    return cv.resample_polyline(poly, step)


def _end_tangent(poly_mm: np.ndarray, at_end: bool, length_mm: float = 10.0) -> np.ndarray:
    """Outward unit tangent of a polyline at its last (at_end) or first node, over length_mm."""
    p = poly_mm if at_end else poly_mm[::-1]
    s = cv.arc_length(p[::-1])
    k = int(np.clip(np.searchsorted(s, length_mm), 1, len(p) - 1))
    t = p[-1] - p[-1 - k]
    return t / max(np.linalg.norm(t), 1e-12)


def merge_split_curves(
    raw: list[dict], points_mm: np.ndarray, config: SkeletonConfig, dist_fn: DistanceFn | None,
    area_mm2: np.ndarray | None = None,
) -> tuple[list[dict], int]:
    """Join main curves that are one rib split by a sampling gap; returns (curves, number of joins).

    Two curves (same label or both unlabelled) are joined when an end of one is within
    config.merge_gap_mm of an end of the other, both end tangents point at the other end (within
    config.merge_angle_deg) and they face each other. Closest pairs first; the joined polyline is
    refined again on the union of both curves' points.
    """
    cos_max = np.cos(np.deg2rad(config.merge_angle_deg))
    n_joins = 0
    while True:
        mains = [i for i, r in enumerate(raw) if not r["branch"]]
        best = None
        for ii, i in enumerate(mains):
            for j in mains[ii + 1:]:
                a, b = raw[i], raw[j]
                if a["label_id"] != b["label_id"]:
                    continue
                for ea in (False, True):
                    for eb in (False, True):
                        pa = a["poly"][-1] if ea else a["poly"][0]
                        pb = b["poly"][-1] if eb else b["poly"][0]
                        gap = pb - pa
                        d = float(np.linalg.norm(gap))
                        if d > config.merge_gap_mm or (best is not None and d >= best[0]):
                            continue
                        ta, tb = _end_tangent(a["poly"], ea), _end_tangent(b["poly"], eb)
                        u = gap / max(d, 1e-9)
                        facing = -(ta @ tb) >= cos_max
                        aimed = d < 1.0 or ((ta @ u) >= cos_max and (-(tb @ u)) >= cos_max)
                        if facing and aimed:
                            best = (d, i, j, ea, eb)
        if best is None:
            return raw, n_joins
        _, i, j, ea, eb = best
        a, b = raw[i], raw[j]
        pa = a["poly"] if ea else a["poly"][::-1]
        pb = b["poly"][::-1] if eb else b["poly"]
        idx = np.concatenate([a["idx"], b["idx"]])
        poly = refine_curve(np.vstack([pa, pb]), points_mm[idx], config, (True, True), dist_fn,
                            None if area_mm2 is None else area_mm2[idx])
        merged = {"poly": poly, "idx": idx, "label_id": a["label_id"], "component": a["component"],
                  "branch": False}
        for r in raw:  # branches of b now hang off the merged curve
            if r["component"] == b["component"]:
                r["component"] = a["component"]
        raw = [r for k, r in enumerate(raw) if k not in (i, j)] + [merged]
        n_joins += 1


def _name_key(name: str) -> tuple:
    """Sort key: rib names "L1".."L12", "R1".."R12" in anatomical order, then anything else."""
    if len(name) >= 2 and name[0] in "LR" and name[1:].isdigit():
        return (0, name[0], int(name[1:]), "")
    return (1, "", 0, name)


def _check_optional(points: np.ndarray, normals, point_labels):
    n = len(points)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != (n, 3):
            raise RibPullInputError("bad_parameter", f"normals must have shape ({n}, 3); got {normals.shape}")
        if not np.isfinite(normals).all():
            normals = None  # unusable; estimated instead
    if point_labels is not None:
        point_labels = np.asarray(point_labels)
        if point_labels.shape != (n,):
            raise RibPullInputError(
                "bad_parameter", f"point_labels must have shape ({n},); got {point_labels.shape}"
            )
        point_labels = point_labels.astype(np.int64)
    return normals, point_labels


def skeletonize(
    points_mm: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    point_labels: np.ndarray | None = None,
    label_names: dict[int, str] | None = None,
    distance_to_surface_mm: DistanceFn | None = None,
    config: SkeletonConfig | None = None,
    progress: Progress | None = None,
) -> Skeleton:
    """Medial curves of the ribs sampled by `points_mm` (N, 3) surface points in mm.

    normals: (N, 3) optional, only used for the radius estimate. point_labels: (N,) int label per
    point (e.g. TotalSegmentator 92..115); clusters never mix labels and each curve takes the
    majority label of its points, named through `label_names` (98 -> "rib_left_7" -> "L7"; without
    names TotalSegmentator's numbering is assumed for 92..115). Without labels, curves are named from
    geometry (see labels.geometric_labels). distance_to_surface_mm: f((Q, 3) mm) -> (Q,) mm, e.g.
    |SDF|; default: from the points (surface_distance_fn). progress(fraction, message).
    Raises RibPullInputError for unusable input (too few points, non-finite, on a line/plane).
    """
    cfg = config or SkeletonConfig()
    t0 = time.perf_counter()
    say = progress or (lambda f, m: None)
    pts = validate_points(points_mm, cfg.min_points)
    normals, point_labels = _check_optional(pts, normals, point_labels)
    # exact duplicates make the local Delaunay of the Laplacian degenerate
    _, first = np.unique(pts, axis=0, return_index=True)
    if len(first) < len(pts):
        first = np.sort(first)
        pts = pts[first]
        normals = None if normals is None else normals[first]
        point_labels = None if point_labels is None else point_labels[first]
    say(0.02, "clustering")
    # with labels, clusters never mix labels, so the link may exceed the gap between ribs
    cap = cfg.link_max_mm * (3.0 if point_labels is not None else 1.0)
    link = cfg.link_mm or auto_link_mm(pts, cfg.link_factor, cap)
    comp = find_components(pts, link, point_labels, cfg.min_component_points)
    dropped = float((comp < 0).mean())
    if dropped > cfg.max_dropped_fraction:
        raise RibPullInputError(
            "too_few_points",
            f"the points are too sparse to separate the ribs: {100 * dropped:.0f}% of them fall in clusters "
            f"of fewer than {cfg.min_component_points} points linked closer than {link:.1f} mm. "
            "Give a denser cloud (about 20,000 points for an adult ribcage) or per-point rib labels",
        )
    t_cluster = time.perf_counter()
    say(0.05, f"contracting {comp.max() + 1} clusters")
    contracted, cinfo = laplacian_contraction(pts, cfg, components=comp)
    t_contract = time.perf_counter()
    say(0.6, "extracting curves")
    dist_fn = distance_to_surface_mm or surface_distance_fn(pts, normals, cfg.radius_k)
    mid_x = float(np.median(pts[:, 0]))
    area = np.ones(len(pts))  # lumped area per point (mm^2) from each cluster's first Laplacian
    for ci, c_info in zip(cinfo["component_ids"], cinfo["components"]):
        area[comp == ci] = c_info["area_mm2"]

    raw = []  # dicts: poly (m, 3), idx (point indices), label_id, component, branch
    for ci in cinfo["component_ids"]:
        members = np.flatnonzero(comp == ci)
        p_c, q_c = pts[members], contracted[members]
        _, nbr = cKDTree(p_c).query(p_c, k=min(9, len(p_c)))
        polys, _, _ = cv.contracted_paths(
            q_c, nbr[:, 1:], cfg.sample_radius_mm, cfg.prune_length_mm, cfg.branch_clearance_mm
        )
        if not polys:
            continue
        if len(polys) > 1:  # points go to the path nearest to their contracted position
            dense = [cv.resample_polyline(p, 0.5) for p in polys]
            owner = np.concatenate([np.full(len(d), i) for i, d in enumerate(dense)])
            _, j = cKDTree(np.vstack(dense)).query(q_c)
            point_owner = owner[j]
        else:
            point_owner = np.zeros(len(p_c), dtype=np.int64)
        for k, poly in enumerate(polys):
            mine = point_owner == k
            if mine.sum() < 10:
                continue
            extend = (True, True) if k == 0 else (False, True)
            refined = refine_curve(poly, p_c[mine], cfg, extend, dist_fn, area[members[mine]])
            lid = majority_label(point_labels[members[mine]])[0] if point_labels is not None else None
            raw.append({"poly": refined, "idx": members[mine], "label_id": lid, "component": ci,
                        "branch": k > 0})
    n_merged = 0
    if cfg.merge_gap_mm > 0:
        raw, n_merged = merge_split_curves(raw, pts, cfg, dist_fn, area)
    say(0.9, "measuring curves")
    raw = [r for r in raw if cv.arc_length(r["poly"])[-1] >= cfg.min_curve_length_mm]
    raw = [(r["poly"], r["label_id"], r["component"], r["branch"]) for r in raw]

    polys = []
    for poly, lid, ci, branch in raw:
        if not branch and orient_head_first(poly, mid_x):
            poly = poly[::-1].copy()
        polys.append(poly)
    if point_labels is None:
        names = geometric_labels([p for p, r in zip(polys, raw) if not r[3]], mid_x, cfg.left_is_positive_x)
        it = iter(names)
        names = [next(it) if not r[3] else None for r in raw]
        # branches take their main curve's name with a suffix
        main_name = {r[2]: n for r, n in zip(raw, names) if n is not None}
        names = [n if n is not None else f"{main_name.get(r[2], 'branch')}_branch" for r, n in zip(raw, names)]
    else:
        names = [label_name(r[1], label_names) if r[1] is not None else "unlabelled" for r in raw]

    # output order: main curves L1..L12, R1..R12 (then other names), branches after all mains
    order = sorted(range(len(raw)), key=lambda k: (raw[k][3], _name_key(names[k])))
    nodes, edges, radius, curves_out = [], [], [], []
    offset = 0
    first_node_of_comp: dict[int, list[int]] = {}
    for k in order:
        poly, (_, lid, ci, branch), name = polys[k], raw[k], names[k]
        m = len(poly)
        ids = list(range(offset, offset + m))
        r = np.abs(np.asarray(dist_fn(poly), dtype=np.float64).reshape(-1))
        kappa = cv.menger_curvature(cv.smooth_polyline(poly, 2.0 * cfg.step_mm, cfg.step_mm), cfg.step_mm)
        nodes.append(poly)
        radius.append(r)
        edges.append(np.c_[ids[:-1], ids[1:]])
        if branch:  # join the branch's attached end to the nearest node of its component's curves
            others = first_node_of_comp.get(ci, [])
            if others:
                cand = np.concatenate([np.arange(a, b) for a, b in others])
                allp = np.vstack(nodes)
                d0 = np.linalg.norm(allp[cand] - poly[0], axis=1)
                edges.append(np.array([[int(cand[np.argmin(d0)]), ids[0]]]))
        first_node_of_comp.setdefault(ci, []).append((offset, offset + m))
        curves_out.append(RibCurve(
            label=name, label_id=lid, node_ids=ids,
            length_mm=float(cv.arc_length(poly)[-1]),
            mean_radius_mm=float(r.mean()), min_radius_mm=float(r.min()),
            max_curvature_per_mm=float(kappa.max()) if len(kappa) else 0.0,
        ))
        offset += m
    t_end = time.perf_counter()
    info = {
        "n_points": len(pts),
        "link_mm": float(link),
        "n_components": len(cinfo["component_ids"]),
        "n_merged_splits": int(n_merged),
        "dropped_point_fraction": dropped,
        "contraction_iterations": [int(c["iterations"]) for c in cinfo["components"]],
        "mid_sagittal_x_mm": mid_x,
        "time_s": {"cluster": t_cluster - t0, "contract": t_contract - t_cluster,
                   "curves": t_end - t_contract, "total": t_end - t0},
        "config": cfg.to_dict(),
    }
    say(1.0, f"{len(curves_out)} curves")
    return Skeleton(
        nodes_mm=np.vstack(nodes) if nodes else np.zeros((0, 3)),
        edges=np.vstack(edges) if edges else np.zeros((0, 2), dtype=np.int64),
        radius_mm=np.concatenate(radius) if radius else np.zeros(0),
        curves=curves_out,
        info=info,
    )


def _sample_surface(tri: np.ndarray, cross: np.ndarray, cum_area: np.ndarray, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """n area-uniform points on triangles (F, 3, 3) with their unit face normals ((n, 3), (n, 3));
    cross: (F, 3) edge cross products (normal directions), cum_area: cumulative sum of their norms.
    The distribution of trimesh.sample.sample_surface, several times faster on big meshes (sorted
    uniforms: sequential face look-up; only the sampled faces are touched). Points come in face order."""
    fi = np.minimum(np.searchsorted(cum_area, np.sort(rng.random(n)) * cum_area[-1]), len(tri) - 1)
    r = rng.random((n, 2))
    flip = r.sum(1) > 1.0  # fold the unit square onto the triangle
    r[flip] = 1.0 - r[flip]
    t = tri[fi]
    pts = t[:, 0] + r[:, :1] * (t[:, 1] - t[:, 0]) + r[:, 1:] * (t[:, 2] - t[:, 0])
    nrm = cross[fi]
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    return pts, nrm


def skeleton_from_mesh(
    mesh_mm: trimesh.Trimesh,
    n_points: int = 20_000,
    seed: int = 0,
    point_labels_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    **kw,
) -> Skeleton:
    """Skeleton of a closed surface mesh (mm): samples `n_points` uniformly by area (with face
    normals) and calls `skeletonize`; the radius comes from the mesh (distances to a dense sample of
    it with normals) unless `distance_to_surface_mm` is passed. point_labels_fn: (n, 3) mm -> (n,)
    int labels for the samples (e.g. the label of the nearest input voxel of a label map), so the
    curves are named by the input. Other keywords go to `skeletonize`."""
    if not isinstance(mesh_mm, trimesh.Trimesh) or len(mesh_mm.faces) == 0:
        raise RibPullInputError("bad_parameter", "skeleton_from_mesh needs a non-empty triangle mesh")
    rng = np.random.default_rng(seed)
    tri = np.asarray(mesh_mm.vertices, dtype=np.float64)[np.asarray(mesh_mm.faces, dtype=np.int64)]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    cum = np.cumsum(np.linalg.norm(cross, axis=1))  # twice the face areas, accumulated
    pts, normals = _sample_surface(tri, cross, cum, int(n_points), rng)
    if kw.get("distance_to_surface_mm") is None:
        dense, dnormals = _sample_surface(tri, cross, cum, max(10 * int(n_points), 200_000), rng)
        kw["distance_to_surface_mm"] = surface_distance_fn(dense, dnormals, 8)
    kw.setdefault("normals", normals)
    if point_labels_fn is not None:
        kw["point_labels"] = np.asarray(point_labels_fn(pts))
    return skeletonize(pts, **kw)
