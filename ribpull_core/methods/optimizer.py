"""The training loop's optimiser: Adam on torch's own fused kernel, without torch.optim.Optimizer.

torch.optim.Optimizer imports torch._dynamo the first time one is built in a process (its
add_param_group and step are wrapped by torch._disable_dynamo): ~2.4 s of a 2-core CPU, paid by
every `ribpull fit` from the command line and by every bench run (each its own process), ~10 % of
a whole 60k-point fit. `FusedAdam` runs the same kernel that torch.optim.Adam(fused=True) runs
(aten::_fused_adam_), with torch's defaults (betas 0.9 / 0.999, eps 1e-8, no weight decay, no
AMSGrad), so a fit's trajectory is the same; tests/test_optimizer.py checks it step by step against
torch.optim.Adam. `make_optimizer` keeps torch.optim.Adam for other devices and dtypes.
"""

from __future__ import annotations

import torch

BETAS = (0.9, 0.999)
EPS = 1e-8


class FusedAdam:
    """Adam over param groups, each a dict with "params" (a list of float32 tensors) and "lr"
    (read at every step, so a schedule may change it between steps). The interface the loop
    uses: zero_grad() (gradients set to None, torch.optim's default), step(). Parameters without a gradient in a step are
    skipped and keep their moments, as in torch.optim."""

    def __init__(self, groups: list[dict]):
        self.param_groups = groups
        # per parameter: (exp_avg, exp_avg_sq, step), step a float32 scalar tensor as torch's fused path keeps it
        self.state: dict[torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}

    def zero_grad(self) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                p.grad = None

    def _state_of(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        state = self.state.get(p)
        if state is None:
            state = (torch.zeros_like(p, memory_format=torch.preserve_format),
                     torch.zeros_like(p, memory_format=torch.preserve_format),
                     torch.zeros((), dtype=torch.float32, device=p.device))
            self.state[p] = state
        return state

    @torch.no_grad()
    def step(self) -> None:
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            exp_avgs, exp_avg_sqs, steps = (list(t) for t in zip(*(self._state_of(p) for p in params)))
            torch._foreach_add_(steps, 1)
            torch._fused_adam_(params, [p.grad for p in params], exp_avgs, exp_avg_sqs, [], steps,
                               lr=float(group["lr"]), beta1=BETAS[0], beta2=BETAS[1], weight_decay=0.0,
                               eps=EPS, amsgrad=False, maximize=False)


def make_optimizer(groups: list[dict], device: torch.device):
    """The loop's Adam for param groups ("params" lists, "lr"): `FusedAdam` where every parameter
    is float32 on the CPU or a CUDA device (torch.optim.Adam(fused=True) runs the same kernel on
    both), else torch.optim.Adam. On an H200 machine the _dynamo import was most of a 60k fit's
    set-up: its fit stage went 11.4 -> 5.2 s (docs/benchmarks.md, GPU run).
    """
    fusable = torch.device(device).type in ("cpu", "cuda") and all(
        p.dtype == torch.float32 for g in groups for p in g["params"])
    return FusedAdam(groups) if fusable else torch.optim.Adam(groups)
