"""A synthetic CT series and a rib DICOM SEG made from a label map, for tests and demos.

`ct_series_from_labels` writes one CT slice per index along the label volume's third axis, in the
LPS patient frame (the label map's RAS affine converted), with bone-like Hounsfield units where a
label is set; `seg_from_labels` encodes the label map as a multi-frame SEG on those slices (one
segment per label, named like TotalSegmentator's DICOM SEG: "rib_left_7" ...), referencing them.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset
from pydicom.uid import generate_uid

from . import CT_SOP_CLASS_UID, LPS_FROM_RAS, MODEL_NAME, SOFTWARE_VERSION
from .instance import new_instance
from .ribs import CATEGORY_CODE, RIB_CODE, rib_side_number

#: not "RibPull": these stand for a scanner's and a segmenter's objects, not RibPull's results
MANUFACTURER = "RibPull synthetic study"
BONE_HU = 700
TISSUE_HU = 40


def ct_series_from_labels(labels: np.ndarray, affine_ras: np.ndarray, *, patient_id: str = "RIBPULL-PHANTOM",
                          patient_name: str = "Phantom^Rib", study_uid: str | None = None) -> list[Dataset]:
    """(X, Y, Z) label volume + its voxel -> RAS mm affine -> Z CT Image datasets (int16 HU, one per
    k), pixel (row j, column i), in the LPS patient frame. The affine's first two columns must be
    orthogonal (any voxel size; the slices may be oblique)."""
    aff = LPS_FROM_RAS @ np.asarray(affine_ras, dtype=np.float64)
    spacing = np.linalg.norm(aff[:3, :3], axis=0)
    row_dir, col_dir = aff[:3, 0] / spacing[0], aff[:3, 1] / spacing[1]
    study_uid = study_uid or generate_uid()
    series_uid, for_uid = generate_uid(), generate_uid()
    today = _dt.date.today().strftime("%Y%m%d")
    out = []
    for k in range(labels.shape[2]):
        ds = new_instance(CT_SOP_CLASS_UID)
        ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = patient_name, patient_id, "", "O"
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study_uid, series_uid, for_uid
        ds.StudyDate = ds.SeriesDate = ds.ContentDate = today
        ds.StudyTime = ds.SeriesTime = ds.ContentTime = "120000"
        ds.StudyID, ds.AccessionNumber, ds.ReferringPhysicianName = "1", "", ""
        ds.Modality, ds.SeriesNumber, ds.InstanceNumber = "CT", 1, k + 1
        ds.Manufacturer, ds.ManufacturerModelName, ds.SoftwareVersions = MANUFACTURER, MODEL_NAME, SOFTWARE_VERSION
        ds.PositionReferenceIndicator = ""
        ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
        ds.ImageOrientationPatient = [float(v) for v in (*row_dir, *col_dir)]
        ds.ImagePositionPatient = [float(v) for v in aff[:3, :3] @ [0, 0, k] + aff[:3, 3]]
        ds.PixelSpacing = [float(spacing[1]), float(spacing[0])]  # row spacing (between rows), column spacing
        ds.SliceThickness = float(spacing[2])
        ds.KVP, ds.AcquisitionNumber = 120, 1
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.Rows, ds.Columns = int(labels.shape[1]), int(labels.shape[0])
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = 0, 1, "HU"
        hu = np.where(labels[:, :, k].T > 0, BONE_HU, TISSUE_HU).astype(np.int16)
        ds.PixelData = hu.tobytes()
        out.append(ds)
    return out


def seg_from_labels(ct: list[Dataset], labels: np.ndarray, names: dict[int, str], *,
                    fractional: bool = False) -> Dataset:
    """A multi-frame SEG of `labels` (the (X, Y, Z) volume `ct` was made from) on the slices of `ct`:
    one segment per label value in `names` (segment numbers 1.. in sorted label order), segment label
    = the name, coded as Rib + laterality when the name is a rib. BINARY, or FRACTIONAL (probability 0 or 1, stored as 0 / 255)."""
    import highdicom as hd

    values = sorted(names)
    stack = np.stack([labels[:, :, k].T for k in range(labels.shape[2])])  # (frames, rows, cols)
    masks = np.stack([stack == v for v in values], axis=-1).astype(np.uint8)
    descriptions = [_segment_description(i + 1, names[v]) for i, v in enumerate(values)]
    seg = hd.seg.Segmentation(
        source_images=ct, pixel_array=masks.astype(np.float32) if fractional else masks,
        segmentation_type="FRACTIONAL" if fractional else "BINARY",
        segment_descriptions=descriptions, series_instance_uid=generate_uid(), series_number=100,
        sop_instance_uid=generate_uid(), instance_number=1, manufacturer=MANUFACTURER,
        manufacturer_model_name=MODEL_NAME, software_versions=SOFTWARE_VERSION, device_serial_number="0",
        max_fractional_value=255, omit_empty_frames=True, series_description="synthetic rib segmentation",
    )
    return seg


def _segment_description(number: int, name: str):
    import highdicom as hd

    sn = rib_side_number(name)
    algo = hd.AlgorithmIdentificationSequence(name="synthetic", version=SOFTWARE_VERSION,
                                              family=hd.sr.CodedConcept("123109", "DCM", "Manual Processing"))
    from pydicom.sr.codedict import codes

    return hd.seg.SegmentDescription(
        segment_number=number, segment_label=str(name), segmented_property_category=CATEGORY_CODE,
        segmented_property_type=RIB_CODE if sn else codes.SCT.Bone, algorithm_type="AUTOMATIC",
        algorithm_identification=algo, tracking_uid=generate_uid(), tracking_id=str(name))


def write_datasets(datasets: list[Dataset], outdir: str | Path, prefix: str) -> list[Path]:
    """Write datasets as <outdir>/<prefix>_<0001>.dcm; returns the paths."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, ds in enumerate(datasets):
        p = outdir / f"{prefix}_{i + 1:04d}.dcm"
        ds.save_as(p, enforce_file_format=True)
        paths.append(p)
    return paths
