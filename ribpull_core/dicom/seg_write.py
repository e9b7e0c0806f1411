"""The reconstructed ribs as a DICOM SEG on the source geometry: one segment per rib.

One segment per reconstructed rib, in rib order (L1..L12, then R1..R12; with all 24 present segment
n is rib RIB_NAMES[n - 1]), coded as `ribs` describes: label "L7", type Rib, side as anatomic region,
tracking id "rib_left_7". Inputs that are not ribs keep their own label and come after the ribs. The
SEG is derived from the input SEG (same patient, study and frame of reference; its ReferencedSeries
is the input SEG's series) and also references the input's own source series (e.g. the CT).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydicom.uid import generate_uid

from . import MANUFACTURER, MODEL_NAME, SOFTWARE_VERSION
from .ribs import CATEGORY_CODE, RIB_CODE, laterality_code, rib_segment_number, totalseg_class_name


def segment_numbers_for(names: dict[int, str]) -> dict[int, int]:
    """Input label value -> output segment number: ribs at their fixed number (L1 = 1 .. R12 = 24),
    anything else after 24 in label order."""
    out, extra = {}, 25
    for value in sorted(names):
        n = rib_segment_number(names[value])
        if n is None or n in out.values():
            n, extra = extra, extra + 1
        out[value] = n
    return out


def write_rib_seg(path: str | Path, source, segment_volume: np.ndarray, affine_lps: np.ndarray,
                  segment_names: dict[int, str], series_number: int = 901):
    """Write the SEG of `segment_volume` ((slices, rows, columns) uint16 segment numbers, 0 = none;
    affine_lps: voxel (slice, row, column) -> LPS mm) to `path`; segment_names: number -> name.
    source: the input's SegSource (or a NIfTI input's GeneratedStudy). Returns the written highdicom
    Segmentation."""
    import highdicom as hd

    present = sorted(int(v) for v in np.unique(segment_volume) if v)
    descriptions = [_description(n, segment_names.get(n, f"segment_{n}")) for n in present]
    remap = np.zeros(int(segment_volume.max()) + 1, dtype=np.uint16)
    remap[present] = np.arange(1, len(present) + 1)  # highdicom wants segments 1..n in order
    for i, d in enumerate(descriptions):
        d.SegmentNumber = i + 1
    volume = hd.Volume(array=remap[segment_volume], affine=np.asarray(affine_lps, dtype=np.float64),
                       coordinate_system="PATIENT", frame_of_reference_uid=source.frame_of_reference_uid)
    seg = hd.seg.Segmentation(
        source_images=source.source_images, pixel_array=volume, segmentation_type="BINARY",
        segment_descriptions=descriptions, series_instance_uid=generate_uid(), series_number=series_number,
        sop_instance_uid=generate_uid(), instance_number=1, manufacturer=MANUFACTURER,
        manufacturer_model_name=MODEL_NAME, software_versions=SOFTWARE_VERSION, device_serial_number="0",
        omit_empty_frames=True, series_description="RibPull reconstructed ribs",
        content_label="RIBPULL", content_description="ribs of the RibPull reconstruction (SparseOcc mesh)",
    )
    add_source_series_references(seg, source)
    seg.save_as(str(path))
    return seg


def add_source_series_references(ds, source) -> None:
    """Append the input's own source series (e.g. the CT) to ds.ReferencedSeriesSequence."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    seq = ds.get("ReferencedSeriesSequence") or Sequence()
    have = {str(item.SeriesInstanceUID) for item in seq}
    for series_uid, instances in source.referenced_series:
        if series_uid in have:
            continue
        item = Dataset()
        item.SeriesInstanceUID = series_uid
        refs = []
        for sop_class, sop_instance in instances:
            r = Dataset()
            r.ReferencedSOPClassUID, r.ReferencedSOPInstanceUID = sop_class, sop_instance
            refs.append(r)
        item.ReferencedInstanceSequence = Sequence(refs)
        seq.append(item)
    ds.ReferencedSeriesSequence = seq


def _description(number: int, name: str):
    import highdicom as hd
    from pydicom.sr.codedict import codes

    side = laterality_code(name)
    algo = hd.AlgorithmIdentificationSequence(
        name="RibPull SparseOcc", version=SOFTWARE_VERSION,
        family=hd.sr.CodedConcept("123110", "DCM", "Artificial Intelligence"))
    return hd.seg.SegmentDescription(
        segment_number=number, segment_label=str(name)[:64], segmented_property_category=CATEGORY_CODE,
        segmented_property_type=RIB_CODE if side is not None else codes.SCT.Bone, algorithm_type="AUTOMATIC",
        algorithm_identification=algo, tracking_uid=generate_uid(), tracking_id=totalseg_class_name(name)[:64],
        anatomic_regions=[side] if side is not None else None)
