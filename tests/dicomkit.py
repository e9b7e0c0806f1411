"""Test helpers for the DICOM tests: the phantom as a synthetic CT study with a rib SEG, and a
stand-in "fit" (the mask itself) so the writers can be checked without running a network."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

#: coarse voxels keep the series small (≈150 slices) and the fits quick
PHANTOM_SPACING_MM = 2.0


@lru_cache(maxsize=1)
def phantom_labels(spacing_mm: float = PHANTOM_SPACING_MM) -> tuple[np.ndarray, np.ndarray, dict[int, str]]:
    """(label volume (X, Y, Z) uint8, its voxel -> RAS mm affine, label -> TotalSegmentator name)."""
    from ribpull_core.io import totalseg_rib_names
    from ribpull_core.phantom import PhantomConfig, make_phantom, voxelize

    vol, affine = voxelize(make_phantom(PhantomConfig(n_points=1000)), spacing_mm=spacing_mm)
    present = set(np.unique(vol).tolist())
    return vol, affine, {k: v for k, v in totalseg_rib_names().items() if k in present}


def phantom_study(outdir: Path, fractional: bool = False) -> dict:
    """Write the phantom's CT series (ct/) and its rib SEG (seg.dcm) under outdir.
    Returns {"ct": [paths], "seg": path, "ct_datasets": [...], "seg_dataset": ds, "labels", "affine", "names"}."""
    from ribpull_core.dicom.synthetic import ct_series_from_labels, seg_from_labels, write_datasets

    vol, affine, names = phantom_labels()
    ct = ct_series_from_labels(vol, affine)
    seg = seg_from_labels(ct, vol, names, fractional=fractional)
    outdir.mkdir(parents=True, exist_ok=True)
    seg_path = outdir / "seg.dcm"
    seg.save_as(seg_path)
    return {"ct": write_datasets(ct, outdir / "ct", "ct"), "seg": seg_path, "ct_datasets": ct,
            "seg_dataset": seg, "labels": vol, "affine": affine, "names": names}
