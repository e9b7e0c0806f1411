"""A DICOM source made from a NIfTI label map: a generated study, so a NIfTI input can have the DICOM
outputs a DICOM SEG input gets (seg.dcm, measurements_sr.dcm, mesh_stl.dcm) plus the study's images.

A NIfTI label map has no study, no images and no patient frame. `GeneratedStudy` makes them: a
synthetic CT series on the label map's own voxel grid (`synthetic.ct_series_from_labels`: one slice
per index k along the third axis, pixel (row j, column i), bone-like HU where a selected label is
set), with new Study / Series / Frame of Reference UIDs. The three outputs then reference that series
exactly as they reference a DICOM SEG's source series, and `study_ct.zip` holds the slices so a
viewer can show the SEG on them.

Frames: the fit of a NIfTI input runs in its RAS mm world (nibabel's); DICOM objects are in the LPS
patient frame, (x, y, z)_LPS = (-x, -y, z)_RAS. `write_outputs` converts the mesh, the input points
and the signed distance grid to LPS before the writers see them, so the SEG frames lie on the CT
slices and the STL's vertices are mesh.ply's with x and y negated. The NIfTI job's own outputs
(mesh.ply, sdf.nii.gz, ...) stay in RAS.
"""

from __future__ import annotations

import dataclasses
import zipfile
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import RibPullInputError
from . import CT_SOP_CLASS_UID, LPS_FROM_RAS
from .instance import SourceUids

#: the generated CT series, one DICOM file per slice (ct_0001.dcm ...), as a job artifact
STUDY_CT_ARTIFACT = "study_ct.zip"

#: patient identity of a generated study (a NIfTI label map carries none)
PATIENT_NAME = "Anonymous^NIfTI"
PATIENT_ID = "RIBPULL-NIFTI"

#: voxel axes (i, j, k) of a NIfTI volume -> (slice k, row j, column i), the order of the CT frames
_SLICE_ROW_COLUMN = (2, 1, 0)


def require_voxel_grid(cloud) -> None:
    """Raise RibPullInputError("dicom_outputs_need_label_map") unless `cloud` was read from a label
    map (NIfTI or DICOM SEG): DICOM outputs need a voxel grid to put their slices on."""
    if cloud.nifti_affine is None or cloud.nifti_shape is None:
        raise RibPullInputError(
            "dicom_outputs_need_label_map",
            f"dicom_outputs needs a voxel grid to place the DICOM images on, and this input is a point cloud "
            f"({cloud.source_format}); upload a label map (NIfTI .nii/.nii.gz) or a DICOM SEG instead, or "
            "leave dicom_outputs off")


@dataclasses.dataclass
class GeneratedStudy(SourceUids):
    """A synthetic CT study on a label map's grid; stands where a DICOM SEG input's SegSource stands
    for the writers (header, referenced_series, study / series / frame-of-reference UIDs).

    labels: (X, Y, Z) uint8 volume, non-zero where a selected label is; affine_ras: its voxel (i, j, k)
    -> RAS mm affine (the NIfTI's, already in mm)."""

    labels: np.ndarray
    affine_ras: np.ndarray

    @classmethod
    def from_label_cloud(cls, cloud) -> GeneratedStudy:
        """The study of a label-map cloud straight from the loader (its points are voxel centres)."""
        from ..pointcloud import mask_voxel_indices

        require_voxel_grid(cloud)
        affine = np.asarray(cloud.nifti_affine, dtype=np.float64)
        cols = affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0)
        if abs(float(cols[:, 0] @ cols[:, 1])) > 1e-4:
            raise RibPullInputError(
                "dicom_outputs_bad_grid",
                "the label map's first two voxel axes are not perpendicular (a sheared affine), and DICOM "
                "image rows and columns must be; resample the label map onto a grid without shear, or leave "
                "dicom_outputs off")
        labels = np.zeros(tuple(int(n) for n in cloud.nifti_shape[:3]), dtype=np.uint8)
        labels[tuple(mask_voxel_indices(cloud).T)] = 1
        return cls(labels=labels, affine_ras=affine)

    @cached_property
    def ct(self) -> list:
        """The CT slices (pydicom Datasets, LPS patient frame), generated on first use."""
        from .synthetic import ct_series_from_labels

        return ct_series_from_labels(self.labels, self.affine_ras, patient_id=PATIENT_ID, patient_name=PATIENT_NAME)

    @property
    def header(self):
        """The first CT slice: patient, study and frame of reference of every output."""
        return self.ct[0]

    @property
    def referenced_series(self) -> list[tuple[str, list[tuple[str, str]]]]:
        return [(self.series_uid, [(CT_SOP_CLASS_UID, str(ds.SOPInstanceUID)) for ds in self.ct])]

    @property
    def source_images(self) -> list:
        """Every CT slice: the images the output SEG is derived from."""
        return self.ct

    def write_ct_zip(self, path: str | Path) -> Path:
        """The CT slices as DICOM files (ct_0001.dcm ...) in a deflated zip; returns the path."""
        from io import BytesIO

        path = Path(path)
        with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as zf:
            for ds in self.ct:
                buf = BytesIO()
                ds.save_as(buf, enforce_file_format=True)
                zf.writestr(f"ct_{int(ds.InstanceNumber):04d}.dcm", buf.getvalue())
        return path

    def write_outputs(self, outdir: str | Path, cloud, mesh, sdf_mm: np.ndarray, sdf_affine_ras: np.ndarray,
                      metrics: dict) -> dict[str, Path]:
        """seg.dcm, measurements_sr.dcm, mesh_stl.dcm and study_ct.zip of a NIfTI input's fit into
        `outdir`; returns {artifact name: path}.

        cloud / mesh: the fitted cloud and the reconstruction, RAS mm; sdf_mm / sdf_affine_ras: the
        signed distance volume on the label map's grid (voxel (i, j, k) -> RAS mm; every s-th voxel
        when the SDF grid is strided). All are converted to LPS, the volume to (slice, row, column)."""
        from .export import write_dicom_outputs

        outdir = Path(outdir)
        lps_mesh = mesh.copy()
        lps_mesh.apply_transform(LPS_FROM_RAS)  # a reflection of two axes: a rotation, faces keep their winding
        lps_cloud = dataclasses.replace(cloud, points=cloud.points @ LPS_FROM_RAS[:3, :3].T, normals=None,
                                        occupancy_points=None, occupancy_inside=None, occupancy_distance_mm=None,
                                        dicom_source=self)
        volume = np.transpose(sdf_mm, _SLICE_ROW_COLUMN)
        affine = LPS_FROM_RAS @ np.asarray(sdf_affine_ras, dtype=np.float64)[:, [*_SLICE_ROW_COLUMN, 3]]
        paths = write_dicom_outputs(outdir, lps_cloud, lps_mesh, volume, affine, metrics)
        paths[STUDY_CT_ARTIFACT] = self.write_ct_zip(outdir / STUDY_CT_ARTIFACT)
        return paths
