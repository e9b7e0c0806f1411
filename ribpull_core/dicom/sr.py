"""Rib measurements as a DICOM structured report: TID 1500 Measurement Report (highdicom) in a
Comprehensive 3D SR.

One measurement group per rib curve of the skeleton (tracking id = the rib name, finding site = the
rib with its laterality, referencing the rib's segment in RibPull's output SEG): centerline length,
mean radius and minimum radius, all in mm (UCUM "mm"). One more group holds the surface metrics of
the reconstruction against its input (Chamfer L1, Hausdorff, F-score, normal consistency), coded in
RibPull's private scheme "99RIBPULL" (DICOM has no codes for them).
"""

from __future__ import annotations

from pathlib import Path

from pydicom.sr.codedict import codes
from pydicom.uid import generate_uid

from . import MANUFACTURER
from .ribs import RIB_CODE, laterality_code

PRIVATE_SCHEME = "99RIBPULL"
#: metrics.json "surface" key -> (code value, meaning, UCUM unit)
SURFACE_MEASURES = {
    "cd_l1_mm": ("CDL1", "Chamfer distance L1 to input", ("mm", "UCUM", "millimeter")),
    "hausdorff_mm": ("HD", "Hausdorff distance to input", ("mm", "UCUM", "millimeter")),
    "fscore": ("FSCORE", "F-score at tau", ("1", "UCUM", "no units")),
    "normal_consistency": ("NC", "Normal consistency", ("1", "UCUM", "no units")),
}


def write_measurement_report(path: str | Path, source, seg, metrics: dict, segment_of: dict[str, int],
                             series_number: int = 902):
    """Write the report to `path`; returns the highdicom Comprehensive3DSR.

    seg: RibPull's output SEG (highdicom Segmentation), referenced by each rib's group;
    metrics: the pipeline's metrics dict (skeleton curves, surface); segment_of: rib name -> segment
    number in `seg`."""
    import highdicom as hd

    mm = codes.UCUM.Millimeter
    algo = hd.sr.AlgorithmIdentification(name="RibPull", version="0.1.0")
    groups = []
    for curve in (metrics.get("skeleton") or {}).get("curves") or []:
        name = str(curve.get("label") or "")
        if not name:
            continue
        measurements = [hd.sr.Measurement(name=codes.SCT.Length, value=float(curve["length_mm"]), unit=mm,
                                          algorithm_id=algo)]
        for key, derivation in (("mean_radius_mm", codes.SCT.Mean), ("min_radius_mm", codes.SCT.Minimum)):
            if curve.get(key) is not None:
                measurements.append(hd.sr.Measurement(name=codes.SCT.Radius, value=float(curve[key]), unit=mm,
                                                      derivation=derivation, algorithm_id=algo))
        side = laterality_code(name)
        site = hd.sr.FindingSite(anatomic_location=RIB_CODE, laterality=side) if side is not None else None
        kw = {}
        if name in segment_of:
            kw["referenced_segment"] = hd.sr.ReferencedSegment(
                sop_class_uid=seg.SOPClassUID, sop_instance_uid=seg.SOPInstanceUID,
                segment_number=int(segment_of[name]),
                source_series=hd.sr.SourceSeriesForSegmentation(source.referenced_series[0][0]))
        else:  # a curve without a segment: referenced to the output SEG's series only
            kw["referenced_segment"] = hd.sr.ReferencedSegment(
                sop_class_uid=seg.SOPClassUID, sop_instance_uid=seg.SOPInstanceUID, segment_number=1,
                source_series=hd.sr.SourceSeriesForSegmentation(source.referenced_series[0][0]))
        groups.append(hd.sr.VolumetricROIMeasurementsAndQualitativeEvaluations(
            tracking_identifier=hd.sr.TrackingIdentifier(uid=generate_uid(), identifier=name),
            finding_type=RIB_CODE, finding_sites=[site] if site else None, algorithm_id=algo,
            measurements=measurements, **kw))
    surface = metrics.get("surface") or {}
    surface_measurements = []
    for key, (value, meaning, unit) in SURFACE_MEASURES.items():
        if surface.get(key) is None:
            continue
        surface_measurements.append(hd.sr.Measurement(
            name=hd.sr.CodedConcept(value, PRIVATE_SCHEME, meaning), value=float(surface[key]),
            unit=hd.sr.CodedConcept(*unit), algorithm_id=algo))
    if surface_measurements:
        groups.append(hd.sr.MeasurementsAndQualitativeEvaluations(
            tracking_identifier=hd.sr.TrackingIdentifier(uid=generate_uid(), identifier="surface metrics"),
            algorithm_id=algo, measurements=surface_measurements))
    context = hd.sr.ObservationContext(
        observer_person_context=None,
        observer_device_context=hd.sr.ObserverContext(
            observer_type=codes.DCM.Device,
            observer_identifying_attributes=hd.sr.DeviceObserverIdentifyingAttributes(
                uid=generate_uid(), name="RibPull", manufacturer_name=MANUFACTURER)))
    report = hd.sr.MeasurementReport(observation_context=context,
                                     procedure_reported=codes.LN.CTUnspecifiedBodyRegion,
                                     imaging_measurements=groups)
    sr = hd.sr.Comprehensive3DSR(
        evidence=[seg], content=report, series_instance_uid=generate_uid(), series_number=series_number,
        sop_instance_uid=generate_uid(), instance_number=1, manufacturer=MANUFACTURER,
        series_description="RibPull rib measurements", is_complete=True)
    sr.save_as(str(path))
    return sr
