"""From contracted points to clean medial curves (mm): sampling, graph, paths, recentring, ends.

A cluster's contracted points are reduced to ball samples (Cao et al.'s farthest-point ball
sampling), linked when their members are neighbours on the original surface, collapsed to a tree
(minimum spanning tree) and split into simple paths: the longest path first, then only side
branches that run far outside the tube around it (a rib is one path). Each path becomes a polyline that is then refined on the ORIGINAL
surface points: recentred on the ellipse fitted to its cross-sections, smoothed, and extended along
its end tangents to the cap centres, and resampled at ~1 mm.
"""

from __future__ import annotations

import networkx as nx
import numpy as np
from numba import njit
from scipy import sparse
from scipy.ndimage import gaussian_filter1d
from scipy.sparse.csgraph import minimum_spanning_tree
from scipy.spatial import cKDTree

# ----------------------------------------------------------------------------------------------
# contracted points -> graph -> paths


def ball_sample(points_mm: np.ndarray, radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Farthest-point ball sampling: (sample indices (S,), assignment (N,) sample number per point).

    Starts from the point farthest from the centroid and repeatedly adds the point farthest from
    all samples until every point is within `radius_mm` of one; points go to their nearest sample.
    """
    pts = np.ascontiguousarray(points_mm, dtype=np.float64)
    first = int(np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))
    return _farthest_point_samples(pts, first, float(radius_mm))


@njit(cache=True)
def _farthest_point_samples(points, first, radius):  # pragma: no cover - compiled
    """`ball_sample`'s loop, compiled: one pass over the points per sample instead of numpy's five
    temporaries (sternum label map's skeleton, 9 clusters of up to ~8k points: 0.52 -> 0.07 s).
    Distances are summed over the axes in order, as numpy's norm sums them, so the samples and the
    assignment are numpy's (the first farthest point on a tie, as np.argmax)."""
    n = points.shape[0]
    dist = np.empty(n)
    assign = np.zeros(n, dtype=np.int64)
    samples = np.empty(n, dtype=np.int64)
    samples[0] = first
    count = 1
    for i in range(n):
        dx = points[i, 0] - points[first, 0]
        dy = points[i, 1] - points[first, 1]
        dz = points[i, 2] - points[first, 2]
        dist[i] = np.sqrt(dx * dx + dy * dy + dz * dz)
    while True:
        far = 0
        for i in range(1, n):
            if dist[i] > dist[far]:
                far = i
        if dist[far] <= radius:
            break
        for i in range(n):
            dx = points[i, 0] - points[far, 0]
            dy = points[i, 1] - points[far, 1]
            dz = points[i, 2] - points[far, 2]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            if d < dist[i]:
                assign[i] = count
                dist[i] = d
        samples[count] = far
        count += 1
    return samples[:count].copy(), assign


def sample_graph(
    assign: np.ndarray, neighbor_idx: np.ndarray, node_mm: np.ndarray, max_edge_mm: float | None = None
) -> sparse.csr_matrix:
    """(S, S) symmetric sparse graph: samples a, b linked when some point of a has a kNN neighbour
    (`neighbor_idx` (N, k), on the original surface) in b; weight = distance between samples (mm).
    Links longer than max_edge_mm (contracted points thrown off the curve) are dropped."""
    a = np.repeat(assign, neighbor_idx.shape[1])
    b = assign[neighbor_idx.ravel()]
    keep = a != b
    pairs = np.unique(np.sort(np.c_[a[keep], b[keep]], axis=1), axis=0)
    s = len(node_mm)
    w = np.linalg.norm(node_mm[pairs[:, 0]] - node_mm[pairs[:, 1]], axis=1) + 1e-9
    if max_edge_mm is not None:
        pairs, w = pairs[w <= max_edge_mm], w[w <= max_edge_mm]
    if len(pairs) == 0:
        return sparse.csr_matrix((s, s))
    g = sparse.coo_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(s, s))
    return (g + g.T).tocsr()


def tree_paths(
    tree: nx.Graph, pos_mm: np.ndarray, min_branch_mm: float, clearance_mm: float = 8.0
) -> list[list[int]]:
    """Split a weighted tree (edge attr 'weight' in mm, node positions pos_mm (S, 3)) into paths.

    The first path is the tree's longest path (its diameter). Then, repeatedly, the branch hanging
    off the covered nodes that runs longest OUTSIDE the tube of radius `clearance_mm` around them
    (its own edges with both ends farther than that from every covered node) is added, from its
    attachment node, while that outside length is at least `min_branch_mm`. Everything else is
    pruned: side spurs, and strands running alongside the main path inside the same tube (a
    half-contracted flat tube is a ribbon that a spanning tree crosses in parallel strands).

    The tree is walked as adjacency lists: in a tree the one path between two nodes is the
    shortest, so a walk that adds each edge's weight to its parent's distance gives the distances
    networkx's Dijkstra gives, to the bit, without its subgraph views (sternum map's skeleton: the
    walks ~0.5 -> ~0.05 s).
    """
    nodes = list(tree.nodes)
    if not nodes:
        return []
    if len(nodes) == 1:
        return [nodes]
    adj = {n: [(m, float(d.get("weight", 1.0))) for m, d in tree.adj[n].items()] for n in nodes}
    d0, _ = _walk(adj, nodes[0])
    a = max(d0, key=d0.get)
    dist_a, parent_a = _walk(adj, a)
    paths = [_path_to(parent_a, max(dist_a, key=dist_a.get))]
    covered = set(paths[0])
    while len(covered) < len(nodes):
        cov_tree = cKDTree(pos_mm[sorted(covered)])
        best = None
        seen = set(covered)
        for first in nodes:  # each branch off the covered nodes, in the tree's node order
            if first in seen:
                continue
            branch, attach = _branch_of(adj, first, covered, seen)
            if attach is None:  # a part not connected to the covered nodes (not a tree)
                continue
            dist, parent = _walk(adj, attach, within=branch)
            path = _path_to(parent, max(dist, key=dist.get))
            clear = cov_tree.query(pos_mm[path])[0] > clearance_mm
            seg = np.linalg.norm(np.diff(pos_mm[path], axis=0), axis=1)
            outside = float(seg[clear[:-1] & clear[1:]].sum())
            if best is None or outside > best[0]:
                best = (outside, path)
        if best is None or best[0] < min_branch_mm:
            break
        paths.append(best[1])
        covered.update(best[1])
    return paths


def _walk(adj: dict, source: int, within: set | None = None) -> tuple[dict, dict]:
    """Distances (mm) from `source` along a tree given as adjacency lists {node: [(neighbour,
    weight)]}, and each reached node's parent: ({node: distance}, {node: parent}). within: the only
    nodes to enter besides the source (None: all)."""
    dist, parent = {source: 0.0}, {source: source}
    stack = [source]
    while stack:
        u = stack.pop()
        for v, w in adj[u]:
            if v not in dist and (within is None or v in within):
                dist[v] = dist[u] + w
                parent[v] = u
                stack.append(v)
    return dist, parent


def _path_to(parent: dict, node: int) -> list[int]:
    """The node ids from a `_walk`'s source to `node`."""
    path = [node]
    while parent[path[-1]] != path[-1]:
        path.append(parent[path[-1]])
    return path[::-1]


def _branch_of(adj: dict, first: int, covered: set, seen: set) -> tuple[set, int]:
    """The uncovered part of a tree that holds `first` (marked in `seen`), and the one covered
    node it hangs off (a connected covered part of a tree meets each such branch once; None
    where it meets none)."""
    branch, stack, attach = {first}, [first], None
    seen.add(first)
    while stack:
        u = stack.pop()
        for v, _ in adj[u]:
            if v in covered:
                attach = v
            elif v not in seen:
                seen.add(v)
                branch.add(v)
                stack.append(v)
    return branch, attach


def contracted_paths(
    contracted_mm: np.ndarray, neighbor_idx: np.ndarray, sample_radius_mm: float, prune_length_mm: float,
    clearance_mm: float = 8.0,
) -> tuple[list[np.ndarray], np.ndarray, list[list[int]]]:
    """Paths of one cluster: ([polyline (m, 3) mm of sample positions], assignment (N,), [sample ids]).

    Ball-samples the contracted points, links samples whose members are surface neighbours, keeps a
    minimum spanning tree per connected part and splits it into paths with `tree_paths`.
    """
    samples, assign = ball_sample(contracted_mm, sample_radius_mm)
    s = len(samples)
    counts = np.bincount(assign, minlength=s).astype(float)
    node = np.zeros((s, 3))
    np.add.at(node, assign, contracted_mm)
    node /= counts[:, None]
    g = sample_graph(assign, neighbor_idx, node, max_edge_mm=10.0 * sample_radius_mm)
    mst = minimum_spanning_tree(g).tocoo()
    tree = nx.Graph()
    tree.add_nodes_from(range(s))
    tree.add_weighted_edges_from(zip(mst.row.tolist(), mst.col.tolist(), mst.data.tolist()))
    polylines, ids = [], []
    for comp in nx.connected_components(tree):
        for p in tree_paths(tree.subgraph(comp), node, prune_length_mm, clearance_mm):
            if len(p) < 2:
                continue
            polylines.append(node[p])
            ids.append(list(p))
    return polylines, assign, ids


# ----------------------------------------------------------------------------------------------
# polyline utilities


def arc_length(poly_mm: np.ndarray) -> np.ndarray:
    """(m,) cumulative arc length (mm) of a polyline (m, 3), starting at 0."""
    seg = np.linalg.norm(np.diff(poly_mm, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def resample_polyline(poly_mm: np.ndarray, step_mm: float) -> np.ndarray:
    """Resample a polyline (m, 3) at (nearly) equal arc-length spacing <= step_mm; keeps both ends."""
    s = arc_length(poly_mm)
    if len(poly_mm) < 2 or s[-1] <= 0:
        return poly_mm[:1].copy()
    n = max(2, int(np.ceil(s[-1] / step_mm)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly_mm[:, k]) for k in range(3)], axis=1)


def smooth_polyline(poly_mm: np.ndarray, sigma_mm: float, step_mm: float) -> np.ndarray:
    """Gaussian smoothing along an equally spaced polyline (spacing step_mm), sigma in mm.

    Ends are padded by point reflection (x(-s) = 2 x(0) - x(s)), which keeps straight and gently
    curved ends in place instead of pulling them inward.
    """
    m = len(poly_mm)
    if m < 3 or sigma_mm <= 0:
        return poly_mm.copy()
    sig = sigma_mm / step_mm
    pad = min(m - 1, int(np.ceil(4 * sig)))
    head = 2 * poly_mm[0] - poly_mm[pad:0:-1]
    tail = 2 * poly_mm[-1] - poly_mm[-2:-pad - 2:-1]
    ext = np.vstack([head, poly_mm, tail])
    sm = gaussian_filter1d(ext, sig, axis=0, mode="nearest")
    return sm[pad:pad + m]


def tangents(poly_mm: np.ndarray) -> np.ndarray:
    """(m, 3) unit tangents (central differences)."""
    t = np.gradient(poly_mm, axis=0)
    return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)


def rotation_minimizing_frames(poly_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, N, B) each (m, 3): unit tangent and a rotation-minimizing normal frame, transported by
    double reflection (Wang et al. 2008), so cross-section coordinates of neighbouring nodes line up."""
    t = tangents(poly_mm)
    m = len(poly_mm)
    ref = np.array([0.0, 0.0, 1.0]) if abs(t[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n0 = np.cross(t[0], ref)
    e = (n0 / np.linalg.norm(n0)).tolist()
    tl = t.tolist()
    out = [e]
    for i in range(m - 1):
        t0, t1 = tl[i], tl[i + 1]
        b = [t0[0] + t1[0], t0[1] + t1[1], t0[2] + t1[2]]
        bb = b[0] * b[0] + b[1] * b[1] + b[2] * b[2]
        if bb > 1e-12:  # reflection in the plane normal to t0 + t1, then in the plane normal to t1
            f = 2.0 * (b[0] * e[0] + b[1] * e[1] + b[2] * e[2]) / bb
            e = [e[0] - f * b[0], e[1] - f * b[1], e[2] - f * b[2]]
            f = 2.0 * (e[0] * t1[0] + e[1] * t1[1] + e[2] * t1[2])
            e = [e[0] - f * t1[0], e[1] - f * t1[1], e[2] - f * t1[2]]
        out.append(e)
    n = np.asarray(out)
    n -= (n * t).sum(1, keepdims=True) * t
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return t, n, np.cross(t, n)


def project_to_polyline(points_mm: np.ndarray, poly_mm: np.ndarray, fine_mm: float = 0.1):
    """Closest-point projection of points (N, 3) onto a polyline (m, 3).

    Returns (s (N,) arc length of the foot point in mm, foot index (N,) into a resampled copy at
    `fine_mm`, dist (N,) mm, fine polyline (F, 3), fine arc length (F,)).
    """
    fine = resample_polyline(poly_mm, fine_mm)
    s_f = arc_length(fine)
    d, j = cKDTree(fine).query(points_mm, k=1)
    return s_f[j], j, d, fine, s_f


def menger_curvature(poly_mm: np.ndarray, step_mm: float, baseline_mm: float = 5.0) -> np.ndarray:
    """(m,) curvature in 1/mm from the circle through nodes i-k, i, i+k (k x step ~ baseline_mm);
    0 where the triple does not fit."""
    m = len(poly_mm)
    k = max(1, round(baseline_mm / step_mm))
    kap = np.zeros(m)
    if m < 2 * k + 1:
        return kap
    a, b, c = poly_mm[:-2 * k], poly_mm[k:-k], poly_mm[2 * k:]
    ab, bc, ca = b - a, c - b, a - c
    cross = np.linalg.norm(np.cross(ab, bc), axis=1)
    denom = np.linalg.norm(ab, axis=1) * np.linalg.norm(bc, axis=1) * np.linalg.norm(ca, axis=1)
    kap[k:-k] = np.where(denom > 1e-12, 2.0 * cross / np.maximum(denom, 1e-12), 0.0)
    return kap


# ----------------------------------------------------------------------------------------------
# refinement on the original surface points


def conic_centres(scatter: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched algebraic conic fit from weighted scatter matrices.

    scatter: (m, 6, 6) sums of w d d^T with d = (x^2, xy, y^2, x, y, 1) of points (x, y) = uv / scale.
    The conic A x^2 + B xy + C y^2 + D x + E y + F = 0 minimising sum w (d . coef)^2 with
    ||coef|| = 1 is the eigenvector of the smallest eigenvalue. Returns (centres (m, 2), semi-axes
    (m, 2) major/minor, valid (m,) bool, major-axis angle (m,) rad in the uv plane) in uv units;
    a fit is valid when the conic is a real ellipse.
    """
    m = len(scatter)
    if m == 0:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=bool), np.zeros(0)
    _, vec = np.linalg.eigh(scatter)
    A, B, C, D, E, F = np.moveaxis(vec[:, :, 0], 1, 0)
    det = 4 * A * C - B * B
    ok = det > 1e-12 * np.maximum(1.0, A * A + C * C)
    safe = np.where(ok, det, 1.0)
    cx = (B * E - 2 * C * D) / safe
    cy = (B * D - 2 * A * E) / safe
    f0 = A * cx * cx + B * cx * cy + C * cy * cy + D * cx + E * cy + F
    tr, dt = A + C, A * C - B * B / 4
    disc = np.sqrt(np.maximum(tr * tr / 4 - dt, 0.0))
    ev = np.stack([tr / 2 - disc, tr / 2 + disc], axis=1)  # eigenvalues of [[A, B/2], [B/2, C]]
    with np.errstate(divide="ignore", invalid="ignore"):
        ax2 = -f0[:, None] / ev
    ok &= np.all(ax2 > 0, axis=1) & np.isfinite(ax2).all(axis=1)
    axes = np.sqrt(np.where(ok[:, None], ax2, 0.0)) * scale  # (along eigvec of ev[:, 0], ev[:, 1])
    # major axis = eigenvector of the smaller eigenvalue of [[A, B/2], [B/2, C]] (x/y-ratio invariant
    # to the common scale); angle in the uv plane
    angle = np.where(ok, 0.5 * np.arctan2(B, A - C) + np.pi / 2, 0.0)
    swap = axes[:, 0] < axes[:, 1]
    axes = np.sort(axes, axis=1)[:, ::-1]
    centres = np.stack([cx, cy], axis=1) * scale
    centres[~ok] = 0.0
    return centres, axes, ok, np.where(swap, angle + np.pi / 2, angle)


