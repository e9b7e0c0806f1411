"""Laplacian-based contraction of a point cloud (the paper's eq. 3-4; Cao et al. 2010).

Each iteration solves, in least squares,

    [W_L L; W_H] P' = [0; W_H P]                                   (eq. 3)

i.e. minimises E(P') = ||W_L L P'||_F^2 + sum_i W_H,i^2 ||p'_i - p_i||^2   (eq. 4)

with L the cotangent point-cloud Laplacian (robust-laplacian), W_L a scalar contraction weight that
grows 3x per iteration and W_H,i an attraction weight that grows as the point's neighbourhood
shrinks. The cloud collapses onto its curve skeleton in a few iterations.

Results depend on scale, so each cloud is first scaled to a longest bounding-box side of 1.6 (Cao)
and mapped back to mm afterwards. Every connected cluster (rib) is contracted on its own.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import robust_laplacian
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from ribpull_core.skeleton.components import auto_link_mm, find_components, validate_points
from ribpull_core.skeleton.model import SkeletonConfig


def normalise_scale(points_mm: np.ndarray, longest_side: float = 1.6) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre on the bounding-box centre and scale the longest side to `longest_side`.

    Returns (points (N, 3) normalised, center_mm (3,), scale) with p_norm = (p_mm - center) * scale.
    """
    lo, hi = points_mm.min(axis=0), points_mm.max(axis=0)
    center = (lo + hi) / 2.0
    side = float((hi - lo).max())
    scale = longest_side / side if side > 0 else 1.0
    return (points_mm - center) * scale, center, scale


def default_n_neighbors(n_points: int) -> int:
    """Cao et al.'s neighbourhood size: clamp(0.012 N, 8, 30)."""
    return int(np.clip(round(0.012 * n_points), 8, 30))


def point_laplacian(points: np.ndarray, n_neighbors: int, mollify_factor: float = 1e-5):
    """Cotangent point-cloud Laplacian L (N, N) PSD csr and lumped areas (N,) (robust-laplacian)."""
    L, M = robust_laplacian.point_cloud_laplacian(
        np.ascontiguousarray(points, dtype=np.float64), mollify_factor=mollify_factor,
        n_neighbors=int(n_neighbors),
    )
    return sparse.csr_matrix(L), np.asarray(M.diagonal()).ravel()


def ring_size(points: np.ndarray, neighbor_idx: np.ndarray) -> np.ndarray:
    """(N,) size of each point's one-ring: mean distance to its (fixed) kNN neighbours `neighbor_idx`
    (N, k), in the points' units. Shrinks as the neighbourhood contracts."""
    d = np.linalg.norm(points[neighbor_idx] - points[:, None, :], axis=2)
    return d.mean(axis=1)


def contraction_energy(p_new: np.ndarray, p_old: np.ndarray, L, w_l: float, w_h: np.ndarray) -> float:
    """Paper eq. 4: E(P') = ||W_L L P'||_F^2 + sum_i W_H,i^2 ||p'_i - p_i||_2^2 (normalised units)."""
    lp = L @ p_new
    return float((w_l ** 2) * np.sum(lp * lp) + np.sum((w_h ** 2) * np.sum((p_new - p_old) ** 2, axis=1)))


def contraction_step(points: np.ndarray, L, w_l: float, w_h: np.ndarray) -> np.ndarray:
    """Paper eq. 3: least-squares solution of [W_L L; W_H] P' = [0; W_H P].

    Solved through the normal equations (W_L^2 L^T L + W_H^2) P' = W_H^2 P, a sparse SPD system,
    with one sparse LU factorisation for the three coordinates. points: (N, 3); w_h: (N,).
    """
    wh2 = w_h ** 2
    A = (w_l ** 2) * (L.T @ L) + sparse.diags(wh2)
    lu = splu(sparse.csc_matrix(A))
    return lu.solve(np.ascontiguousarray(wh2[:, None] * points))


