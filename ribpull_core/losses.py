"""Loss terms, one function per equation of the paper (and per baseline's published loss).

All tensors are in the unit frame. Shapes: queries (B, 3), scalar fields (B,), gradients (B, 3).
"""

from __future__ import annotations

import torch


def margin_uncertainty(logits: torch.Tensor) -> torch.Tensor:
    """U(x) = p_in(x) - p_out(x) in [-1, 1] from 2 logits [out, in] (SparseOcc; paper eq. 1's U_theta).

    logits: (B, 2) -> (B,). The surface is the zero set of U (RibPull meshes at the median of U at
    the input points instead)."""
    p = torch.softmax(logits, dim=-1)
    return p[..., 1] - p[..., 0]


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


def neural_pull_loss(pulled: torch.Tensor, nearest_input: torch.Tensor) -> torch.Tensor:
    """Neural-Pull's loss as coded: mean ||q' - p_nn(q)||_2 (plain L2 norm, not squared; weight 1).

    pulled = `pull_to_surface(q, f(q), grad f(q))`, nearest_input = the input point nearest to q.
    (B, 3), (B, 3) -> scalar."""
    return sampling_loss(pulled, nearest_input, weight=1.0)


# --- DiGS baseline (Ben-Shabat et al. 2022, "DiGS: Divergence guided shape implicit neural
# representation for unoriented point clouds"; public code Chumbyte/DiGS, models/losses.py) --------


def spatial_gradient(values: torch.Tensor, points: torch.Tensor, create_graph: bool = True) -> torch.Tensor:
    """grad_x f at each point by autograd. values (B,) or (B, 1) computed from points (B, 3) that
    require grad -> (B, 3). create_graph=True keeps it differentiable (needed by every loss on it)."""
    (g,) = torch.autograd.grad(values.sum(), points, create_graph=create_graph)
    return g


def laplacian(grad: torch.Tensor, points: torch.Tensor, create_graph: bool = True) -> torch.Tensor:
    """Divergence of the gradient field, div(grad f) = sum_i d^2 f / dx_i^2 (DiGS's "divergence").

    grad (B, 3) = `spatial_gradient(f, points)` with create_graph=True; points (B, 3) -> (B,).
    The three vector-Jacobian products (one per axis, as in the DiGS code) run as one batched
    backward pass (~15 % faster on CPU than a loop); NaNs are set to 0 as in the DiGS code."""
    if not grad.requires_grad:  # the gradient does not depend on the points (affine field)
        return torch.zeros(grad.shape[0], dtype=grad.dtype, device=grad.device)
    d = grad.shape[-1]
    basis = torch.eye(d, dtype=grad.dtype, device=grad.device)[:, None, :].expand(d, *grad.shape)
    (h,) = torch.autograd.grad(
        grad, points, grad_outputs=basis, is_grads_batched=True, create_graph=create_graph, materialize_grads=True
    )  # h[i] = d grad_i / d points, (d, B, d)
    div = torch.diagonal(h, dim1=0, dim2=2).sum(-1)
    return torch.nan_to_num(div, nan=0.0)


def digs_manifold_loss(f_surface: torch.Tensor) -> torch.Tensor:
    """DiGS/SIREN "sdf term": mean |f(p)| over input (on-surface) points. (B,) -> scalar; weight 3e3."""
    return f_surface.abs().mean()


def digs_off_surface_loss(f_off: torch.Tensor, alpha: float = 100.0) -> torch.Tensor:
    """DiGS/SIREN "inter term": mean exp(-alpha |f(x)|) over off-surface points, which keeps the zero
    set away from free space. (B,) -> scalar; alpha = 100, weight 1e2."""
    return torch.exp(-alpha * f_off.abs()).mean()


def eikonal_l1_loss(grad: torch.Tensor) -> torch.Tensor:
    """DiGS's eikonal term ("abs" type): mean | ||grad f|| - 1 | over all points given (DiGS uses the
    on- and off-surface gradients together). (B, 3) -> scalar; weight 5e1."""
    return (grad.norm(dim=-1) - 1.0).abs().mean()


def divergence_loss(div: torch.Tensor, clamp_min: float = 0.1, clamp_max: float = 50.0) -> torch.Tensor:
    """DiGS's divergence term ("l1" type): mean clamp(|div grad f|, 0.1, 50) at off-surface points.

    div (B,) = `laplacian(...)` -> scalar. Inside the clamp range it pushes the field towards zero
    divergence (smooth, low-curvature level sets); outside it has no gradient."""
    return torch.clamp(div.abs(), clamp_min, clamp_max).mean()


def divergence_weight(
    iteration: int, total: int, w0: float = 1e2, hold_until: float = 0.2, zero_from: float = 0.4
) -> float:
    """DiGS's annealing of the divergence weight ("linear" decay, params 1e2 0.2 1e2 0.4 0 0):
    w0 until hold_until*total, linear to 0 at zero_from*total, then 0."""
    t = iteration / max(1, total)
    if t < hold_until:
        return w0
    if t >= zero_from:
        return 0.0
    return w0 * (1.0 - (t - hold_until) / (zero_from - hold_until))


def sign_margin_loss(u: torch.Tensor, inside: torch.Tensor, margin: torch.Tensor) -> torch.Tensor:
    """RibPull's data-derived supervision as a hinge on the margin uncertainty U (B,).

    Points known to be inside need U >= margin, outside ones U <= -margin; mean relu(margin - y*U)
    with y = +1/-1. The margin (B,) is about half the point's distance to the surface in unit-frame
    units, which agrees with eq. 1's pull: one Newton step of length U lands on the surface only if U
    behaves like a signed distance near it (a cross-entropy would push U to +-1 there instead)."""
    y = inside.to(u.dtype) * 2 - 1
    return torch.relu(margin - y * u).mean()
