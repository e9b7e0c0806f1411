"""A new, empty DICOM instance of one SOP class: file meta (explicit VR little endian) and a fresh
SOP Instance UID. The writers (stl.py) and the synthetic CT (synthetic.py) fill in the rest."""

from __future__ import annotations

from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid


def new_instance(sop_class_uid: str) -> Dataset:
    """A Dataset with file meta and SOPClassUID / SOPInstanceUID set (the UID generated here)."""
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = sop_class_uid
    ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID = sop_class_uid
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID
    return ds
