"""SparseOcc (Ouasfi & Boukhayma 2024) as used by RibPull: occupancy from unoriented points.

Paper eq. 1: pull queries onto the zero set of the margin uncertainty U = p_in - p_out and match
them to their nearest input point. Paper eq. 2: minimax entropy regulariser. Presets:

- ``paper``: the reference configuration (8x256 MLP, 20k iterations, batch 5000, ribcage entropy
  settings, decaying query jitter) — faithful, and slow on a CPU (~0.46 s per iteration).
- ``default``: RibPull's CPU configuration. Same losses, plus (a) free-space supervision: points
  that a flood fill from the bounding box reaches without crossing the (voxelised, dilated) input
  are outside — the sign far from the points is otherwise unconstrained and the field can close the
  thorax into one blob; near-surface inside/outside points along normals oriented by that flood fill,
  both as hinges on U that agree with eq. 1's pull; (b) multi-scale queries; (c) a hash-grid encoded field with a tiny decoder;
  (d) early stopping when the loss stops improving.
- ``smoke``: a few seconds, for tests.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from ..fields import build_module
from ..losses import (
    margin_uncertainty,
    minimax_entropy_loss,
    minimax_weight,
    pull_to_surface,
    sampling_loss,
    sign_margin_loss,
)
from .base import (
    CancelFn,
    FittedField,
    Method,
    ProgressFn,
    ProgressThrottle,
    check_cancel,
    knn_sigma,
    sample_pull_queries,
    seed_everything,
    warmup_cosine_lr,
)


@dataclass
class SparseOccConfig:
    """SparseOcc training configuration (unit-frame lengths: the input's longest side spans 2).

    network: "mlp" (the Neural-Pull 8x256 MLP) or "grid" (GridOccupancyField).
    gradient: how grad U is computed for the pull — "autograd" (exact, double backward) or
        "finite_difference" (central differences with step fd_step).
    query_scales: multipliers of the Neural-Pull query spread (0.25*sqrt(N/20000)*sigma_50);
        several values give multi-scale queries, split evenly.
    query_jitter: (start, end) std of Gaussian jitter added to queries each iteration, decaying
        linearly (RibPull's ribcage script: 0.05 -> 0.01); (0, 0) disables it.
    free_space_weight: weight of the free-space (outside) cross-entropy; 0 disables it.
    near_surface_weight: weight of the near-surface inside/outside cross-entropy at input points
        -/+ near_surface_offset (x flood-fill spacing) along flood-fill-oriented normals; 0 disables.
    gradient "finite_difference" uses forward differences (3 extra evaluations per query).
    early_stop_window: iterations per window of the convergence test (0 disables); training stops
        when the mean loss of the last window improved by less than early_stop_rel_tol relative to the
        previous window, after at least early_stop_min_fraction of the schedule.
    """

    iterations: int = 20_000
    batch_size: int = 5000
    network: str = "mlp"
    mlp_hidden: int = 256
    mlp_layers: int = 8
    grid_levels: int = 12
    grid_features: int = 2
    grid_log2_table: int = 19
    grid_base_resolution: int = 16
    grid_max_resolution: int = 512
    grid_hidden: int = 64
    lr: float = 1e-3
    grid_lr: float = 1e-2
    warmup: int = 1000
    final_lr_ratio: float = 0.0
    n_queries: int = 1_000_000
    knn: int = 50
    query_scales: tuple[float, ...] = (1.0,)
    query_jitter: tuple[float, float] = (0.05, 0.01)
    sampling_weight: float = 10.0
    gradient: str = "autograd"
    fd_step: float = 0.005
    entropy_input_points: int = 1000
    entropy_uniform_points: int = 10_000
    lambda_max: float = 10.0
    lambda_min: float = 1.0
    n_minimax: int = 1000
    free_space_weight: float = 0.0
    free_space_points: int = 5000
    near_surface_weight: float = 0.0
    near_surface_points: int = 2048
    near_surface_offset: float = 0.5
    early_stop_window: int = 0
    early_stop_rel_tol: float = 0.01
    early_stop_min_fraction: float = 0.3
    max_input_points: int = 200_000
    seed: int = 0


def paper_config() -> SparseOccConfig:
    """RibPull's reference SparseOcc configuration (methods.md): 8x256 MLP, 20k iterations."""
    return SparseOccConfig()


def default_config() -> SparseOccConfig:
    """RibPull's CPU default: hash-grid field trained with the SparseOcc losses plus data-derived
    sign supervision (free space and near-surface hinges), multi-scale queries, early stopping.
    Measured on the phantom in docs/benchmarks.md."""
    return SparseOccConfig(
        iterations=1000,
        batch_size=2048,
        network="grid",
        grid_levels=8,
        grid_log2_table=18,
        grid_max_resolution=256,
        gradient="finite_difference",
        lr=2e-3,
        grid_lr=2e-2,
        warmup=30,
        final_lr_ratio=0.05,
        n_queries=400_000,
        query_scales=(0.5, 1.0, 2.0),
        query_jitter=(0.0, 0.0),
        entropy_input_points=1000,
        entropy_uniform_points=1000,
        lambda_max=1.0,
        n_minimax=200,
        free_space_weight=10.0,
        free_space_points=2048,
        near_surface_weight=10.0,
        near_surface_points=4096,
        early_stop_window=100,
        early_stop_rel_tol=0.005,
        early_stop_min_fraction=0.6,
    )


def smoke_config() -> SparseOccConfig:
    """A short `default` (tens of seconds on a CPU): coarse but correct surfaces, for tests and CI."""
    return dataclasses.replace(
        default_config(),
        iterations=250,
        batch_size=1024,
        n_queries=100_000,
        free_space_points=1024,
        near_surface_points=2048,
        early_stop_window=0,
    )


# --- free space ------------------------------------------------------------------------------


@dataclass
class SpaceLabels:
    """Occupancy labels derived from the data (unit frame).

    free: (M, 3) points certainly outside; free_distance: (M,) their distance to the nearest input
    point. near_in / near_out: (K, 3) points just inside / outside
    the sampled surface (input point -/+ offset along its normal, oriented by the flood fill).
    spacing: flood-fill voxel size; offset: the normal offset used.
    """

    free: np.ndarray
    free_distance: np.ndarray
    near_in: np.ndarray
    near_out: np.ndarray
    spacing: float
    offset: float


def outside_mask(points_unit: np.ndarray, block_factor: float = 1.0, max_cells: int = 384
                 ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Flood-fill the empty space around the points; returns (outside (X,Y,Z) bool, blocked bool,
    spacing, origin (3,)).

    A voxel is blocked when it lies within r = block_factor x (median distance to the 8th neighbour)
    of an input point: r closes the gaps between neighbouring samples, so the blocked shell has no
    holes, yet stays thin enough that narrow gaps between ribs stay open. Voxels are r/2 wide (at
    most max_cells along the longest side). Every voxel reached from the border of a padded box
    without crossing the shell is outside. Cavities (rib interiors) are never reached, so they are
    never labelled.
    """
    tree = cKDTree(points_unit)
    d8, _ = tree.query(points_unit[:: max(1, len(points_unit) // 50_000)], k=min(9, len(points_unit)), workers=-1)
    block = block_factor * float(np.median(d8[:, -1]))
    lo, hi = points_unit.min(0), points_unit.max(0)
    spacing = max(block / 2.0, float((hi - lo).max() + 8 * block) / max_cells)
    origin = lo - 3 * block
    shape = np.ceil((hi - lo + 6 * block) / spacing).astype(int) + 1
    hit = np.zeros(shape, bool)
    ijk = np.clip(np.round((points_unit - origin) / spacing).astype(int), 0, shape - 1)
    hit[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    # distance from each voxel centre to the nearest voxel holding a point (+ half a voxel of slack)
    blocked = ndimage.distance_transform_edt(~hit) * spacing <= block + 0.5 * spacing
    labels, _ = ndimage.label(~blocked)
    border = np.unique(np.concatenate([labels[[0, -1]].ravel(), labels[:, [0, -1]].ravel(), labels[:, :, [0, -1]].ravel()]))
    outside = np.isin(labels, border[border > 0])
    return outside, blocked, spacing, origin - 0.5 * spacing


def oriented_normals(points_unit: np.ndarray, outside: np.ndarray, spacing: float, origin: np.ndarray, k: int = 16) -> np.ndarray:
    """(N, 3) unit normals by PCA over k neighbours, flipped to point towards the flood-filled outside
    (the gradient of a smoothed outside indicator). This orients the unoriented input from the data."""
    _, nn = cKDTree(points_unit).query(points_unit, k=min(k, len(points_unit)))
    nb = points_unit[nn] - points_unit[nn].mean(axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(nb, full_matrices=False)
    normals = vt[:, -1, :]
    smooth = ndimage.gaussian_filter(outside.astype(np.float32), 1.0)
    coords = ((points_unit - origin) / spacing - 0.5).T
    grad = np.stack([ndimage.map_coordinates(np.gradient(smooth, axis=a), coords, order=1) for a in range(3)], 1)
    flip = np.einsum("ij,ij->i", normals, grad) < 0
    normals[flip] *= -1
    return normals


def space_labels(points_unit: np.ndarray, rng: np.random.Generator, n_free: int = 400_000,
                 offset_fraction: float = 0.5) -> SpaceLabels:
    """Free-space points (half near the surface, within 4 voxels of the dilated input, half anywhere
    outside) and near-surface inside/outside pairs at +-offset along the oriented normals, with
    offset = offset_fraction x the flood-fill spacing (a length derived from the sampling density)."""
    outside, blocked, spacing, origin = outside_mask(points_unit)
    near = outside & ndimage.binary_dilation(blocked, iterations=8)
    pools = []
    for mask, n in ((near, n_free // 2), (outside, n_free - n_free // 2)):
        cells = np.argwhere(mask)
        if len(cells):
            pick = cells[rng.integers(0, len(cells), n)]
            pools.append(origin + (pick + rng.random((n, 3))) * spacing)
    free = np.concatenate(pools).astype(np.float32) if pools else np.zeros((0, 3), np.float32)
    normals = oriented_normals(points_unit, outside, spacing, origin)
    offset = offset_fraction * 2 * spacing  # in units of the blocking radius (2 voxels)
    free_distance = cKDTree(points_unit).query(free, k=1, workers=-1)[0].astype(np.float32) if len(free) else np.zeros(0, np.float32)
    return SpaceLabels(free, free_distance, (points_unit - offset * normals).astype(np.float32),
                       (points_unit + offset * normals).astype(np.float32), spacing, offset)


# --- the method ------------------------------------------------------------------------------


def _arch(cfg: SparseOccConfig) -> dict:
    if cfg.network == "mlp":
        return {"name": "NeuralPullMLP", "kwargs": {"out_dim": 2, "hidden": cfg.mlp_hidden, "layers": cfg.mlp_layers}}
    if cfg.network == "grid":
        return {
            "name": "GridOccupancyField",
            "kwargs": {
                "n_levels": cfg.grid_levels,
                "features": cfg.grid_features,
                "log2_table": cfg.grid_log2_table,
                "base_resolution": cfg.grid_base_resolution,
                "max_resolution": cfg.grid_max_resolution,
                "hidden": cfg.grid_hidden,
            },
        }
    raise ValueError(f"unknown network {cfg.network!r}")


def margin_and_gradient(module: torch.nn.Module, q: torch.Tensor, method: str, fd_step: float):
    """U(q) (B,) and grad U(q) (B, 3), differentiable w.r.t. the weights.

    "autograd": exact gradient through a double backward. "finite_difference": central differences
    (6 extra evaluations) — cheaper for grid encodings and smoother across grid cells."""
    if method == "autograd":
        q = q.requires_grad_(True)
        u = margin_uncertainty(module(q))
        (g,) = torch.autograd.grad(u.sum(), q, create_graph=True)
        return u, g
    eye = torch.eye(3, dtype=q.dtype, device=q.device) * fd_step
    stacked = torch.cat([q, (q[:, None, :] + eye).reshape(-1, 3)])
    u_all = margin_uncertainty(module(stacked))
    b = q.shape[0]
    u = u_all[:b]
    g = (u_all[b:].view(b, 3) - u[:, None]) / fd_step
    return u, g


class SparseOcc(Method):
    """SparseOcc occupancy fitting (paper eq. 1-2) with RibPull's optional free-space term."""

    name = "sparseocc"
    config_class = SparseOccConfig
    presets: ClassVar[dict] = {"paper": paper_config, "default": default_config, "smoke": smoke_config}

    def fit(self, points_unit: np.ndarray, device: torch.device, progress: ProgressFn | None = None,
            should_cancel: CancelFn | None = None) -> FittedField:
        cfg: SparseOccConfig = self.config
        t0 = time.perf_counter()
        seed_everything(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        pts = np.asarray(points_unit, dtype=np.float64)
        if len(pts) > cfg.max_input_points:  # the loss only needs a dense enough sample
            pts = pts[rng.choice(len(pts), cfg.max_input_points, replace=False)]
        queries, nearest = self._queries(pts, rng)
        q_all = torch.from_numpy(queries).to(device)
        target_all = torch.from_numpy(pts.astype(np.float32)).to(device)[torch.from_numpy(nearest).to(device)]
        pts_t = torch.from_numpy(pts.astype(np.float32)).to(device)
        labels = space_labels(pts, rng, offset_fraction=cfg.near_surface_offset) if (cfg.free_space_weight > 0 or cfg.near_surface_weight > 0) else None
        free = torch.from_numpy(labels.free).to(device) if labels is not None and cfg.free_space_weight > 0 else None
        # hinge margins: half the distance to the data (free space, capped) and half the normal offset
        free_margin = torch.from_numpy(np.minimum(0.5 * labels.free_distance, 0.5)).to(device) if free is not None else None
        near_margin = 0.5 * labels.offset if labels is not None else 0.0
        near = (torch.from_numpy(np.concatenate([labels.near_in, labels.near_out])).to(device)
                if labels is not None and cfg.near_surface_weight > 0 else None)
        lo = torch.from_numpy(pts.min(0).astype(np.float32)).to(device) - 0.05
        hi = torch.from_numpy(pts.max(0).astype(np.float32)).to(device) + 0.05

        arch = _arch(cfg)
        module = build_module(arch).to(device)
        if cfg.network == "grid":
            groups = [{"params": module.embedding.parameters(), "base_lr": cfg.grid_lr},
                      {"params": module.decoder.parameters(), "base_lr": cfg.lr}]
            fd_step = module.finest_cell if cfg.gradient == "finite_difference" else cfg.fd_step
        else:
            groups = [{"params": module.parameters(), "base_lr": cfg.lr}]
            fd_step = cfg.fd_step
        for g in groups:
            g["lr"] = g["base_lr"]
        opt = torch.optim.Adam(groups, lr=cfg.lr, fused=(device.type == "cpu"))
        gen = torch.Generator(device=device).manual_seed(cfg.seed)
        report = ProgressThrottle(progress, cfg.iterations)
        history: list[float] = []
        window_means: list[float] = []
        it = 0
        for it in range(cfg.iterations):
            if it % 10 == 0:
                check_cancel(should_cancel)
            for g in groups:
                g["lr"] = warmup_cosine_lr(it, cfg.iterations, g["base_lr"], cfg.warmup, cfg.final_lr_ratio)
            loss = self._step_loss(module, it, q_all, target_all, pts_t, (free, free_margin), (near, near_margin), lo, hi, fd_step, gen)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            lv = float(loss.detach())
            history.append(lv)
            report(it, lv)
            if self._converged(history, window_means, it):
                break
        iterations_run = it + 1
        fitted = FittedField(module=module.eval(), kind="occupancy", arch=arch, method=self.name, config=asdict(cfg),
                             iterations_run=iterations_run, fit_seconds=time.perf_counter() - t0,
                             loss_history=history[:: max(1, len(history) // 500)])
        # RibPull meshes at the median of U over the input points (paper, Figure 3 caption)
        fitted.level = float(np.median(fitted.evaluate(pts.astype(np.float32))["U"]))
        return fitted

    def _step_loss(self, module, it, q_all, target_all, pts_t, free_and_margin, near_and_margin, lo, hi, fd_step, gen) -> torch.Tensor:
        """Total loss of one iteration. All points of the iteration go through the network in ONE
        forward pass (on a CPU the per-call overhead dominates small batches), then each term takes
        its slice: pull queries (+ finite-difference probes), entropy points, free space, near surface."""
        cfg: SparseOccConfig = self.config
        (free, free_margin), (near, near_margin) = free_and_margin, near_and_margin
        device = q_all.device
        idx = torch.randint(0, len(q_all), (cfg.batch_size,), device=device, generator=gen)
        q, target = q_all[idx], target_all[idx]
        j0, j1 = cfg.query_jitter
        if j0 > 0 or j1 > 0:
            q = q + (j0 + (j1 - j0) * it / max(1, cfg.iterations - 1)) * torch.randn(q.shape, device=device, generator=gen)
        if cfg.gradient == "autograd":
            u, grad_u = margin_and_gradient(module, q.clone(), "autograd", fd_step)
            parts: dict[str, torch.Tensor] = {}
        else:
            eye = torch.eye(3, dtype=q.dtype, device=device) * fd_step
            parts = {"q": q, "probe": (q[:, None, :] + eye).reshape(-1, 3)}
        w_entropy = minimax_weight(it, cfg.n_minimax)
        use_entropy = w_entropy > 1e-6 and (cfg.lambda_max > 0 or cfg.lambda_min > 0)
        if use_entropy:
            parts["uniform"] = lo + (hi - lo) * torch.rand((cfg.entropy_uniform_points, 3), device=device, generator=gen)
            parts["on_input"] = pts_t[torch.randint(0, len(pts_t), (cfg.entropy_input_points,), device=device, generator=gen)]
        if free is not None and len(free):
            fidx = torch.randint(0, len(free), (cfg.free_space_points,), device=device, generator=gen)
            parts["free"] = free[fidx]
        if near is not None:
            nidx = torch.randint(0, len(near), (cfg.near_surface_points,), device=device, generator=gen)
            parts["near"] = near[nidx]
        logits = dict(zip(parts, torch.split(module(torch.cat(list(parts.values()))), [len(v) for v in parts.values()]))) if parts else {}
        if cfg.gradient != "autograd":
            u = margin_uncertainty(logits["q"])
            grad_u = (margin_uncertainty(logits["probe"]).view(-1, 3) - u[:, None]) / fd_step  # forward differences
        loss = sampling_loss(pull_to_surface(q, u, grad_u), target, cfg.sampling_weight)
        if use_entropy:
            loss = loss + w_entropy * minimax_entropy_loss(logits["uniform"], logits["on_input"], cfg.lambda_min, cfg.lambda_max)
        if "free" in logits:
            u_free = margin_uncertainty(logits["free"])
            loss = loss + cfg.free_space_weight * sign_margin_loss(u_free, torch.zeros_like(u_free, dtype=torch.bool), free_margin[fidx])
        if "near" in logits:
            inside = nidx < len(near) // 2  # the first half of `near` are the inside points
            u_near = margin_uncertainty(logits["near"])
            loss = loss + cfg.near_surface_weight * sign_margin_loss(u_near, inside, torch.full_like(u_near, near_margin))
        return loss

    def _queries(self, pts: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Neural-Pull queries, split evenly over `query_scales`."""
        cfg: SparseOccConfig = self.config
        base = 0.25 * math.sqrt(len(pts) / 20000.0)
        per = cfg.n_queries // len(cfg.query_scales)
        tree = cKDTree(pts)
        sigma = knn_sigma(pts, cfg.knn)
        qs, nn = zip(*(sample_pull_queries(pts, per, rng, k=cfg.knn, scale=base * s, sigma=sigma, tree=tree)
                       for s in cfg.query_scales))
        return np.concatenate(qs), np.concatenate(nn)

    def _converged(self, history: list[float], window_means: list[float], it: int) -> bool:
        cfg: SparseOccConfig = self.config
        w = cfg.early_stop_window
        if w <= 0 or (it + 1) % w != 0:
            return False
        window_means.append(float(np.mean(history[-w:])))
        if it + 1 < cfg.early_stop_min_fraction * cfg.iterations or len(window_means) < 2:
            return False
        prev, last = window_means[-2], window_means[-1]
        return (prev - last) < cfg.early_stop_rel_tol * abs(prev)
