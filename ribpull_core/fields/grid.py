"""A multi-resolution hash-grid occupancy field (Instant-NGP-style encoding, pure PyTorch).

Why: the paper's 8x256 MLP costs ~458 ms per iteration on a 2-core CPU. A grid encoding puts most of
the capacity in table look-ups, so a tiny decoder MLP suffices and an iteration costs a fraction of
that. Tables are one `nn.Embedding` trained with fused dense Adam (`methods.optimizer`; on a CPU, coalescing sparse gradients
costs more than updating the whole table); coarse levels whose grid fits in the table are indexed densely (no hash
collisions). Output: 2 logits [out, in] like SparseOcc, plus a prior so U has a usable gradient
from the first iteration: a sphere (inside radius `init_radius`), or, when the input states its
solid (a label map), that solid's signed distance (`prior_shape`, `set_prior`): a warm start whose
zero set is already the map's surface, which the training only corrects.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

# Instant-NGP's spatial hash primes
_PRIMES = (1, 2654435761, 805459861)
# 8 corner offsets of a cell, (8, 3)
_CORNERS = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.int64)


class GridOccupancyField(nn.Module):
    """(B, 3) unit-frame points in [-domain, domain]^3 -> (B, 2) logits [out, in].

    n_levels resolutions grow geometrically from base_resolution to max_resolution cells across the
    domain; each level stores `features` floats per vertex in a table of 2^log2_table rows.
    """

    def __init__(
        self,
        n_levels: int = 12,
        features: int = 2,
        log2_table: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 512,
        hidden: int = 64,
        hidden_layers: int = 2,
        domain: float = 1.2,
        init_radius: float = 0.5,
        prior_slope: float = 4.0,
        prior_shape: tuple[int, int, int] | list[int] | None = None,
    ):
        super().__init__()
        self.n_levels, self.features, self.domain = n_levels, features, domain
        self.init_radius, self.prior_slope = init_radius, prior_slope
        self.has_distance_prior = prior_shape is not None
        if self.has_distance_prior:
            # saved with the weights (persistent), so a loaded field has the same prior
            self.register_buffer("prior_distance", torch.zeros((1, 1, *(int(n) for n in prior_shape))))
            self.register_buffer("prior_to_grid", torch.zeros(3, 4))
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(1, n_levels - 1))
        res = [math.floor(base_resolution * growth**i) for i in range(n_levels)]
        table = 2**log2_table
        sizes = [min(table, (r + 1) ** 3) for r in res]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self.register_buffer("resolutions", torch.tensor(res, dtype=torch.int64), persistent=False)
        self.register_buffer("table_sizes", torch.tensor(sizes, dtype=torch.int64), persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.int64), persistent=False)
        self.register_buffer("dense", torch.tensor([(r + 1) ** 3 <= table for r in res]), persistent=False)
        # dense levels come first because resolutions grow
        self.n_dense = int(sum((r + 1) ** 3 <= table for r in res))
        self.embedding = nn.Embedding(int(sum(sizes)), features)
        nn.init.uniform_(self.embedding.weight, -1e-4, 1e-4)
        layers: list[nn.Module] = []
        d = n_levels * features
        for _ in range(hidden_layers):
            layers += [nn.Linear(d, hidden), nn.ReLU()]
            d = hidden
        last = nn.Linear(d, 2)
        nn.init.normal_(last.weight, 0.0, 1e-3)
        nn.init.zeros_(last.bias)
        self.decoder = nn.Sequential(*layers, last)

    @property
    def finest_cell(self) -> float:
        """Edge of the finest grid cell in unit-frame units."""
        return 2 * self.domain / float(self.resolutions[-1])

    def _level_indices(self, lo_hi: torch.Tensor, levels: slice, dense: bool) -> torch.Tensor:
        """Table rows of the 8 cell corners for a group of levels. lo_hi: (B, L, 3, 2) -> (B, l, 8)."""
        c = lo_hi[:, levels]
        b, n = c.shape[:2]
        ix, iy, iz = c[:, :, 0], c[:, :, 1], c[:, :, 2]  # (B, l, 2)
        if dense:
            r1 = (self.resolutions[levels] + 1).view(1, -1, 1)
            idx = (ix * (r1 * r1)).view(b, n, 2, 1, 1) + (iy * r1).view(b, n, 1, 2, 1) + iz.view(b, n, 1, 1, 2)
        else:
            mask = (self.table_sizes[levels] - 1).view(1, -1, 1, 1, 1)
            idx = (
                ix.view(b, n, 2, 1, 1)
                ^ (iy * _PRIMES[1]).view(b, n, 1, 2, 1)
                ^ (iz * _PRIMES[2]).view(b, n, 1, 1, 2)
            ) & mask
        return idx.reshape(b, n, 8) + self.offsets[levels].view(1, -1, 1)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3) -> (B, n_levels * features) trilinearly interpolated features.

        On a CPU, when no gradient w.r.t. x is needed, the compiled kernels in grid_kernels run the
        same computation several times faster; otherwise (CUDA, autograd w.r.t. x) it is pure torch.
        """
        if x.device.type == "cpu" and not x.requires_grad and x.dtype == torch.float32:
            from .grid_kernels import HashGridEncode, encode_inference

            if not torch.is_grad_enabled():
                return encode_inference(x, self.embedding.weight, *self._kernel_args())
            return HashGridEncode.apply(x, self.embedding.weight, *self._kernel_args())
        return self._encode_torch(x)

    def _kernel_args(self):
        if getattr(self, "_np_args", None) is None:
            self._np_args = (self.resolutions.cpu().numpy(), self.table_sizes.cpu().numpy(),
                             self.offsets.cpu().numpy(), self.dense.cpu().numpy(), float(self.domain))
        return self._np_args

    def _encode_torch(self, x: torch.Tensor) -> torch.Tensor:
        """Pure-torch encoding, differentiable w.r.t. x and the tables.

        Index and weight arithmetic is done per axis on (B, L, 2) tensors and combined by
        broadcasting to the 8 corners, which is several times cheaper on a CPU than per-corner
        arithmetic; dense and hashed levels are indexed separately (no wasted hashing).
        """
        b, n_lev = x.shape[0], self.n_levels
        u = (x.clamp(-self.domain, self.domain) + self.domain) / (2 * self.domain)  # (B, 3) in [0, 1]
        pos = u.unsqueeze(1) * self.resolutions.view(1, -1, 1).to(x.dtype)  # (B, L, 3)
        # the last cell owns the upper face, so a point clamped onto the domain edge stays in range
        base = torch.minimum(pos.detach().floor(), (self.resolutions - 1).view(1, -1, 1).to(x.dtype))
        frac = pos - base  # keeps the gradient w.r.t. x
        base = base.long()
        lo_hi = torch.stack([base, base + 1], dim=-1)  # (B, L, 3, 2)
        n_dense = self.n_dense
        parts = []
        if n_dense:
            parts.append(self._level_indices(lo_hi, slice(0, n_dense), True))
        if n_dense < n_lev:
            parts.append(self._level_indices(lo_hi, slice(n_dense, n_lev), False))
        idx = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
        feats = self.embedding(idx.reshape(-1)).view(b * n_lev, 8, self.features)
        wlo = 1 - frac
        wx, wy, wz = (torch.stack([wlo[..., k], frac[..., k]], dim=-1) for k in range(3))  # (B, L, 2)
        w = (wx.view(b, n_lev, 2, 1, 1) * wy.view(b, n_lev, 1, 2, 1) * wz.view(b, n_lev, 1, 1, 2)).reshape(b * n_lev, 1, 8)
        return torch.bmm(w, feats).reshape(b, n_lev * self.features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        logits = self.decoder(self.encode(x))
        if self.has_distance_prior:
            # in-logit minus out-logit ~ -2*slope*distance: U starts as the input's own solid
            prior = -self.prior_slope * self.prior_signed_distance(x)
        else:
            # sphere prior: in-logit minus out-logit ~ 2*slope*(r - |x|), so U starts as a smooth sphere
            prior = self.prior_slope * (self.init_radius - x.norm(dim=-1, keepdim=True))
        return logits + torch.cat([-prior, prior], dim=-1)

    def set_prior(self, distance_unit: np.ndarray, unit_to_index: np.ndarray) -> None:
        """Set the signed-distance prior (the module must be built with prior_shape = its shape).

        distance_unit: (X, Y, Z) signed distance (unit-frame units, negative inside) at the nodes of
        a grid; unit_to_index: (3, 4) affine from a unit-frame point to its (fractional) node index.
        """
        shape = tuple(self.prior_distance.shape[2:])
        if tuple(distance_unit.shape) != shape:
            raise ValueError(f"prior of shape {distance_unit.shape} for a field built for {shape}")
        a = np.asarray(unit_to_index, dtype=np.float64)
        # grid_sample wants coordinates in [-1, 1] (align_corners) ordered (Z, Y, X) of the volume
        scale = 2.0 / np.maximum(np.asarray(shape, dtype=np.float64) - 1.0, 1.0)
        to_grid = scale[:, None] * a
        to_grid[:, 3] -= 1.0
        with torch.no_grad():
            self.prior_distance.copy_(torch.as_tensor(np.asarray(distance_unit, dtype=np.float32))[None, None])
            self.prior_to_grid.copy_(torch.as_tensor(to_grid[::-1].copy(), dtype=torch.float32))

    def prior_signed_distance(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3) unit-frame points -> (B, 1) the prior's signed distance (trilinear; beyond its grid
        the value at the nearest border node)."""
        g = x @ self.prior_to_grid[:, :3].T + self.prior_to_grid[:, 3]
        d = torch.nn.functional.grid_sample(self.prior_distance, g.view(1, -1, 1, 1, 3).to(self.prior_distance.dtype),
                                            mode="bilinear", padding_mode="border", align_corners=True)
        return d.view(-1, 1).to(x.dtype)
