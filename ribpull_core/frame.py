"""Map between the input's millimetre frame and the unit frame the networks are trained in.

The paper's convention (RibPull): the longest bounding-box side maps to 2, i.e. the shape fits in
[-1, 1]^3. We also centre the box (Neural-Pull does), which changes nothing about the metric units
(paper units = mm * 2 / longest side) but keeps the shape symmetric in the cube.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class UnitFrame:
    """x_unit = (x_mm - center_mm) / half_extent_mm; x_mm = x_unit * half_extent_mm + center_mm.

    center_mm: (3,) bounding-box centre in mm. half_extent_mm: half the longest side in mm, so the
    longest side spans [-1, 1] in unit coordinates. One unit-frame unit is half_extent_mm millimetres.
    """

    center_mm: tuple[float, float, float]
    half_extent_mm: float

    @classmethod
    def fit(cls, points_mm: np.ndarray) -> UnitFrame:
        lo, hi = points_mm.min(axis=0), points_mm.max(axis=0)
        half = float((hi - lo).max()) / 2.0
        if not np.isfinite(half) or half <= 0:
            raise ValueError("cannot build a frame for points with zero extent")
        return cls(tuple(float(c) for c in (lo + hi) / 2.0), half)

    def to_unit(self, x_mm: np.ndarray) -> np.ndarray:
        """(..., 3) mm -> (..., 3) unit frame."""
        return (np.asarray(x_mm, dtype=np.float64) - np.asarray(self.center_mm)) / self.half_extent_mm

    def to_mm(self, x_unit: np.ndarray) -> np.ndarray:
        """(..., 3) unit frame -> (..., 3) mm."""
        return np.asarray(x_unit, dtype=np.float64) * self.half_extent_mm + np.asarray(self.center_mm)

    @property
    def paper_units_per_mm(self) -> float:
        """Multiply a length in mm by this to get the paper's normalised units (longest side = 2)."""
        return 1.0 / self.half_extent_mm

    def to_dict(self) -> dict:
        return {"center_mm": list(self.center_mm), "half_extent_mm": self.half_extent_mm}

    @classmethod
    def from_dict(cls, d: dict) -> UnitFrame:
        return cls(tuple(float(c) for c in d["center_mm"]), float(d["half_extent_mm"]))
