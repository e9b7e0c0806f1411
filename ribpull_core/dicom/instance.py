"""A new, empty DICOM instance of one SOP class: file meta (explicit VR little endian) and a fresh
SOP Instance UID. The writers (stl.py) and the synthetic CT (synthetic.py) fill in the rest. And the
identity the writers take from an output's source (`SourceUids`)."""

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


class SourceUids:
    """The UIDs the output writers take from a source's `header` (a dataset): its study, series,
    SOP instance and frame of reference. Mixed into seg_read.SegSource (an input SEG) and
    nifti_source.GeneratedStudy (a NIfTI input's generated CT), which supply `header`."""

    header: Dataset

    @property
    def study_uid(self) -> str:
        return str(self.header.StudyInstanceUID)

    @property
    def series_uid(self) -> str:
        return str(self.header.SeriesInstanceUID)

    @property
    def sop_instance_uid(self) -> str:
        return str(self.header.SOPInstanceUID)

    @property
    def frame_of_reference_uid(self) -> str:
        return str(self.header.FrameOfReferenceUID)
