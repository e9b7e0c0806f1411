"""THE pipeline: input file -> fitted field -> mesh, SDF, skeleton, metrics, weights on disk.

`run_pipeline` is the one function the CLI (`ribpull fit`), the Celery worker and the benchmark call.
It reports progress through a callback and stops cleanly (raising `JobCanceled`) when its
cancellation check returns True. Bad input raises `RibPullInputError`; nothing is written to
`outdir` until a stage has finished (files are written to a temporary directory and moved in).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

#: artifact file names the pipeline can produce (the service serves exactly these)
ARTIFACT_NAMES = (
    "mesh.ply", "mesh.stl", "mesh.obj", "mesh.glb",
    "sdf.nii.gz",
    "model.safetensors", "model.json",
    "metrics.json",
    "skeleton.json", "skeleton.glb", "skeleton.obj", "scene.glb",
    "preview.png",
)


@dataclass
class PipelineOptions:
    """User-facing knobs (CLI flags and the service's `params` map onto these).

    preset: named FitConfig preset ("default", "paper", "smoke", ...); method: override the preset's
    method ("sparseocc", "neuralpull", "digs"); iterations / resolution: override the schedule and the
    finest marching-cubes resolution; labels: NIfTI label values to keep; skeleton: also extract the
    medial axis; device: "auto", "cpu" or "cuda"; reference: a mesh or point file to measure against
    instead of the input; metrics_samples: samples per side for the surface metrics.
    """

    preset: str = "default"
    method: str | None = None
    iterations: int | None = None
    resolution: int | None = None
    labels: list[int] | None = None
    skeleton: bool = True
    preview: bool = True
    device: str = "auto"
    seed: int = 0
    reference: Path | None = None
    metrics_samples: int | None = None
    max_points: int = 2_000_000
    max_file_bytes: int = 512 * 1024 * 1024


@dataclass
class PipelineProgress:
    """stage: load|fit|mesh|sdf|skeleton|metrics|export|done; fraction: overall progress in [0, 1]."""

    stage: str
    fraction: float
    iteration: int | None = None
    iterations: int | None = None
    loss: float | None = None
    message: str = ""


@dataclass
class PipelineResult:
    outdir: Path
    artifacts: dict[str, Path] = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)


ProgressCallback = Callable[[PipelineProgress], None]
CancelCheck = Callable[[], bool]
