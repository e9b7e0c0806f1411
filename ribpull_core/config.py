"""Typed configs for a whole `ribpull fit` run, with named presets.

A run = a method config (SparseOcc / Neural-Pull / DiGS, each owned by its method module) plus the
stage configs below. `get_preset(name)` returns a fresh `FitConfig`; CLI flags and service params
override fields of it with `dataclasses.replace`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass
class MeshConfig:
    """Marching cubes on the inside score, coarse-to-fine.

    resolution: cells along the longest side of the (padded) input bounding box at the finest level.
    coarse_resolution: first, dense pass; finer levels only evaluate cells near the surface.
    padding: bounding-box padding as a fraction of the half extent (paper: 0.05 in unit frame).
    """

    resolution: int = 384
    coarse_resolution: int = 64
    padding: float = 0.05
    keep_components_min_fraction: float = 0.0  # drop components smaller than this fraction of faces


@dataclass
class SdfConfig:
    """Signed distance volume in mm (negative inside), written as NIfTI.

    voxel_mm: grid spacing; None means the input NIfTI's spacing for NIfTI inputs, else 1/128 of the
    longest side. padding_mm: margin around the input bounding box (non-NIfTI inputs).
    """

    voxel_mm: float | None = None
    padding_mm: float = 5.0
    max_voxels: int = 16_000_000


@dataclass
class MetricsConfig:
    """ConvONet-style surface metrics; n_samples per side (paper: 100k)."""

    n_samples: int = 100_000
    fscore_tau_mm: float = 1.0


@dataclass
class LabelMapConfig:
    """How a NIfTI label map becomes training data (the load stage).

    boundary_sigma_mm: the fitted points are the centres of the voxel faces between selected and
    unselected voxels; when > 0 each moves along its axis to where the mask, smoothed by a Gaussian
    of this std (mm), crosses 0.5 (a sub-voxel boundary instead of the staircase).
    band_voxels: voxel centres within this many voxels of the boundary become known-occupancy
    samples (inside / outside) for methods that use them; 0 disables.
    """

    boundary_sigma_mm: float = 0.0
    band_voxels: float = 0.0


@dataclass
class FitConfig:
    """Everything one fit needs. `method_config` is the method's own dataclass."""

    preset: str
    method: str
    method_config: Any
    mesh: MeshConfig = field(default_factory=MeshConfig)
    sdf: SdfConfig = field(default_factory=SdfConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    label_map: LabelMapConfig = field(default_factory=LabelMapConfig)
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)
