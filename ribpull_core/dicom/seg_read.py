"""DICOM SEG -> the label-map point cloud the pipeline fits (mm, LPS patient frame).

A SEG (binary or fractional, multi-frame, frames in any order, empty frames omitted or not) becomes
an integer label volume whose values are segment numbers, on the grid its frames span (highdicom's
`get_volume`: slices sorted along the common normal, voxel index -> LPS mm affine from the per-frame
plane positions, the plane orientation and the pixel spacing). That volume then goes through the same
code as a NIfTI label map (`ribpull_core.io.label_volume_cloud`), so a SEG is fitted exactly like the
equivalent NIfTI, only in the LPS frame. A fractional segment is inside where its value passes half
the maximum (probability or occupancy > 0.5).

Which segments are ribs: `labels` (segment numbers) when given; else every segment whose label
names a rib ("rib_left_7", "L7", "left rib 7") or whose segmented property type is Rib
(SCT 113197003); else the single segment of a one-segment SEG. Anything else is refused with a
message that lists the segments.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import RibPullInputError
from ..pointcloud import PointCloud
from . import SEG_SOP_CLASS_UID
from .instance import SourceUids
from .ribs import RIB_CODE, rib_side_number

#: attributes copied from the source SEG into every object RibPull writes for it
PATIENT_STUDY_KEYWORDS = (
    "PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyInstanceUID", "StudyDate",
    "StudyTime", "StudyID", "AccessionNumber", "ReferringPhysicianName", "FrameOfReferenceUID",
)


@dataclass
class SegSource(SourceUids):
    """What the DICOM outputs need to know about the input SEG.

    header: the SEG's dataset without its pixel data (patient, study, frame of reference, segments).
    referenced_series: [(series uid, [(sop class uid, sop instance uid), ...])] of the images the
        SEG was made from (its ReferencedSeriesSequence), e.g. the CT series.
    segment_names: segment number -> rib name ("L7") or the segment's own label.
    """

    header: object
    referenced_series: list[tuple[str, list[tuple[str, str]]]] = field(default_factory=list)
    segment_names: dict[int, str] = field(default_factory=dict)

    @property
    def source_images(self) -> list:
        """The images an output SEG is derived from: the input SEG itself."""
        return [self.header]


def load_seg(path: str | Path, labels: list[int] | None, max_points: int,
             max_voxel_bytes: int = 1024**3) -> PointCloud:
    """Read a DICOM SEG file as a label-map PointCloud in LPS mm (see the module docstring); the
    cloud's `dicom_source` is its SegSource. Raises RibPullInputError for anything the user can fix."""
    import pydicom

    try:
        ds = pydicom.dcmread(str(path))
    except Exception as exc:  # noqa: BLE001 - any parse failure is the file's fault
        raise RibPullInputError("parse_error", f"could not read the DICOM file: {type(exc).__name__}: {exc}") from None
    return seg_dataset_cloud(ds, labels, max_points, max_voxel_bytes)


def seg_dataset_cloud(ds, labels: list[int] | None, max_points: int, max_voxel_bytes: int = 1024**3) -> PointCloud:
    """`load_seg` for a pydicom Dataset already in memory (e.g. retrieved by WADO-RS)."""
    import highdicom as hd

    from ..io import label_volume_cloud

    sop = str(getattr(ds, "SOPClassUID", ""))
    if sop != SEG_SOP_CLASS_UID:
        name = getattr(getattr(ds, "SOPClassUID", None), "name", "") or sop or "no SOP class"
        raise RibPullInputError(
            "not_segmentation",
            f"this DICOM object is a {name}, not a Segmentation (SEG, {SEG_SOP_CLASS_UID}); send the rib "
            "segmentation (e.g. TotalSegmentator's --output_type dicom) instead")
    _check_geometry(ds)
    referenced = _referenced_series(ds)
    rows, cols, frames = int(ds.Rows), int(ds.Columns), int(getattr(ds, "NumberOfFrames", 1))
    if rows * cols * frames > max_voxel_bytes:
        raise RibPullInputError("too_large", f"the SEG holds {frames} frames of {rows} x {cols}; the limit is "
                                             f"{max_voxel_bytes / 2**20:.0f} MiB of voxels")
    try:
        seg = hd.seg.Segmentation.from_dataset(ds, copy=False)
    except Exception as exc:  # noqa: BLE001
        raise RibPullInputError("parse_error", f"not a valid DICOM SEG: {type(exc).__name__}: {exc}") from None
    names = {int(n): _segment_name(seg.get_segment_description(int(n))) for n in seg.segment_numbers}
    present = _non_empty_segments(ds)
    selected = _select_segments(seg, names, present, labels)
    vol, affine = _label_volume(seg, selected)
    cloud = label_volume_cloud(vol, affine, selected, {n: names[n] for n in selected}, max_points)
    header = ds.copy()
    for kw in ("PixelData", "FloatPixelData", "DoubleFloatPixelData"):
        if kw in header:
            delattr(header, kw)
    cloud.dicom_source = SegSource(header=header, referenced_series=referenced,
                                   segment_names={n: names[n] for n in selected})
    return cloud


