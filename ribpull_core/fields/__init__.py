"""Neural fields: torch modules mapping (B, 3) unit-frame points to raw outputs.

`build_module({"name": ..., "kwargs": {...}})` rebuilds any registered network, which is how saved
weights are loaded back without pickling code.
"""

from __future__ import annotations

import importlib
from typing import Any

from torch import nn

from .mlp import NeuralPullMLP

#: network name -> "module:Class"; modules are imported on first use
FIELD_CLASSES = {
    "NeuralPullMLP": "ribpull_core.fields.mlp:NeuralPullMLP",
    "SirenMLP": "ribpull_core.fields.siren:SirenMLP",
    "GridOccupancyField": "ribpull_core.fields.grid:GridOccupancyField",
}


def build_module(arch: dict[str, Any]) -> nn.Module:
    """Instantiate the network described by arch = {"name": str, "kwargs": dict}."""
    try:
        mod_name, cls_name = FIELD_CLASSES[arch["name"]].split(":")
    except KeyError as exc:
        raise ValueError(f"unknown field network {arch.get('name')!r}; known: {sorted(FIELD_CLASSES)}") from exc
    cls = getattr(importlib.import_module(mod_name), cls_name)
    return cls(**arch.get("kwargs", {}))


__all__ = ["FIELD_CLASSES", "NeuralPullMLP", "build_module"]
