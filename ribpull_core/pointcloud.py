"""The in-memory point cloud every loader returns and every stage consumes.

All coordinates are millimetres in the input's own frame (for NIfTI inputs: the scanner frame given
by the header affine, as nibabel reads it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PointCloud:
    """Points in mm with optional per-point normals and integer labels.

    points: (N, 3) float64, millimetres.
    normals: (N, 3) float64 unit vectors, or None.
    labels: (N,) int32 label per point (e.g. the NIfTI label value), or None.
    source_format: loader name, e.g. "ply", "nifti".
    source_bytes: size of the input file in bytes (0 when built in memory).
    nifti_affine / nifti_shape: voxel->mm affine (4, 4) and volume shape for NIfTI inputs, so
        outputs (the SDF volume) can be aligned with the input volume.
    label_names: optional map label value -> anatomical name (e.g. 98 -> "rib_left_7").
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    labels: np.ndarray | None = None
    source_format: str = "memory"
    source_bytes: int = 0
    nifti_affine: np.ndarray | None = None
    nifti_shape: tuple[int, int, int] | None = None
    label_names: dict[int, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64).reshape(-1, 3)
        if self.normals is not None:
            self.normals = np.ascontiguousarray(self.normals, dtype=np.float64).reshape(-1, 3)
        if self.labels is not None:
            self.labels = np.ascontiguousarray(self.labels, dtype=np.int32).reshape(-1)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def bbox_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """(min (3,), max (3,)) corners of the axis-aligned bounding box in mm."""
        return self.points.min(axis=0), self.points.max(axis=0)