def fit_ellipse_center(uv: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, float, float] | None:
    """Weighted algebraic conic fit of 2D points (n, 2): (centre (2,), major, minor semi-axis) in
    the points' units, or None when the best conic is not an ellipse. Minimises
    sum_i w_i (A u^2 + B uv + C v^2 + D u + E v + F)^2 with ||(A..F)|| = 1 (points pre-scaled)."""
    w = np.ones(len(uv)) if w is None else np.asarray(w, dtype=np.float64)
    if len(uv) < 6:
        return None
    mu = (w[:, None] * uv).sum(0) / w.sum()
    sc = float(np.sqrt((w * ((uv - mu) ** 2).sum(1)).sum() / w.sum())) or 1.0
    x, y = ((uv - mu) / sc).T
    d = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
    c, ax, ok, _ = conic_centres((d.T * w) @ d[None], sc)
    return (c[0] + mu, float(ax[0, 0]), float(ax[0, 1])) if ok[0] else None


def window_matrix(s_nodes: np.ndarray, s_points: np.ndarray, sigma_mm, half_mm=None) -> sparse.csr_matrix:
    """(m, n) sparse Gaussian weights exp(-(s_node - s_point)^2 / (2 sigma^2)) for points within
    half_mm of the node (default 3 sigma); sigma_mm and half_mm may be per node (m,) arrays (mm)."""
    m = len(s_nodes)
    sig = np.broadcast_to(np.asarray(sigma_mm, dtype=np.float64), (m,))
    half = 3.0 * sig if half_mm is None else np.broadcast_to(np.asarray(half_mm, dtype=np.float64), (m,))
    order = np.argsort(s_points, kind="stable")
    ss = s_points[order]
    lo = np.searchsorted(ss, s_nodes - half, side="left")
    hi = np.searchsorted(ss, s_nodes + half, side="right")
    cnt = np.maximum(hi - lo, 0)
    rows = np.repeat(np.arange(m), cnt)
    pos = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)
    cols = order[pos]
    vals = np.exp(-0.5 * ((s_nodes[rows] - s_points[cols]) / sig[rows]) ** 2)
    return sparse.csr_matrix((vals, (rows, cols)), shape=(m, len(s_points)))


