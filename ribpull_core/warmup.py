"""Compile the core's numba kernels ahead of the first real job (`ribpull warmup`).

The CPU kernels (hash grid, closest points, SDF grid, patches, metrics) are numba functions,
compiled on their first call and then kept in numba's cache (`cache=True`: the package's
`__pycache__`, or NUMBA_CACHE_DIR where that is set). On a fresh install a user's first jobs pay
for those compiles. Measured on this project's 2-core machine (2026-12-07), in a fresh clone the
first 1.5 mm label-map run of `ribpull bench` took 28.0 s. Of that, 15.7 s was the mesh stage,
mostly compiling. Once compiled, the same run took 20.3 s, with a 5.3 s mesh stage. A 3 x 3 x 4 mm
map on an empty cache took 72 s: its fit took 30.8 s and its mesh 28.6 s (tests/test_warmup.py).

`warm_up` runs the one pipeline (`pipeline.run_pipeline`, default preset) on synthetic
inputs, so that those compiles happen at install time (`make install`, the Docker image) instead.
Each input takes a different path through the pipeline:

- 60k points / 0.3 mm: the flood-fill warm start and the round quadric patches;
- 5k points / 1 mm: the sphere start, the noise flow and the section quadrics;
- a partial-volume label map with anisotropic voxels: the label-map set-up, the tube patches and
  the smoothing-bias flow. Its voxel centres are not nodes of the SDF's closest-point grid, so
  this is also the SDF's point-query path.

Nothing is kept except numba's cache: the inputs and outputs go to a temporary directory.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class WarmupInput:
    """One synthetic input of the warm-up: a phantom with n_points samples of noise_mm noise, or
    (spacing_mm set) its partial-volume label map with voxels of spacing_mm (sx, sy, sz) mm."""

    name: str
    n_points: int = 60_000
    noise_mm: float = 0.3
    spacing_mm: tuple[float, float, float] | None = None


WARMUP_INPUTS: tuple[WarmupInput, ...] = (
    WarmupInput("points-60k-0.3mm"),
    WarmupInput("points-5k-1mm", n_points=5_000, noise_mm=1.0),
    WarmupInput("label-map-1.5x1.5x2.5mm", spacing_mm=(1.5, 1.5, 2.5)),
)


def warm_up(workdir: str | Path | None = None, inputs: tuple[WarmupInput, ...] = WARMUP_INPUTS,
            log: Callable[[str], None] = print) -> list[dict]:
    """Run the pipeline once on each of `inputs` (in workdir, else a temporary directory that is
    removed afterwards) and return, per input, {"input", "seconds" (wall), "timings_s" (the run's
    own per-stage times)}. log(line) is called after each run."""
    from .phantom import PhantomConfig, write_phantom
    from .pipeline import PipelineOptions, run_pipeline

    place = tempfile.TemporaryDirectory(prefix="ribpull-warmup-") if workdir is None else nullcontext(workdir)
    with place as where:
        root = Path(where)
        out = []
        for item in inputs:
            case = root / item.name
            files = write_phantom(case, PhantomConfig(n_points=item.n_points, noise_mm=item.noise_mm),
                                  nifti=item.spacing_mm is not None, spacing_mm=item.spacing_mm or 1.0,
                                  partial_volume=True)
            t = time.perf_counter()
            result = run_pipeline(files["mask" if item.spacing_mm is not None else "points"], case / "out",
                                  PipelineOptions())
            seconds = time.perf_counter() - t
            out.append({"input": item.name, "seconds": round(seconds, 2), "timings_s": result.metrics["timings_s"]})
            log(f"warm-up: {item.name} in {seconds:.1f} s")
        return out