def contract_cluster(points_mm: np.ndarray, config: SkeletonConfig) -> tuple[np.ndarray, dict]:
    """Contract ONE connected cluster (eq. 3-4 with Cao's schedule); returns ((N, 3) mm, info).

    Schedule: W_H0 = config.w_h0, W_L0 = 1 / (5 x mean kNN edge length) unless given;
    W_L <- min(growth x W_L, w_l_max); W_H,i = W_H0 x ring0_i / ring_i (capped at w_h_max);
    stop after max_iterations or when the mean ring size shrinks by less than stop_shrink; a step
    that makes the mean ring size grow (numerical breakdown once the cloud is a thin curve) is
    rejected and ends the contraction.
    """
    n = len(points_mm)
    P, center, scale = normalise_scale(points_mm, config.normalised_side)
    k = config.n_neighbors or default_n_neighbors(n)
    k = int(min(k, n - 1))
    _, nbr = cKDTree(P).query(P, k=k + 1)
    nbr = nbr[:, 1:]
    ring0 = ring_size(P, nbr)
    mean_ring0 = float(ring0.mean())
    w_l = config.w_l0 if config.w_l0 is not None else 1.0 / (5.0 * mean_ring0)
    w_h = np.full(n, config.w_h0)
    L, area = point_laplacian(P, k, config.mollify_factor)
    history = []
    prev_ring = mean_ring0
    it = 0
    for it in range(1, config.max_iterations + 1):
        if it > 1 and config.recompute_laplacian:
            L, _ = point_laplacian(P, k, config.mollify_factor)
        P_new = contraction_step(P, L, w_l, w_h)
        if not np.isfinite(P_new).all():
            break
        ring = ring_size(P_new, nbr)
        mean_ring = float(ring.mean())
        if mean_ring > prev_ring:  # the solve went unstable (degenerate Laplacian): keep the last P
            history.append({"iteration": it, "w_l": w_l, "ring_ratio": mean_ring / mean_ring0,
                            "energy": None, "rejected": True})
            break
        energy = contraction_energy(P_new, P, L, w_l, w_h)
        P = P_new
        history.append({"iteration": it, "w_l": w_l, "ring_ratio": mean_ring / mean_ring0,
                        "energy": energy})
        if (prev_ring - mean_ring) < config.stop_shrink * prev_ring:
            break
        prev_ring = mean_ring
        w_l = min(config.w_l_growth * w_l, config.w_l_max)
        w_h = np.minimum(config.w_h0 * ring0 / np.maximum(ring, 1e-12), config.w_h_max)
    info = {"n_points": n, "n_neighbors": k, "iterations": it, "history": history,
            "area_norm": area, "scale": scale}
    return P / scale + center, info


def laplacian_contraction(
    points_mm: np.ndarray,
    config: SkeletonConfig | None = None,
    components: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Contract a point cloud onto its curve skeleton (paper eq. 3-4), cluster by cluster.

    points_mm: (N, 3) mm. components: (N,) cluster id per point (-1 = ignore); None = computed with
    `find_components` (so the Laplacian never links two ribs). Returns (contracted (N, 3) mm, info);
    ignored points keep their position. info: {"components": [per-cluster info], "time_s": ...};
    each cluster's info holds its iteration count, W_L / ring-ratio / energy history and the lumped
    area per point (`area_mm2`, from the first Laplacian).
    """
    config = config or SkeletonConfig()
    t0 = time.perf_counter()
    points_mm = validate_points(points_mm, config.min_points)
    if components is None:
        link = config.link_mm or auto_link_mm(points_mm, config.link_factor, config.link_max_mm)
        components = find_components(points_mm, link, None, config.min_component_points)
    components = np.asarray(components)
    ids = [int(c) for c in np.unique(components) if c >= 0]
    out = points_mm.copy()
    member_lists = [np.flatnonzero(components == c) for c in ids]

    def run(members):
        return contract_cluster(points_mm[members], config)

    n_jobs = config.n_jobs or os.cpu_count() or 1
    if n_jobs > 1 and len(ids) > 1:
        with ThreadPoolExecutor(max_workers=n_jobs) as pool:
            results = list(pool.map(run, member_lists))
    else:
        results = [run(m) for m in member_lists]
    infos = []
    for members, (contracted, info) in zip(member_lists, results):
        out[members] = contracted
        info["area_mm2"] = info.pop("area_norm") / info["scale"] ** 2
        infos.append(info)
    return out, {"components": infos, "component_ids": ids, "time_s": time.perf_counter() - t0}
