"""The Neural-Pull / SparseOcc MLP (8 x 256, ReLU, skip at layer 4, geometric init, weight norm)."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn.utils.parametrizations import weight_norm


class NeuralPullMLP(nn.Module):
    """(B, 3) unit-frame points -> (B, out_dim).

    out_dim=2: occupancy logits [out, in], initialised so logit_out ~ |x| - r and logit_in ~ r - |x|
    (a sphere of radius r = init_radius is "inside"), as SparseOcc does.
    out_dim=1: a signed distance, initialised to |x| - r (Neural-Pull / IGR geometric init).
    The input is re-concatenated before layer `skip` and the concatenation divided by sqrt(2).
    """

    def __init__(
        self,
        out_dim: int = 2,
        hidden: int = 256,
        layers: int = 8,
        skip: int | None = 4,
        init_radius: float = 0.5,
        use_weight_norm: bool = True,
    ):
        super().__init__()
        self.out_dim, self.skip = out_dim, skip
        dims = [3] + [hidden] * layers
        self.hidden_layers = nn.ModuleList()
        for i in range(layers):
            in_dim = dims[i]
            out = dims[i + 1] - 3 if (skip is not None and i + 1 == skip) else dims[i + 1]
            lin = nn.Linear(in_dim, out)
            nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(out))
            nn.init.zeros_(lin.bias)
            if skip is not None and i == skip:
                # the re-injected xyz columns start at zero so the init stays a sphere
                nn.init.zeros_(lin.weight[:, -3:])
            self.hidden_layers.append(weight_norm(lin) if use_weight_norm else lin)
        last = nn.Linear(hidden, out_dim)
        w = torch.randn(1, hidden) * 1e-4 + math.sqrt(math.pi) / math.sqrt(hidden)
        with torch.no_grad():
            if out_dim == 1:
                last.weight.copy_(w)
                last.bias.fill_(-init_radius)
            else:
                last.weight.copy_(torch.cat([w, -w], 0))
                last.bias.copy_(torch.tensor([-init_radius, init_radius]))
        self.output = last
        self.act = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = x
        for i, lin in enumerate(self.hidden_layers):
            if self.skip is not None and i == self.skip:
                h = torch.cat([h, x], dim=-1) / math.sqrt(2)
            h = self.act(lin(h))
        return self.output(h)
