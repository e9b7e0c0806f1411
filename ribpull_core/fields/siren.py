"""SIREN field used by the DiGS baseline (sine activations, optional geometric initialisations).

Facts followed (DiGS, Ben-Shabat et al. 2022, public code Chumbyte/DiGS, models/DiGS.py):
every hidden layer computes sin(omega * (W h + b)) with omega = 30, the output layer is linear.
Three initialisations:

- ``"siren"``: SIREN's (Sitzmann et al. 2020): W ~ U(+-sqrt(6/n_in)/omega), first layer U(+-1/n_in);
  the raw output is the field.
- ``"geometric_sine"``: DiGS's geometric sine init. Every layer W ~ U(+-sqrt(3/n_out))/omega,
  b ~ U(+-1/(1000 n_out))/omega; the last hidden layer is (pi/2 I + 0.001 N)/omega with bias
  (pi/2 + 0.001 N)/omega, so it computes cos(pi/2 h) ~ 1 - pi^2 h^2 / 8; the output layer has
  W = -1 (+1e-5 N), b = n_in, i.e. o = sum_j (1 - cos(pi/2 h_j)) >= 0, growing away from the origin.
  The output is then reshaped into an approximate sphere SDF:
  f = scale * (sign(o) sqrt(|o| + 1e-8) - radius)   (sphere_radius = 1.6, sphere_scale = 0.1 in the
  DiGS surface-reconstruction script).
- ``"mfgi"`` (multi-frequency geometric init, DiGS's default for surface reconstruction): as
  ``"geometric_sine"``, but the first layer's rows are split into groups by ``period_portions`` whose
  weights are scaled so each group spans ``periods`` periods of the sine over the input range
  (25 % low frequency, 75 % up to omega), and the second layer only connects the low-frequency block
  (the rest is scaled by 5e-4), so the initial field is still a smooth sphere but high frequencies are
  available to the optimiser.

Sign: with the geometric inits the output is negative near the origin and positive far away, i.e.
negative INSIDE, which is RibPull's `FittedField` "sdf" convention; no flip is needed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

INIT_TYPES = ("siren", "geometric_sine", "mfgi")


class SirenMLP(nn.Module):
    """(B, in_dim) unit-frame points -> (B, out_dim).

    Layers: Linear(in_dim, hidden), `hidden_layers` x Linear(hidden, hidden), Linear(hidden, out_dim);
    sin(omega * .) after every layer but the last. DiGS surface reconstruction: hidden=256,
    hidden_layers=4, init="mfgi". All arguments are plain JSON values so `FittedField.arch` can
    rebuild the module.
    """

    def __init__(
        self,
        in_dim: int = 3,
        out_dim: int = 1,
        hidden: int = 256,
        hidden_layers: int = 4,
        omega: float = 30.0,
        init: str = "mfgi",
        sphere_radius: float = 1.6,
        sphere_scale: float = 0.1,
        periods: Sequence[float] = (1.0, 30.0),
        period_portions: Sequence[float] = (0.25, 0.75),
    ):
        super().__init__()
        if init not in INIT_TYPES:
            raise ValueError(f"unknown SIREN init {init!r}; choose one of {INIT_TYPES}")
        if init != "siren" and (out_dim != 1 or hidden_layers < 1):
            raise ValueError("geometric SIREN inits need out_dim=1 and at least one hidden layer")
        if init == "mfgi" and hidden_layers < 2:
            raise ValueError("mfgi needs hidden_layers >= 2 (its second and last hidden layers differ)")
        self.omega = float(omega)
        self.init = init
        self.sphere_radius = float(sphere_radius)
        self.sphere_scale = float(sphere_scale)
        self.first = nn.Linear(in_dim, hidden)
        self.hidden_layers = nn.ModuleList(nn.Linear(hidden, hidden) for _ in range(hidden_layers))
        self.output = nn.Linear(hidden, out_dim)
        with torch.no_grad():
            if init == "siren":
                self._init_siren()
            else:
                self._init_geometric_sine()
                if init == "mfgi":
                    self._init_mfgi(list(periods), list(period_portions))

    # --- initialisations ----------------------------------------------------------------------

    def _layers(self) -> list[nn.Linear]:
        return [self.first, *self.hidden_layers, self.output]

    def _init_siren(self) -> None:
        for lin in self._layers():
            bound = math.sqrt(6.0 / lin.in_features) / self.omega
            lin.weight.uniform_(-bound, bound)
        self.first.weight.uniform_(-1.0 / self.first.in_features, 1.0 / self.first.in_features)

    def _init_geometric_sine(self) -> None:
        for lin in self._layers():
            n_out = lin.out_features
            bound = math.sqrt(3.0 / n_out)
            lin.weight.uniform_(-bound, bound).div_(self.omega)
            lin.bias.uniform_(-1.0 / (1000.0 * n_out), 1.0 / (1000.0 * n_out)).div_(self.omega)
        last_hidden = self.hidden_layers[-1]
        n = last_hidden.out_features
        last_hidden.weight.copy_((0.5 * math.pi * torch.eye(n) + 1e-3 * torch.randn(n, n)) / self.omega)
        last_hidden.bias.copy_((0.5 * math.pi * torch.ones(n) + 1e-3 * torch.randn(n)) / self.omega)
        n_in = self.output.in_features
        self.output.weight.copy_(-torch.ones(1, n_in) + 1e-5 * torch.randn(1, n_in))
        self.output.bias.fill_(float(n_in))

    def _init_mfgi(self, periods: list[float], portions: list[float]) -> None:
        n_hidden = self.first.out_features
        counts = [int(p * n_hidden) for p in portions]
        if len(counts) != len(periods) or sum(counts) != n_hidden:
            raise ValueError(f"period_portions {portions} must split hidden={n_hidden} exactly, one per period")
        n_in = self.first.in_features
        rows = []
        for period, count in zip(periods, counts):
            bound = math.sqrt(3.0 / n_in) * period / self.omega
            rows.append(torch.empty(count, n_in).uniform_(-bound, bound))
        self.first.weight.copy_(torch.cat(rows, 0))
        # second layer: only the low-frequency block is connected at full strength. (The reference's
        # range for the damped part is U(-sqrt(3/n), sqrt(3/n)/30) * 5e-4, asymmetric; kept as is.)
        second = self.hidden_layers[0]
        n = second.in_features
        k = counts[0]
        w = torch.empty(n, n).uniform_(-math.sqrt(3.0 / n), math.sqrt(3.0 / n) / self.omega) * 5e-4
        w[:k, :k] = torch.empty(k, k).uniform_(-math.sqrt(3.0 / n) / self.omega, math.sqrt(3.0 / n) / self.omega)
        second.weight.copy_(w)

    # --- forward ------------------------------------------------------------------------------

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = torch.sin(self.omega * self.first(x))
        for lin in self.hidden_layers:
            h = torch.sin(self.omega * lin(h))
        out = self.output(h)
        if self.init != "siren":
            # DiGS's sphere reshaping of the geometric inits: sqrt turns o ~ c|x|^2 into ~|x|
            out = torch.sign(out) * torch.sqrt(out.abs() + 1e-8)
            out = (out - self.sphere_radius) * self.sphere_scale
        return out
