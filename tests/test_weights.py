"""Weights round trip: a loaded field answers exactly like the saved one."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from ribpull_core.errors import RibPullInputError
from ribpull_core.fields import NeuralPullMLP
from ribpull_core.frame import UnitFrame
from ribpull_core.methods.base import FittedField
from ribpull_core.weights import load_field, save_field

ARCH = {"name": "NeuralPullMLP", "kwargs": {"out_dim": 2, "hidden": 64, "layers": 6, "skip": 3}}
FRAME = UnitFrame((100.0, -50.0, 20.0), 150.0)


def trained_like_field() -> FittedField:
    torch.manual_seed(0)
    net = NeuralPullMLP(**ARCH["kwargs"])  # weight norm on: parametrized g and v are saved
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return FittedField(net, kind="occupancy", arch=ARCH, level=-0.123456789012345, method="sparseocc",
                       config={"iterations": 10, "lr": 1e-3})


def test_round_trip_is_exact(tmp_path):
    field = trained_like_field()
    wpath, jpath = save_field(field, FRAME, tmp_path, extra={"input_bytes": 1234})
    assert (wpath.name, jpath.name) == ("model.safetensors", "model.json")
    meta = json.loads(jpath.read_text())
    assert meta["format_version"] == 1 and meta["units"] == "mm" and meta["input_bytes"] == 1234
    assert meta["frame"] == {"center_mm": [100.0, -50.0, 20.0], "half_extent_mm": 150.0}
    x = torch.rand(4096, 3) * 2 - 1
    with torch.no_grad():
        ref = field.module(x)
    for where in (tmp_path, wpath, jpath):
        loaded, frame, meta2 = load_field(where)
        assert frame == FRAME and meta2 == meta
        assert (loaded.kind, loaded.level, loaded.method, loaded.arch) == ("occupancy", field.level, "sparseocc", ARCH)
        with torch.no_grad():
            assert torch.equal(loaded.module(x), ref)
    pts = np.random.default_rng(0).uniform(-1, 1, (1000, 3))
    np.testing.assert_array_equal(loaded.evaluate(pts)["U"], field.evaluate(pts)["U"])


def test_bad_or_missing_files_are_parse_errors(tmp_path):
    with pytest.raises(RibPullInputError) as err:
        load_field(tmp_path)
    assert err.value.code == "parse_error" and "missing" in err.value.message
    field = trained_like_field()
    _, jpath = save_field(field, FRAME, tmp_path)
    meta = json.loads(jpath.read_text())
    meta["arch"]["kwargs"]["hidden"] = 32  # the tensors no longer fit the network
    jpath.write_text(json.dumps(meta))
    with pytest.raises(RibPullInputError, match="does not match") as err:
        load_field(tmp_path)
    assert err.value.code == "parse_error"
    jpath.write_text("{not json")
    with pytest.raises(RibPullInputError, match="not valid JSON"):
        load_field(tmp_path)
    save_field(field, FRAME, tmp_path)
    (tmp_path / "model.safetensors").write_bytes(b"garbage")
    with pytest.raises(RibPullInputError, match="safetensors"):
        load_field(tmp_path)


def test_a_grid_field_with_a_solid_prior_round_trips_and_starts_as_that_solid(tmp_path):
    from ribpull_core.fields.grid import GridOccupancyField

    arch = {"name": "GridOccupancyField", "kwargs": {"n_levels": 4, "log2_table": 10, "max_resolution": 32,
                                                     "hidden": 16, "prior_shape": [21, 21, 21]}}
    module = GridOccupancyField(**arch["kwargs"])
    # a ball of radius 0.3 (unit frame) on nodes at -0.5 .. 0.5: index = (x + 0.5) * 20
    axis = np.linspace(-0.5, 0.5, 21)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    distance = (np.sqrt(x**2 + y**2 + z**2) - 0.3).astype(np.float32)
    module.set_prior(distance, np.hstack([20.0 * np.eye(3), np.full((3, 1), 10.0)]))
    field = FittedField(module.eval(), kind="occupancy", arch=arch, level=0.0, method="sparseocc", config={})
    # an untrained decoder adds ~nothing: the field's zero set is the prior's sphere of radius 0.3
    pts = np.random.default_rng(1).normal(size=(2000, 3))
    pts *= np.random.default_rng(2).uniform(0.05, 0.45, (2000, 1)) / np.linalg.norm(pts, axis=1, keepdims=True)
    u = field.evaluate(pts)["U"]
    r = np.linalg.norm(pts, axis=1)
    assert (u[r < 0.27] > 0).all() and (u[r > 0.33] < 0).all()
    save_field(field, FRAME, tmp_path)
    loaded, _, _ = load_field(tmp_path)
    np.testing.assert_array_equal(loaded.evaluate(pts)["U"], u)
