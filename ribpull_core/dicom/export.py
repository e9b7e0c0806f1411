"""All DICOM outputs of a finished fit of a DICOM input: seg.dcm, measurements_sr.dcm, mesh_stl.dcm.

Called by the pipeline's export stage when the input was a DICOM SEG (cloud.dicom_source set); every
coordinate is already in the source's LPS patient frame (mm), because the fit ran in it. A NIfTI input
with dicom_outputs comes through `nifti_source.GeneratedStudy.write_outputs`, which converts its RAS
fit to LPS first and passes its generated CT study as the source.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: artifact names of the DICOM outputs, in the order they are written (and stored into a PACS)
DICOM_ARTIFACTS = ("seg.dcm", "measurements_sr.dcm", "mesh_stl.dcm")


def rib_segment_volume(sdf_mm: np.ndarray, sdf_affine: np.ndarray, cloud, segment_of_label: dict[int, int]) -> np.ndarray:
    """Segment numbers on the SDF grid ((shape of sdf_mm) uint16, 0 outside): a voxel inside the
    reconstruction (signed distance < 0) takes the segment of the label of its nearest input point.
    sdf_affine: voxel -> mm; segment_of_label: input label value -> segment number."""
    from scipy.spatial import cKDTree

    volume = np.zeros(sdf_mm.shape, dtype=np.uint16)
    inside = np.argwhere(sdf_mm < 0)
    if len(inside) == 0:
        return volume
    centres = inside @ sdf_affine[:3, :3].T + sdf_affine[:3, 3]
    nearest = cKDTree(cloud.points).query(centres, workers=-1)[1]
    labels = cloud.labels if cloud.labels is not None else np.ones(len(cloud.points), np.int32)
    values = np.unique(labels)
    segments = np.array([segment_of_label.get(int(v), 0) for v in values], dtype=np.uint16)
    volume[tuple(inside.T)] = segments[np.searchsorted(values, labels[nearest])]
    return volume


def write_dicom_outputs(outdir: str | Path, cloud, mesh, sdf_mm: np.ndarray, sdf_affine: np.ndarray,
                        metrics: dict) -> dict[str, Path]:
    """Write the three objects into `outdir`; returns {artifact name: path}.

    cloud: the fitted cloud (labels, label_names, dicom_source); mesh: the reconstruction (trimesh,
    LPS mm); sdf_mm / sdf_affine: the signed distance volume on the source grid (voxel -> LPS mm);
    metrics: the pipeline's metrics (skeleton curves, surface)."""
    from .ribs import rib_name
    from .seg_write import segment_numbers_for, write_rib_seg
    from .sr import write_measurement_report
    from .stl import write_encapsulated_stl

    outdir = Path(outdir)
    source = cloud.dicom_source
    labels = np.unique(cloud.labels) if cloud.labels is not None else np.array([1])
    # rib segments are named "L7" whatever the input called them (a NIfTI's "rib_left_7"), as the skeleton does
    names = {int(v): rib_name(cloud.label_names.get(int(v), f"segment_{int(v)}")) for v in labels}
    numbers = segment_numbers_for(names)
    volume = rib_segment_volume(sdf_mm, sdf_affine, cloud, numbers)
    paths = {name: outdir / name for name in DICOM_ARTIFACTS}
    seg = write_rib_seg(paths["seg.dcm"], source, volume, sdf_affine, {numbers[v]: names[v] for v in names})
    # the SEG numbers its non-empty segments 1..n: map names to the numbers it really holds
    segment_of = {str(seg.get_segment_description(n).SegmentLabel): n for n in seg.segment_numbers}
    write_measurement_report(paths["measurements_sr.dcm"], source, seg, metrics, segment_of)
    write_encapsulated_stl(paths["mesh_stl.dcm"], source, mesh)
    return paths
