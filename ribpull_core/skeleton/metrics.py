"""Skeleton accuracy against true centerlines (mm) and graph topology counts."""

from __future__ import annotations

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

from ribpull_core.skeleton.curves import resample_polyline
from ribpull_core.skeleton.model import Skeleton


def densify_edges(nodes_mm: np.ndarray, edges: np.ndarray, step_mm: float = 0.1) -> np.ndarray:
    """(P, 3) points every <= step_mm along every edge (segment), end points included."""
    if len(edges) == 0:
        return nodes_mm.copy()
    a, b = nodes_mm[edges[:, 0]], nodes_mm[edges[:, 1]]
    n = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / step_mm).astype(int))
    seg = np.repeat(np.arange(len(edges)), n + 1)
    t = np.concatenate([np.linspace(0.0, 1.0, k + 1) for k in n])
    return a[seg] + t[:, None] * (b[seg] - a[seg])


def truth_dict(true_centerlines) -> tuple[dict[str, np.ndarray], bool]:
    """Normalise truth to {name: (n, 3)}: a dict is kept (named=True); a RibSeg array (R, n, 3)
    with -1 rows for missing ribs becomes {"0": ..., ...} without usable names (named=False)."""
    if isinstance(true_centerlines, dict):
        return {str(k): np.asarray(v, dtype=np.float64).reshape(-1, 3) for k, v in true_centerlines.items()}, True
    arr = np.asarray(true_centerlines, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[None]
    out = {}
    for i, c in enumerate(arr):
        keep = ~np.all(c == -1, axis=1)
        if keep.sum() >= 2:
            out[str(i)] = c[keep]
    return out, False


def graph_of(skel: Skeleton) -> nx.Graph:
    g = nx.Graph()
    g.add_nodes_from(range(len(skel.nodes_mm)))
    g.add_edges_from(skel.edges.tolist())
    return g


def count_paths(g: nx.Graph) -> int:
    """Branch-free paths of a graph: edges chained through degree-2 nodes; a component that is a
    pure cycle counts as one, isolated nodes count as none."""
    deg = dict(g.degree())
    seen_edges = set()
    n_paths = 0
    for u in g.nodes:
        if deg[u] == 2 or deg[u] == 0:
            continue
        for v in g.neighbors(u):
            if (u, v) in seen_edges:
                continue
            n_paths += 1
            prev, cur = u, v
            seen_edges.update({(prev, cur), (cur, prev)})
            while deg[cur] == 2:
                nxt = next(w for w in g.neighbors(cur) if w != prev)
                if (cur, nxt) in seen_edges:
                    break
                seen_edges.update({(cur, nxt), (nxt, cur)})
                prev, cur = cur, nxt
    for comp in nx.connected_components(g):
        if len(comp) > 1 and all(deg[u] == 2 for u in comp):
            n_paths += 1
    return n_paths


def skeleton_metrics(skel: Skeleton, true_centerlines, coverage_tol_mm: float = 2.0) -> dict:
    """Distances (mm) and topology of a skeleton against true centerlines.

    true_centerlines: {name: (n, 3) mm} or a RibSeg array (24, 500, 3) with -1 rows for missing ribs.
    mean_dist_mm / p95_dist_mm / max_dist_mm: skeleton -> truth, over the skeleton's edges resampled
    every 0.1 mm, to the truth resampled every 0.05 mm. coverage: fraction of the true centerline
    points within coverage_tol_mm of the (resampled) skeleton. n_paths: branch-free paths of the
    graph; n_branch_nodes: nodes of degree >= 3; n_cycles: networkx cycle_basis size;
    n_components: connected parts. label_accuracy (named truth only, else None): fraction of
    curves whose label equals the name of the true rib nearest to them (the rib nearest to most of
    the curve's nodes); label_matches: true rib name -> labels of the curves matched to it.
    """
    truth, named = truth_dict(true_centerlines)
    true_pts = np.vstack(list(truth.values()))
    dense_truth = np.vstack([resample_polyline(c, 0.05) for c in truth.values()])
    truth_owner = np.concatenate(
        [np.full(len(resample_polyline(c, 0.05)), i) for i, c in enumerate(truth.values())]
    )
    names = list(truth.keys())
    g = graph_of(skel)
    sk_dense = densify_edges(skel.nodes_mm, skel.edges, 0.1)
    out: dict = {"n_nodes": len(skel.nodes_mm), "n_curves": len(skel.curves)}
    if len(sk_dense) == 0:
        out.update(mean_dist_mm=float("inf"), p95_dist_mm=float("inf"), max_dist_mm=float("inf"), coverage=0.0)
    else:
        tt = cKDTree(dense_truth)
        d, _ = tt.query(sk_dense)
        out["mean_dist_mm"] = float(d.mean())
        out["p95_dist_mm"] = float(np.percentile(d, 95))
        out["max_dist_mm"] = float(d.max())
        dc, _ = cKDTree(sk_dense).query(true_pts)
        out["coverage"] = float((dc <= coverage_tol_mm).mean())
    deg = np.array([d for _, d in g.degree()]) if g.number_of_nodes() else np.zeros(0)
    out["n_paths"] = count_paths(g)
    out["n_branch_nodes"] = int((deg >= 3).sum())
    out["n_cycles"] = len(nx.cycle_basis(g))
    out["n_components"] = nx.number_connected_components(g) if g.number_of_nodes() else 0
    if named and skel.curves:
        tt = cKDTree(dense_truth)
        correct = 0
        per_rib = {}
        for c in skel.curves:
            pts = skel.curve_points(c)
            _, j = tt.query(pts)
            owner = np.bincount(truth_owner[j], minlength=len(names)).argmax()
            correct += int(c.label == names[owner])
            per_rib.setdefault(names[owner], []).append(c.label)
        out["label_accuracy"] = correct / len(skel.curves)
        out["label_matches"] = per_rib
    else:
        out["label_accuracy"] = None
    return out
