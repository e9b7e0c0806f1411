"""Save and load a FittedField with its UnitFrame: model.safetensors (tensors) + model.json (the rest).

No pickled code: the JSON names the network (`arch`) and `ribpull_core.fields.build_module` rebuilds
it, so a loaded model answers queries in mm exactly like the one that was saved.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from .errors import RibPullInputError
from .fields import build_module
from .frame import UnitFrame
from .methods.base import FittedField

FORMAT_VERSION = 1
WEIGHTS_NAME = "model.safetensors"
META_NAME = "model.json"


def save_field(field: FittedField, frame: UnitFrame, outdir, extra: dict | None = None) -> tuple[Path, Path]:
    """Write outdir/model.safetensors and outdir/model.json; returns (weights path, json path).

    Floating tensors are stored as contiguous fp32 (CPU); model.json holds format_version, arch,
    kind, level, method, config, frame (mm), units="mm", iterations_run, fit_seconds, plus `extra`.
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    if not field.arch or "name" not in field.arch:
        raise ValueError("field.arch must name the network ({'name': ..., 'kwargs': {...}}) to be saved")
    tensors = {}
    for k, v in field.module.state_dict().items():
        v = v.detach().cpu()
        tensors[k] = (v.float() if v.is_floating_point() else v).contiguous().clone()
    wpath, jpath = outdir / WEIGHTS_NAME, outdir / META_NAME
    save_file(tensors, str(wpath), metadata={"format": "ribpull"})
    meta = {
        "format_version": FORMAT_VERSION,
        "arch": field.arch,
        "kind": field.kind,
        "level": float(field.level),
        "method": field.method,
        "config": field.config,
        "frame": frame.to_dict(),
        "units": "mm",
        "iterations_run": int(field.iterations_run),
        "fit_seconds": float(field.fit_seconds),
    }
    if extra:
        meta.update(extra)
    jpath.write_text(json.dumps(meta, indent=2, default=str))
    return wpath, jpath


def _paths(path_or_dir) -> tuple[Path, Path]:
    p = Path(path_or_dir)
    if p.is_dir():
        return p / WEIGHTS_NAME, p / META_NAME
    if p.suffix == ".json":
        return p.with_suffix(".safetensors"), p
    return p, p.with_suffix(".json")


def load_field(path_or_dir, device: str | torch.device = "cpu") -> tuple[FittedField, UnitFrame, dict]:
    """Load what `save_field` wrote: a directory, its model.safetensors or its model.json.

    Returns (field on `device` in eval mode, frame, the JSON metadata). The state dict is loaded
    strictly. Missing, unreadable or mismatched files raise RibPullInputError("parse_error").
    """
    wpath, jpath = _paths(path_or_dir)
    for p in (wpath, jpath):
        if not p.is_file():
            raise RibPullInputError("parse_error", f"model file missing: {p} (need {WEIGHTS_NAME} and {META_NAME})")
    try:
        meta = json.loads(jpath.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RibPullInputError("parse_error", f"{jpath.name} is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format_version") != FORMAT_VERSION:
        raise RibPullInputError(
            "parse_error", f"{jpath.name}: unsupported format_version {meta.get('format_version') if isinstance(meta, dict) else None!r} (expected {FORMAT_VERSION})"
        )
    try:
        arch, kind = meta["arch"], meta["kind"]
        frame = UnitFrame.from_dict(meta["frame"])
        level = float(meta.get("level", 0.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise RibPullInputError("parse_error", f"{jpath.name} lacks a valid {exc} entry") from exc
    if kind not in ("occupancy", "sdf"):
        raise RibPullInputError("parse_error", f"{jpath.name}: unknown field kind {kind!r}")
    try:
        module = build_module(arch)
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise RibPullInputError("parse_error", f"{jpath.name}: cannot rebuild network {arch!r}: {exc}") from exc
    try:
        state = load_file(str(wpath), device="cpu")
    except (SafetensorError, OSError, ValueError) as exc:
        raise RibPullInputError("parse_error", f"{wpath.name} is not a readable safetensors file: {exc}") from exc
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise RibPullInputError("parse_error", f"{wpath.name} does not match network {arch.get('name')!r}: {exc}") from exc
    module = module.to(device).eval()
    field = FittedField(
        module=module,
        kind=kind,
        arch=arch,
        level=level,
        method=str(meta.get("method", "")),
        config=meta.get("config", {}) or {},
        iterations_run=int(meta.get("iterations_run", 0)),
        fit_seconds=float(meta.get("fit_seconds", 0.0)),
    )
    return field, frame, meta
