"""Neural-Pull and DiGS baselines: loss terms on analytic fields, SIREN init, and end-to-end smoke fits."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from ribpull_core.errors import JobCanceled
from ribpull_core.fields import build_module
from ribpull_core.fields.siren import SirenMLP
from ribpull_core.losses import pull_to_surface
from ribpull_core.methods import build_fit_config, get_method_class
from ribpull_core.methods.base import FitProgress, FittedField
from ribpull_core.methods.digs import (
    DiGS,
    DiGSConfig,
    digs_manifold_loss,
    digs_off_surface_loss,
    divergence_loss,
    divergence_weight,
    eikonal_l1_loss,
    laplacian,
    spatial_gradient,
)
from ribpull_core.methods.neuralpull import NeuralPull, NeuralPullConfig, neural_pull_loss
from ribpull_core.methods.training import with_schedule

CENTRE = np.array([0.05, -0.05, 0.0])
# Not an init sphere (Neural-Pull r=1.0, DiGS's irregular ~0.6-1.4), so the fit must move the surface.
# Centred near the origin like RibPull's unit frame: DiGS's sign comes from its init sphere around the
# origin, and with sphere_scale 0.1 its f hardly goes below -0.16 (sqrt reshaping), so deep interiors
# (radius >~ 0.35) of a smoke-length fit are not reliably negative.
RADIUS = 0.3


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """These networks are tiny: one thread is as fast, and two threads thrash when the machine is busy."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def sphere_points(n: int = 2000, radius: float = RADIUS, centre=CENTRE, seed: int = 1) -> np.ndarray:
    v = np.random.default_rng(seed).standard_normal((n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return (radius * v + centre).astype(np.float32)


def _points(x: np.ndarray) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float32, requires_grad=True)


# --- loss terms on analytic fields -----------------------------------------------------------

def test_eikonal_of_exact_sphere_sdf_is_zero_and_of_scaled_sdf_is_not():
    x = _points(np.random.default_rng(0).uniform(-1, 1, (4000, 3)))
    f = x.norm(dim=-1) - 0.5
    g = spatial_gradient(f, x)
    assert eikonal_l1_loss(g).item() < 1e-5
    g2 = spatial_gradient(3.0 * (x.norm(dim=-1) - 0.5), x)
    assert eikonal_l1_loss(g2).item() == pytest.approx(2.0, abs=1e-4)


def test_divergence_of_linear_field_is_clamped_at_min():
    x = _points(np.random.default_rng(0).uniform(-1, 1, (1000, 3)))
    f = x @ torch.tensor([0.3, -1.2, 2.0]) + 0.7
    div = laplacian(spatial_gradient(f, x), x)
    assert torch.allclose(div, torch.zeros_like(div), atol=1e-6)
    assert divergence_loss(div).item() == pytest.approx(0.1, abs=1e-7)


def test_laplacian_matches_analytic_values():
    pts = np.random.default_rng(2).uniform(0.2, 1.0, (500, 3)) * np.sign(np.random.default_rng(3).uniform(-1, 1, (500, 3)))
    x = _points(pts)
    # f = |x|: laplacian = 2 / |x| in 3D
    div = laplacian(spatial_gradient(x.norm(dim=-1), x), x)
    expected = 2.0 / np.linalg.norm(pts, axis=1)
    np.testing.assert_allclose(div.detach().numpy(), expected, rtol=1e-4)
    # f = x^2 + 2y^2 - z^2: laplacian = 2 + 4 - 2 = 4; the clamp keeps it; beyond 50 it saturates
    q = x[:, 0] ** 2 + 2 * x[:, 1] ** 2 - x[:, 2] ** 2
    div_q = laplacian(spatial_gradient(q, x), x)
    assert torch.allclose(div_q, torch.full_like(div_q, 4.0), atol=1e-5)
    assert divergence_loss(div_q).item() == pytest.approx(4.0, abs=1e-5)
    assert divergence_loss(100.0 * div_q).item() == pytest.approx(50.0)


def test_manifold_and_off_surface_terms():
    f = torch.tensor([0.0, 0.1, -0.3])
    assert digs_manifold_loss(f).item() == pytest.approx(0.4 / 3)
    assert digs_off_surface_loss(torch.zeros(5)).item() == pytest.approx(1.0)
    assert digs_off_surface_loss(torch.tensor([0.01, -0.01])).item() == pytest.approx(math.exp(-1.0), rel=1e-6)
    assert digs_off_surface_loss(torch.tensor([1.0])).item() < 1e-40


def test_divergence_weight_schedule():
    assert divergence_weight(0, 1000) == 100.0
    assert divergence_weight(199, 1000) == 100.0
    assert divergence_weight(300, 1000) == pytest.approx(50.0)
    assert divergence_weight(400, 1000) == 0.0
    assert divergence_weight(999, 1000) == 0.0


def test_neural_pull_loss_is_zero_for_exact_sdf_and_nearest_points():
    # exact sphere SDF pulls every query to its radial projection, which is the nearest sphere point
    x = _points(np.random.default_rng(4).uniform(-1, 1, (2000, 3)))
    f = x.norm(dim=-1) - 0.5
    pulled = pull_to_surface(x, f, spatial_gradient(f, x))
    nearest = 0.5 * x.detach() / x.detach().norm(dim=-1, keepdim=True)
    assert neural_pull_loss(pulled, nearest).item() < 1e-6
    # the pull is invariant to the sign of f (f * grad f is); a field twice too steep overshoots by |f|
    pulled_flip = pull_to_surface(x, -f, spatial_gradient(-f, x))
    assert neural_pull_loss(pulled_flip, nearest).item() < 1e-6
    pulled_steep = pull_to_surface(x, 2 * f, spatial_gradient(2 * f, x))
    assert neural_pull_loss(pulled_steep, nearest).item() == pytest.approx(f.abs().mean().item(), rel=1e-4)


# --- SIREN -----------------------------------------------------------------------------------

@pytest.mark.parametrize("init", ["mfgi", "geometric_sine"])
def test_siren_geometric_init_is_negative_inside(init):
    torch.manual_seed(0)
    net = SirenMLP(init=init)
    with torch.no_grad():
        f0 = net(torch.zeros(1, 3)).item()
        far = net(torch.tensor([[2.0, 2.0, 2.0], [-2.0, 2.0, -2.0]]))
    assert f0 == pytest.approx(-0.16, abs=0.01)  # 0.1 * (sqrt(~0) - 1.6)
    assert (far > 0).all()


def test_siren_layer_shapes_and_plain_init():
    net = SirenMLP(hidden=32, hidden_layers=3, init="siren")
    assert [m.weight.shape for m in [net.first, *net.hidden_layers, net.output]] == [
        (32, 3), (32, 32), (32, 32), (32, 32), (1, 32)
    ]
    assert net.first.weight.abs().max() <= 1 / 3
    with pytest.raises(ValueError):
        SirenMLP(hidden=30, init="mfgi")  # 25 % / 75 % does not split 30 rows exactly
    with pytest.raises(ValueError):
        SirenMLP(init="bogus")


# --- end-to-end smoke fits -------------------------------------------------------------------

def _fit(cls, **overrides) -> tuple[FittedField, list[FitProgress], float]:
    cfg = cls.presets["smoke"]()
    if "iterations" in overrides:
        cfg = with_schedule(cfg, iterations=overrides.pop("iterations"))
    cfg = dataclasses.replace(cfg, **overrides)
    reports: list[FitProgress] = []
    pts = sphere_points()
    field = cls(cfg).fit(pts, torch.device("cpu"), progress=reports.append)
    mean_abs_f = float(np.abs(field.evaluate(pts)["inside_score"]).mean())
    return field, reports, mean_abs_f


@pytest.fixture(scope="module", params=[NeuralPull, DiGS], ids=["neuralpull", "digs"])
def smoke_fit(request):
    cls = request.param
    field, reports, mean_abs_f = _fit(cls)
    return cls, field, reports, mean_abs_f


def test_smoke_fit_returns_sdf_field_with_correct_inside(smoke_fit):
    cls, field, _, mean_abs_f = smoke_fit
    cfg = cls.presets["smoke"]()
    assert isinstance(field, FittedField)
    assert field.kind == "sdf" and field.level == 0.0 and field.method == cls.name
    assert field.iterations_run == cfg.iterations
    assert field.config == dataclasses.asdict(cfg)
    assert field.fit_seconds > 0
    score = field.evaluate(np.array([CENTRE, [0.95, 0.95, 0.95], [-0.95, -0.95, 0.95]]))["inside_score"]
    assert score[0] > field.level
    assert score[1] < field.level and score[2] < field.level
    # the surface moved from the initial sphere onto the input: |f| at the input points is small
    # (at the init it is ~0.7 for Neural-Pull's radius-1.0 sphere)
    assert mean_abs_f < 0.02, mean_abs_f
    # classification of a sample of the cube against the true sphere
    g = np.random.default_rng(0).uniform(-1, 1, (20000, 3)).astype(np.float32)
    inside_true = np.linalg.norm(g - CENTRE, axis=1) < RADIUS
    inside_pred = field.evaluate(g)["inside_score"] > field.level
    assert (inside_true == inside_pred).mean() > 0.98


def test_smoke_fit_loss_decreases_and_progress_reported(smoke_fit):
    _, field, reports, _ = smoke_fit
    h = field.loss_history
    assert len(h) >= 10 and all(np.isfinite(h))
    assert np.mean(h[-3:]) < 0.2 * np.mean(h[:3])
    assert reports and reports[-1].iteration == reports[-1].iterations == field.iterations_run
    assert all(r.iterations == field.iterations_run for r in reports)


def test_smoke_field_rebuilds_exactly_from_arch(smoke_fit):
    _, field, _, _ = smoke_fit
    module = build_module(field.arch)
    assert type(module) is type(field.module)
    module.load_state_dict(field.module.state_dict())
    module.eval()
    x = torch.from_numpy(np.random.default_rng(5).uniform(-1, 1, (3000, 3)).astype(np.float32))
    with torch.no_grad():
        assert torch.equal(module(x), field.module(x))


@pytest.mark.parametrize("cls", [NeuralPull, DiGS], ids=["neuralpull", "digs"])
def test_fit_is_deterministic_for_a_seed(cls):
    a, _, _ = _fit(cls, iterations=5)
    b, _, _ = _fit(cls, iterations=5)
    c, _, _ = _fit(cls, iterations=5, seed=1)
    x = torch.from_numpy(np.random.default_rng(6).uniform(-1, 1, (500, 3)).astype(np.float32))
    with torch.no_grad():
        assert torch.equal(a.module(x), b.module(x))
        assert not torch.equal(a.module(x), c.module(x))


@pytest.mark.parametrize("cls", [NeuralPull, DiGS], ids=["neuralpull", "digs"])
def test_cancellation_raises_job_canceled(cls):
    calls = {"n": 0}

    def should_cancel() -> bool:
        calls["n"] += 1
        return calls["n"] > 2

    cfg = with_schedule(cls.presets["smoke"](), iterations=1000)
    with pytest.raises(JobCanceled):
        cls(cfg).fit(sphere_points(500), torch.device("cpu"), should_cancel=should_cancel)
    assert calls["n"] == 3  # checked regularly, stopped at the first True


@pytest.mark.parametrize("name,cls,config_cls", [("neuralpull", NeuralPull, NeuralPullConfig), ("digs", DiGS, DiGSConfig)])
def test_presets_and_registry(name, cls, config_cls):
    assert get_method_class(name) is cls
    for preset in ("paper", "default", "smoke"):
        cfg = cls.presets[preset]()
        assert isinstance(cfg, config_cls) and cfg.iterations >= 1
        fc = build_fit_config(preset, method=name)
        assert fc.method == name and fc.method_config == cfg
    paper = cls.presets["paper"]()
    if cls is NeuralPull:
        assert (paper.iterations, paper.batch_size, paper.schedule.lr, paper.schedule.warmup) == (40_000, 5_000, 1e-3, 1_000)
        assert (paper.layers, paper.hidden, paper.total_queries) == (8, 256, 1_000_000)
    else:
        assert (paper.iterations, paper.n_surface, paper.n_uniform, paper.schedule.lr, paper.schedule.grad_clip) == (
            10_000, 15_000, 15_000, 5e-5, 10.0
        )
        assert (paper.hidden, paper.hidden_layers, paper.init, paper.omega) == (256, 4, "mfgi", 30.0)
        assert (paper.w_manifold, paper.w_off, paper.w_eikonal, paper.w_div) == (3e3, 1e2, 5e1, 1e2)


def test_neuralpull_rejects_skip_outside_the_network():
    cfg = dataclasses.replace(NeuralPull.presets["smoke"](), layers=4, skip=4)
    with pytest.raises(ValueError, match="skip"):
        NeuralPull(cfg).fit(sphere_points(200), torch.device("cpu"))


@pytest.mark.parametrize("cls,terms", [(NeuralPull, {"pull"}), (DiGS, {"manifold", "off_surface", "eikonal", "divergence"})])
def test_one_loop_reports_every_named_loss_term(cls, terms):
    field, _, _ = _fit(cls, iterations=30)
    assert set(field.loss_terms) == terms
    assert all(np.isfinite(v) for v in field.loss_terms.values())
