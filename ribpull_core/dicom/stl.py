"""The reconstructed mesh as an Encapsulated STL instance (the IOD DICOM defines for 3-D models).

The STL bytes are the mesh in the LPS patient coordinates of the source (mm), so the model overlays
the CT; the instance shares the source's patient, study and frame of reference, and references the
input SEG and its source series (e.g. the CT) through SourceInstanceSequence / ReferencedSeriesSequence.
For a NIfTI input the source is its generated study (nifti_source.GeneratedStudy): the STL is derived
from the first generated CT slice and references the generated CT series.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

from pydicom.dataset import Dataset
from pydicom.sequence import Sequence
from pydicom.uid import generate_uid

from . import ENCAPSULATED_STL_SOP_CLASS_UID, MANUFACTURER, MODEL_NAME, SOFTWARE_VERSION
from .instance import new_instance
from .seg_read import PATIENT_STUDY_KEYWORDS


def stl_bytes(mesh) -> bytes:
    """Binary STL of a trimesh mesh (its own coordinates, mm)."""
    return mesh.export(file_type="stl")


def write_encapsulated_stl(path: str | Path, source, mesh, series_number: int = 903,
                           title: str = "RibPull rib surface") -> Dataset:
    """Write `mesh` (trimesh, LPS mm) as Encapsulated STL Storage to `path`; returns the dataset."""
    now = _dt.datetime.now()
    ds = new_instance(ENCAPSULATED_STL_SOP_CLASS_UID)
    for kw in PATIENT_STUDY_KEYWORDS:  # patient, study and frame of reference of the source
        setattr(ds, kw, source.header.get(kw, ""))
    ds.Modality = "M3D"
    ds.SeriesInstanceUID = generate_uid()
    ds.SeriesNumber, ds.InstanceNumber = series_number, 1
    ds.SeriesDescription = title
    ds.Manufacturer, ds.ManufacturerModelName = MANUFACTURER, MODEL_NAME
    ds.SoftwareVersions, ds.DeviceSerialNumber = SOFTWARE_VERSION, "0"
    ds.PositionReferenceIndicator = ""
    ds.ContentDate, ds.ContentTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    ds.AcquisitionDateTime = now.strftime("%Y%m%d%H%M%S")
    ds.BurnedInAnnotation = "NO"
    ds.DocumentTitle = title
    ds.ConceptNameCodeSequence = Sequence()
    ds.MIMETypeOfEncapsulatedDocument = "model/stl"
    data = stl_bytes(mesh)
    ds.EncapsulatedDocumentLength = len(data)
    ds.EncapsulatedDocument = data + (b"\x00" if len(data) % 2 else b"")  # OB values have even length
    units = Dataset()  # Manufacturing 3D Model module: the STL's coordinates are millimetres
    units.CodeValue, units.CodingSchemeDesignator, units.CodeMeaning = "mm", "UCUM", "millimeter"
    ds.MeasurementUnitsCodeSequence = Sequence([units])
    ref = Dataset()  # derived from the input SEG
    ref.ReferencedSOPClassUID = source.header.SOPClassUID
    ref.ReferencedSOPInstanceUID = source.sop_instance_uid
    ds.SourceInstanceSequence = Sequence([ref])
    from .seg_write import add_source_series_references

    add_source_series_references(ds, source)
    if source.series_uid not in {str(s.SeriesInstanceUID) for s in ds.ReferencedSeriesSequence}:
        item = Dataset()  # ... and the input SEG's own series first (a generated CT is listed already)
        item.SeriesInstanceUID = source.series_uid
        inst = Dataset()
        inst.ReferencedSOPClassUID, inst.ReferencedSOPInstanceUID = ref.ReferencedSOPClassUID, ref.ReferencedSOPInstanceUID
        item.ReferencedInstanceSequence = Sequence([inst])
        ds.ReferencedSeriesSequence.insert(0, item)
    ds.save_as(str(path), enforce_file_format=True)
    return ds