def recentre_polyline(
    poly_mm: np.ndarray,
    points_mm: np.ndarray,
    step_mm: float,
    sigma_mm: float,
    weights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Move each node to the centre of its tube cross-section; returns (polyline (m, 3), minor and
    major semi-axis per node (m,) mm (NaN where no ellipse was fitted), major-axis unit vectors
    (m, 3)).

    Surface points are projected onto the curve; their offsets, expressed in rotation-minimizing
    frames, are pooled over a Gaussian window (sigma_mm, cut at 3 sigma) of arc length around each
    node and fitted by an ellipse (for a tube with elliptical sections the fitted centre is the axis
    even when the sampling is uneven). Where no plausible ellipse fits (fewer than 8 points, not an
    ellipse, centre off by more than 0.6 x the spread of the points, major axis > 2 x spread) the
    node moves to the (`weights`-weighted, e.g. area) centroid instead. Points whose foot is an end
    of the curve (caps, or the part beyond a short end) are left out. This removes the
    contraction's bias toward the thick side of the tube.
    """
    m = len(poly_mm)
    s_p, j, _, fine, _ = project_to_polyline(points_mm, poly_mm)
    interior = (j > 0) & (j < len(fine) - 1)
    pts, s_p, j = points_mm[interior], s_p[interior], j[interior]
    t_fine = tangents(fine)
    _, Nn, Bn = rotation_minimizing_frames(poly_mm)
    s_nodes = arc_length(poly_mm)
    node_of = np.clip(np.searchsorted(s_nodes, s_p), 0, m - 1)
    off = pts - fine[j]
    off -= (off * t_fine[j]).sum(1, keepdims=True) * t_fine[j]
    uv = np.stack([(off * Nn[node_of]).sum(1), (off * Bn[node_of]).sum(1)], axis=1)
    W = window_matrix(s_nodes, s_p, sigma_mm)
    count = np.diff(W.indptr)
    wsum = np.asarray(W.sum(1)).ravel()
    spread = np.sqrt((W @ (uv ** 2).sum(1)) / np.maximum(wsum, 1e-12))
    scale = float(np.median(spread[count > 0])) if (count > 0).any() else 1.0
    x, y = (uv / scale).T
    d = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
    scatter = (W @ (d[:, :, None] * d[:, None, :]).reshape(len(d), 36)).reshape(m, 6, 6)
    centres, axes, ok, angle = conic_centres(scatter, scale)
    ok &= (count >= 8) & (np.linalg.norm(centres, axis=1) < 0.6 * spread) & (axes[:, 0] < 2.0 * spread)
    ww = W if weights is None else W @ sparse.diags(weights[interior])
    centroid = (ww @ uv) / np.maximum(np.asarray(ww.sum(1)).ravel(), 1e-12)[:, None]
    c = np.where(ok[:, None], centres, centroid)
    c[count < 3] = 0.0
    out = poly_mm + c[:, :1] * Nn + c[:, 1:] * Bn
    axes = np.where(ok[:, None], axes, np.nan)
    major_dir = np.cos(angle)[:, None] * Nn + np.sin(angle)[:, None] * Bn
    return out, axes[:, 1], axes[:, 0], major_dir


def end_cap_offset(
    end_mm: np.ndarray, tangent: np.ndarray, points_mm: np.ndarray, minor_mm: float,
    major_mm: float | None = None, major_dir: np.ndarray | None = None,
) -> float | None:
    """Signed distance (mm) along the outward end tangent from `end_mm` to the cap centre.

    Casts a ray from the end along `tangent` and models the end as a half-ellipsoid around it with
    the local cross-section (semi-axes major_mm along major_dir and minor_mm; a circle of radius
    minor_mm when no section is known) and length minor_mm along the ray, i.e. the apex of the cap
    minus the local radius (a capsule-like end). Every surface point inside the section outline
    (normalised section radius q < 0.9) in front of the end gives a centre estimate
    z - minor sqrt(1 - q^2) (z: its height along the ray). Returns the median of the estimates
    within minor/2 of the largest one (the cap, not tube wall points behind it), or None when the
    ray meets no surface point.
    """
    rel = points_mm - end_mm
    z = rel @ tangent
    lat = rel - z[:, None] * tangent
    if major_mm is not None and major_dir is not None and np.isfinite(major_mm) and major_mm > 0:
        d = major_dir - (major_dir @ tangent) * tangent
        d /= max(np.linalg.norm(d), 1e-12)
        q2 = (lat @ d / major_mm) ** 2 + (lat @ np.cross(tangent, d) / minor_mm) ** 2
    else:
        q2 = (np.linalg.norm(lat, axis=1) / minor_mm) ** 2
    cand = (q2 < 0.81) & (z > -2.0 * minor_mm)
    if not cand.any():
        return None
    est = z[cand] - minor_mm * np.sqrt(1.0 - q2[cand])
    top = est >= est.max() - 0.5 * minor_mm
    return float(np.median(est[top]))


def adjust_ends(
    poly_mm: np.ndarray, points_mm: np.ndarray, radius_head_mm: float, radius_tip_mm: float,
    step_mm: float, tangent_mm: float = 6.0, extend: tuple[bool, bool] = (True, True),
    sections: tuple | None = None,
) -> np.ndarray:
    """Extend (or trim) both ends of a polyline along their tangents to the cap centres.

    The end tangent is taken over the last `tangent_mm` of the curve; see `end_cap_offset`.
    radius_*_mm: local radius (minor semi-axis) at each end; sections: optional
    ((major_head, dir_head (3,)), (major_tip, dir_tip)) cross-section ellipses at the ends.
    extend: (head, tip) which ends to adjust. Returns the new polyline resampled at `step_mm`.
    """
    poly = resample_polyline(poly_mm, step_mm)
    for end in (0, 1):
        if not extend[end]:
            continue
        if end == 1:
            poly = poly[::-1]
        s = arc_length(poly)
        if s[-1] < 2 * step_mm:
            poly = poly[::-1] if end == 1 else poly
            continue
        k = int(np.searchsorted(s, min(tangent_mm, 0.5 * s[-1])))
        k = max(k, 1)
        t = poly[0] - poly[k]
        t /= np.linalg.norm(t)
        r = radius_head_mm if end == 0 else radius_tip_mm
        sec = sections[end] if sections is not None else (None, None)
        off = end_cap_offset(poly[0], t, points_mm, r, sec[0], sec[1])
        if off is not None:
            if off > 0:
                n_new = int(np.ceil(off / step_mm))
                ext = poly[0] + np.outer(np.linspace(off, 0, n_new + 1)[:-1], t)
                poly = np.vstack([ext, poly])
            elif off < 0:
                cut = min(-off, 0.5 * s[-1])
                keep = s >= cut
                new0 = np.array([np.interp(cut, s, poly[:, q]) for q in range(3)])
                poly = np.vstack([new0, poly[keep]])
        if end == 1:
            poly = poly[::-1]
    return resample_polyline(poly, step_mm)