def _check_geometry(ds) -> None:
    """Refuse a SEG whose frames cannot be placed in patient space, or lie in several orientations."""
    shared = (ds.get("SharedFunctionalGroupsSequence") or [None])[0]
    per_frame = ds.get("PerFrameFunctionalGroupsSequence") or []
    if not per_frame:
        raise RibPullInputError("seg_no_geometry", "the SEG has no per-frame functional groups, so its frames "
                                                   "have no position in patient space; export it with plane "
                                                   "positions (every standard SEG writer does)")
    if "FrameOfReferenceUID" not in ds:
        raise RibPullInputError("seg_no_geometry", "the SEG has no FrameOfReferenceUID: it is not in patient "
                                                   "space (a slide or a 2-D SEG?); a CT rib SEG is needed")

    def _item(frame, keyword):
        seq = frame.get(keyword) if frame is not None else None
        if seq:
            return seq[0]
        seq = shared.get(keyword) if shared is not None else None
        return seq[0] if seq else None

    orientations = set()
    for i, frame in enumerate(per_frame):
        pos = _item(frame, "PlanePositionSequence")
        ori = _item(frame, "PlaneOrientationSequence")
        meas = _item(frame, "PixelMeasuresSequence")
        if pos is None or "ImagePositionPatient" not in pos or ori is None or "ImageOrientationPatient" not in ori \
                or meas is None or "PixelSpacing" not in meas:
            raise RibPullInputError(
                "seg_no_geometry",
                f"frame {i + 1} of the SEG has no plane position, orientation or pixel spacing, so it cannot be "
                "placed in patient space; export the SEG with its geometry")
        orientations.add(tuple(round(float(v), 4) for v in ori.ImageOrientationPatient))
    if len(orientations) > 1:
        raise RibPullInputError(
            "seg_mixed_orientation",
            f"the SEG's frames lie in {len(orientations)} different orientations; a label volume needs one "
            "(resample the segmentation onto one stack of parallel slices)")


def _referenced_series(ds) -> list[tuple[str, list[tuple[str, str]]]]:
    out = []
    for item in ds.get("ReferencedSeriesSequence") or []:
        inst = [(str(r.ReferencedSOPClassUID), str(r.ReferencedSOPInstanceUID))
                for r in item.get("ReferencedInstanceSequence") or []]
        if "SeriesInstanceUID" in item:
            out.append((str(item.SeriesInstanceUID), inst))
    if not out:
        raise RibPullInputError(
            "seg_no_reference",
            "the SEG references no source series (ReferencedSeriesSequence is missing or empty), so the "
            "results could not be tied to the CT; export the SEG from its CT series")
    return out


def _segment_name(desc) -> str:
    label = str(getattr(desc, "SegmentLabel", "") or "")
    sn = rib_side_number(label) or rib_side_number(str(getattr(desc, "TrackingID", "") or ""))
    return f"{sn[0]}{sn[1]}" if sn else (label or f"segment_{int(desc.SegmentNumber)}")


def _is_rib(desc, name: str) -> bool:
    if rib_side_number(name):
        return True
    for item in desc.get("SegmentedPropertyTypeCodeSequence") or []:
        if str(item.get("CodeValue", "")) == RIB_CODE.value and str(item.get("CodingSchemeDesignator", "")) in ("SCT", "SRT"):
            return True
    return False


def _non_empty_segments(ds) -> set[int]:
    """Segment numbers that have at least one frame (a SEG writer omits empty frames)."""
    out = set()
    for frame in ds.get("PerFrameFunctionalGroupsSequence") or []:
        ident = frame.get("SegmentIdentificationSequence")
        if ident:
            out.add(int(ident[0].ReferencedSegmentNumber))
    shared = (ds.get("SharedFunctionalGroupsSequence") or [None])[0]
    if shared is not None and shared.get("SegmentIdentificationSequence"):
        out.add(int(shared.SegmentIdentificationSequence[0].ReferencedSegmentNumber))
    return out


def _select_segments(seg, names: dict[int, str], present: set[int], labels: list[int] | None) -> list[int]:
    listing = ", ".join(f"{n} '{names[n]}'" for n in sorted(names)[:40]) + (", ..." if len(names) > 40 else "")
    if labels is not None:
        chosen = sorted({int(v) for v in labels} & present)
        if not chosen:
            raise RibPullInputError(
                "no_labels", f"none of the requested segment numbers {sorted(set(labels))} has any voxel in the "
                             f"SEG; its segments: {listing}")
        return chosen
    ribs = [n for n in sorted(present) if _is_rib(seg.get_segment_description(n), names[n])]
    if ribs:
        return ribs
    if len(present) == 1:
        return sorted(present)
    if not present:
        raise RibPullInputError("no_labels", "every segment of the SEG is empty")
    raise RibPullInputError(
        "no_labels",
        f"no rib segments in the SEG (none is labelled like 'rib_left_7' / 'L7' or coded as Rib, SCT "
        f"{RIB_CODE.value}); its segments: {listing}; pass labels=[segment numbers] to choose")


def _label_volume(seg, selected: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(volume of segment numbers (slices, rows, columns) uint16, its voxel -> LPS mm affine)."""
    fractional = str(seg.SegmentationType) == "FRACTIONAL"
    threshold = 0.5 * float(getattr(seg, "MaximumFractionalValue", 1)) if fractional else 0.0
    vol = affine = None
    for number in selected:
        try:
            v = seg.get_volume(segment_numbers=[number], dtype=np.uint8, rescale_fractional=False)
        except (ValueError, RuntimeError) as exc:  # frames not a regular stack of parallel slices
            raise RibPullInputError(
                "seg_bad_geometry",
                f"the SEG's frames do not form a regular volume ({exc}); resample the segmentation onto "
                "evenly spaced parallel slices") from None
        if vol is None:
            vol = np.zeros(v.spatial_shape, dtype=np.uint16)
            affine = np.asarray(v.affine, dtype=np.float64)
        elif v.spatial_shape != vol.shape or not np.allclose(v.affine, affine, atol=1e-4):
            raise RibPullInputError("seg_bad_geometry", "the SEG's segments lie on different grids")
        inside = v.array.reshape(v.spatial_shape) > threshold
        vol[inside & (vol == 0)] = number  # overlapping segments: the lower number keeps the voxel
    return vol, affine
