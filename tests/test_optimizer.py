"""The training loop's Adam (ribpull_core/methods/optimizer.py): the same steps as torch.optim.Adam,
without importing torch._dynamo."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
import torch

from ribpull_core.methods.optimizer import FusedAdam, make_optimizer

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device on this machine: FusedAdam's CUDA path is not checked"))]


def _model(seed: int = 0, device: str = "cpu") -> torch.nn.Module:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.Softplus(), torch.nn.Linear(16, 1)).to(device)


def _groups(model: torch.nn.Module) -> list[dict]:
    return [{"params": list(model[0].parameters()), "lr": 1e-2},
            {"params": list(model[2].parameters()), "lr": 3e-3}]


@pytest.mark.parametrize("device", DEVICES)
def test_fused_adam_follows_torch_adam_step_by_step(device):
    ours_model, torch_model = _model(device=device), _model(device=device)
    ours_groups, torch_groups = _groups(ours_model), _groups(torch_model)
    ours, reference = FusedAdam(ours_groups), torch.optim.Adam(torch_groups, fused=True)
    x = torch.randn(64, 3, generator=torch.Generator().manual_seed(1)).to(device)
    for step in range(40):
        for groups in (ours_groups, torch_groups):
            for g in groups:
                g["lr"] *= 0.97  # a schedule changes the rate between steps
        for model, opt in ((ours_model, ours), (torch_model, reference)):
            opt.zero_grad()
            loss = (model(x) ** 2).mean()
            if step % 5 == 4:  # the first layer gets no gradient: skipped, its moments kept
                loss = (model[2](torch.ones(1, 16, device=device)) ** 2).sum()
            loss.backward()
            opt.step()
    for p, q in zip(ours_model.parameters(), torch_model.parameters()):
        torch.testing.assert_close(p, q, rtol=0, atol=1e-7)
    moved = [float((p - q).detach().abs().max()) for p, q in zip(ours_model.parameters(), _model(device=device).parameters())]
    assert min(moved) > 1e-3  # it trained


def test_make_optimizer_keeps_torch_adam_outside_the_fused_case():
    model = _model().double()
    assert isinstance(make_optimizer([{"params": list(model.parameters()), "lr": 1e-3}], torch.device("cpu")),
                      torch.optim.Adam)
    assert isinstance(make_optimizer(_groups(_model()), torch.device("cpu")), FusedAdam)
    assert isinstance(make_optimizer(_groups(_model()), torch.device("cuda")), FusedAdam)  # made, not stepped
    assert isinstance(make_optimizer(_groups(_model()), torch.device("meta")), torch.optim.Adam)


def test_fused_adam_does_not_import_torch_dynamo():
    script = textwrap.dedent("""
        import sys, torch
        from ribpull_core.methods.optimizer import FusedAdam
        m = torch.nn.Linear(3, 1)
        opt = FusedAdam([{"params": list(m.parameters()), "lr": 1e-3}])
        m(torch.ones(2, 3)).sum().backward()
        opt.step()
        print("torch._dynamo" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "False"
