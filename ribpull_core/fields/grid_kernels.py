"""Compiled CPU kernels (numba) for the hash-grid encoding: forward gather and backward scatter.

Pure-PyTorch encoding spends most of its time in elementwise index arithmetic on (B, L, 8)
tensors; fusing it into one loop per point makes a CPU training step several times cheaper. The
kernels compute exactly what `GridOccupancyField._encode_torch` computes (same corner order, same
hash), without a gradient w.r.t. the input points (finite-difference training does not need one).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

_P1 = np.int64(2654435761)
_P2 = np.int64(805459861)


@njit(parallel=True, fastmath=True, cache=True)
def _encode_forward(x, table, res, sizes, offsets, dense, domain, out, idx_out, w_out, keep):  # pragma: no cover - compiled
    n_points = x.shape[0]
    n_levels = res.shape[0]
    n_feat = table.shape[1]
    for b in prange(n_points):
        u = np.empty(3, np.float32)
        for k in range(3):
            v = min(max(x[b, k], -domain), domain)
            u[k] = (v + domain) / (2.0 * domain)
        for lev in range(n_levels):
            r = res[lev]
            px, py, pz = u[0] * r, u[1] * r, u[2] * r
            ix, iy, iz = min(math.floor(px), r - 1), min(math.floor(py), r - 1), min(math.floor(pz), r - 1)
            fx, fy, fz = px - ix, py - iy, pz - iz
            ix, iy, iz = np.int64(ix), np.int64(iy), np.int64(iz)
            r1 = np.int64(r + 1)
            for c in range(8):
                bx, by, bz = (c >> 2) & 1, (c >> 1) & 1, c & 1
                cx, cy, cz = ix + bx, iy + by, iz + bz
                if dense[lev]:
                    h = cx * r1 * r1 + cy * r1 + cz
                else:
                    h = (cx ^ (cy * _P1) ^ (cz * _P2)) & (sizes[lev] - 1)
                row = offsets[lev] + h
                w = (fx if bx else 1.0 - fx) * (fy if by else 1.0 - fy) * (fz if bz else 1.0 - fz)
                if keep:  # corners and weights for the backward pass (training only)
                    idx_out[b, lev, c] = row
                    w_out[b, lev, c] = w
                for f in range(n_feat):
                    out[b, lev * n_feat + f] += w * table[row, f]


@njit(parallel=True, fastmath=True, cache=True)
def _encode_backward(grad_out, idx, w, n_feat, grad_table):  # pragma: no cover - compiled
    n_points, n_levels = idx.shape[0], idx.shape[1]
    # levels own disjoint table rows, so one thread per level scatters without races
    for lev in prange(n_levels):
        for b in range(n_points):
            for c in range(8):
                row = idx[b, lev, c]
                wc = w[b, lev, c]
                for f in range(n_feat):
                    grad_table[row, f] += wc * grad_out[b, lev * n_feat + f]


class HashGridEncode(torch.autograd.Function):
    """features = encode(x; table) with a gradient for `table` only (CPU, float32)."""

    @staticmethod
    def forward(ctx, x, table, res, sizes, offsets, dense, domain):
        xn = x.detach().contiguous().numpy().astype(np.float32, copy=False)
        tn = table.detach().contiguous().numpy()
        n, n_levels, n_feat = xn.shape[0], res.shape[0], tn.shape[1]
        out = np.zeros((n, n_levels * n_feat), np.float32)
        idx = np.empty((n, n_levels, 8), np.int64)
        w = np.empty((n, n_levels, 8), np.float32)
        _encode_forward(xn, tn, res, sizes, offsets, dense, np.float32(domain), out, idx, w, True)
        ctx.save_for_backward(torch.from_numpy(idx), torch.from_numpy(w))
        ctx.table_shape = tuple(table.shape)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        idx, w = ctx.saved_tensors
        grad_table = np.zeros(ctx.table_shape, np.float32)
        _encode_backward(grad_out.contiguous().numpy().astype(np.float32, copy=False), idx.numpy(), w.numpy(),
                         ctx.table_shape[1], grad_table)
        return None, torch.from_numpy(grad_table), None, None, None, None, None


def encode_inference(x: torch.Tensor, table: torch.Tensor, res, sizes, offsets, dense, domain) -> torch.Tensor:
    """The forward of `HashGridEncode` without keeping corners and weights (no gradient): meshing,
    SDF and queries evaluate millions of points, and the (B, L, 8) arrays cost more than the gather."""
    xn = x.detach().contiguous().numpy().astype(np.float32, copy=False)
    tn = table.detach().contiguous().numpy()
    out = np.zeros((xn.shape[0], res.shape[0] * tn.shape[1]), np.float32)
    unused_idx, unused_w = np.empty((1, 1, 1), np.int64), np.empty((1, 1, 1), np.float32)
    _encode_forward(xn, tn, res, sizes, offsets, dense, np.float32(domain), out, unused_idx, unused_w, False)
    return torch.from_numpy(out)


def numba_available() -> bool:
    return numba is not None
