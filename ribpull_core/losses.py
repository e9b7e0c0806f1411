"""Loss terms, one function per equation of the paper (and per baseline's published loss).

All tensors are in the unit frame. Shapes: queries (B, 3), scalar fields (B,), gradients (B, 3).
"""

from __future__ import annotations

import torch


def margin_uncertainty(logits: torch.Tensor) -> torch.Tensor:
    """U(x) = p_in(x) - p_out(x) in [-1, 1] from 2 logits [out, in] (SparseOcc; paper eq. 1's U_theta).

    logits: (B, 2) -> (B,). The surface is the zero set of U (RibPull meshes at the median of U at
    the input points instead). Computed as tanh((l_in - l_out) / 2), the same number as the
    difference of the two softmax probabilities, for a fraction of a softmax's cost (which was ~12 %
    of a default training step on a CPU)."""
    return torch.tanh(0.5 * (logits[..., 1] - logits[..., 0]))


def pull_to_surface(queries: torch.Tensor, value: torch.Tensor, grad: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """One Newton-Raphson step onto the zero set: q' = q - value(q) * grad / ||grad|| (paper eq. 1).

    queries (B, 3), value (B,), grad (B, 3) -> (B, 3). The denominator is the plain norm, as in the
    reference code (not squared)."""
    n = grad.norm(dim=-1, keepdim=True).clamp_min(eps)
    return queries - value[:, None] * grad / n


def sampling_loss(pulled: torch.Tensor, nearest_input: torch.Tensor, weight: float = 10.0) -> torch.Tensor:
    """L_samp (paper eq. 1) as coded: weight * mean ||q' - p_nn(q)||_2 (L2 norm, not squared).

    pulled, nearest_input: (B, 3) -> scalar."""
    return weight * (pulled - nearest_input).norm(dim=-1).mean()


def binary_entropy_from_logits(logits: torch.Tensor) -> torch.Tensor:
    """H = -sum_c p_c log p_c per point from 2 logits. (B, 2) -> (B,), in nats."""
    logp = torch.log_softmax(logits, dim=-1)
    return -(logp.exp() * logp).sum(dim=-1)


def minimax_entropy_loss(
    logits_uniform: torch.Tensor, logits_input: torch.Tensor, lambda_min: float, lambda_max: float
) -> torch.Tensor:
    """L_entr (paper eq. 2): minimise entropy at uniform points of the cube, maximise it at input points.

    L = lambda_min * mean H(uniform) - lambda_max * mean H(input points). Scalar."""
    return lambda_min * binary_entropy_from_logits(logits_uniform).mean() - lambda_max * binary_entropy_from_logits(
        logits_input
    ).mean()


def minimax_weight(iteration: int, n_minimax: int) -> float:
    """Decay of the entropy term's weight: 10^(-8 i / n_minimax) (SparseOcc; ~0 after n_minimax)."""
    return 10.0 ** (-8.0 * iteration / max(1, n_minimax))


def sign_margin_loss(u: torch.Tensor, inside: torch.Tensor, margin: torch.Tensor) -> torch.Tensor:
    """RibPull's data-derived supervision as a hinge on the margin uncertainty U (B,).

    Points known to be inside need U >= margin, outside ones U <= -margin; mean relu(margin - y*U)
    with y = +1/-1. The margin (B,) is about half the point's distance to the surface in unit-frame
    units, which agrees with eq. 1's pull: one Newton step of length U lands on the surface only if U
    behaves like a signed distance near it (a cross-entropy would push U to +-1 there instead)."""
    y = inside.to(u.dtype) * 2 - 1
    return torch.relu(margin - y * u).mean()
