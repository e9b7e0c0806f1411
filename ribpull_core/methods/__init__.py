"""Surface-fitting methods behind one interface (see base.py), and the named run presets.

Every method class offers the presets "paper" (its reference configuration), "default" (RibPull's
CPU-friendly choice) and "smoke" (seconds, for tests). A run preset picks a method and a mesh
resolution; `--method` swaps the method and keeps the preset name.
"""

from __future__ import annotations

import dataclasses
import importlib

from ..config import FitConfig, LabelMapConfig, MeshConfig, RefineConfig, SdfConfig
from ..errors import RibPullInputError
from .base import Method
from .training import with_schedule

#: label maps: std (mm) of the smoothing that places the boundary points between voxel centres. With
#: the smoothing's inward offset restored after refinement (RefineConfig.smoothing_bias_factor), a
#: wider blur averages more of the staircase: CD-L1 at 0.6 / 0.9 / 1.2 mm on the bench's 1.5 mm map
#: 0.2500 / 0.2471 / 0.2469 (HD 0.91 / 0.96 / 1.01; marching cubes + 20 Taubin 0.2672 / 1.03), at
#: 0.75 x 0.75 x 2.5 mm 0.2661 / 0.2597 / 0.2521 (0.3096 / 1.33); 1M samples,
#: benchmarks/label_map_bias_ab.py, 2026-12-03. 0.9 keeps the HD further below the baseline's.
LABEL_MAP_SIGMA_MM = 0.9

#: method name -> "module:Class"
METHOD_CLASSES = {
    "sparseocc": "ribpull_core.methods.sparseocc:SparseOcc",
    "neuralpull": "ribpull_core.methods.neuralpull:NeuralPull",
    "digs": "ribpull_core.methods.digs:DiGS",
}

@dataclasses.dataclass(frozen=True)
class RunPreset:
    """What a run preset picks besides the method's own preset of the same name.

    method: the default method; mesh_resolution: finest marching-cubes resolution; label_map:
    label-map handling; refine: vertex refinement of the mesh onto the input points (None: off);
    sdf_cells: the SDF volume's voxels along the input box's longest side (point inputs; a label
    map's SDF is on its own grid).
    """

    method: str
    mesh_resolution: int
    label_map: LabelMapConfig
    refine: RefineConfig | None
    sdf_cells: int = 128


#: default meshes at 256 cells, about half a cell of its field's finest grid level at 60k points: 384
#: was as accurate (60k / 0.3 mm points CD-L1 0.425 vs 0.423 mm, 1.5 mm label map 0.433 both, 20k
#: 0.545 vs 0.540, 5k 1.461 vs 1.454; 300k samples) and took 3x the mesh stage (8.4 -> 2.4 s at 60k).
#: paper keeps the field's own mesh (no refinement). smoke meshes at 96 cells (~3 mm on the
#: phantom): at 64 (4.5 mm) a rib's 5 mm-thick end could fall between the marching-cubes samples
#: and the rib came out in two pieces (tests/test_pipeline.py, 4 ribs from 12k points). smoke's
#: SDF has 64 voxels along the longest side (~5 mm on a ribcage, as coarse as its mesh): at 128 the
#: volume was ~40% of a tiny smoke job (3.8 of 9.6 s, 4k points, 10 iterations).
#: how default and smoke turn a label map into training data (build_fit_config copies it per fit)
LABEL_MAP_DEFAULT = LabelMapConfig(boundary_sigma_mm=LABEL_MAP_SIGMA_MM, band_voxels=2.0, between_labels=True,
                                   solid_distance_cell_mm=3.0)
RUN_PRESETS = {
    "default": RunPreset("sparseocc", 256, LABEL_MAP_DEFAULT, RefineConfig()),
    "paper": RunPreset("sparseocc", 256, LabelMapConfig(), None),
    "smoke": RunPreset("sparseocc", 96, LABEL_MAP_DEFAULT, RefineConfig(), sdf_cells=64),
}


def get_method_class(name: str) -> type[Method]:
    """The Method subclass registered under `name`."""
    if name not in METHOD_CLASSES:
        raise RibPullInputError("bad_parameter", f"unknown method {name!r}; choose one of {sorted(METHOD_CLASSES)}")
    mod_name, cls_name = METHOD_CLASSES[name].split(":")
    return getattr(importlib.import_module(mod_name), cls_name)


def with_iterations(method_config, iterations: int):
    """A copy of a method config whose schedule runs `iterations` steps. A shorter run is the
    preset's schedule compressed: the warm-up keeps its share of it (at least 1 step)."""
    if iterations < 1:
        raise RibPullInputError("bad_parameter", "iterations must be >= 1")
    schedule = method_config.schedule
    changes = {"iterations": int(iterations)}
    if schedule.warmup and iterations < schedule.iterations:
        changes["warmup"] = max(1, round(schedule.warmup * iterations / schedule.iterations))
    return with_schedule(method_config, **changes)


def with_flood_prior(method_config, cell_mm: float, iterations: int | None):
    """A copy of a method config whose grid field starts a point cloud from the solid its flood fill
    encloses, at nodes cell_mm apart, and then runs at most `iterations` steps, where the method
    trusts that flood fill (`FieldConfig.grid_flood_prior_cell_mm`, `grid_flood_prior_iterations`);
    a method without such a field: the config as it is."""
    field = getattr(method_config, "field", None)
    if field is None or not hasattr(field, "grid_flood_prior_cell_mm"):
        return method_config
    return dataclasses.replace(method_config, field=dataclasses.replace(
        field, grid_flood_prior_cell_mm=float(cell_mm), grid_flood_prior_iterations=iterations))


def build_fit_config(
    preset: str = "default",
    method: str | None = None,
    iterations: int | None = None,
    resolution: int | None = None,
    seed: int = 0,
) -> FitConfig:
    """A fresh FitConfig for run preset `preset`, optionally another method, schedule or resolution.
    A shorter `iterations` than the preset's scales its warm-up by the same factor (at least 1)."""
    if preset not in RUN_PRESETS:
        raise RibPullInputError("bad_parameter", f"unknown preset {preset!r}; choose one of {sorted(RUN_PRESETS)}")
    run = RUN_PRESETS[preset]
    mesh_res, method = run.mesh_resolution, method or run.method
    cls = get_method_class(method)
    method_config = cls.presets[preset]()
    if iterations is not None:
        method_config = with_iterations(method_config, iterations)
    if resolution is not None:
        if not 16 <= resolution <= 1024:
            raise RibPullInputError("bad_parameter", "resolution must be between 16 and 1024")
        mesh_res = int(resolution)
    mesh = MeshConfig(resolution=mesh_res, coarse_resolution=min(64, mesh_res))
    return FitConfig(preset=preset, method=method, method_config=method_config, mesh=mesh,
                     sdf=SdfConfig(cells_per_side=run.sdf_cells),
                     label_map=dataclasses.replace(run.label_map),
                     refine=None if run.refine is None else dataclasses.replace(run.refine), seed=seed)


__all__ = ["METHOD_CLASSES", "RUN_PRESETS", "Method", "RunPreset", "build_fit_config", "get_method_class", "with_flood_prior",
           "with_iterations"]
