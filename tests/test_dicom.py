"""DICOM SEG in (ribpull_core.dicom.seg_read through load_point_cloud) and SEG / SR / STL out
(ribpull_core.dicom.export), on the phantom as a synthetic CT study. No network: the writers get the
input mask as the "reconstruction" (its marching-cubes mesh and a +-1 signed distance)."""

from __future__ import annotations

import copy
import subprocess

import dicomkit
import numpy as np
import orthanckit
import pydicom
import pytest

from ribpull_core.dicom import ENCAPSULATED_STL_SOP_CLASS_UID, SEG_SOP_CLASS_UID
from ribpull_core.errors import RibPullInputError
from ribpull_core.io import _nifti_to_cloud, load_point_cloud

RIBS = [f"L{i}" for i in range(1, 13)] + [f"R{i}" for i in range(1, 13)]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    return dicomkit.phantom_study(tmp_path_factory.mktemp("study"))


def _sorted_rows(points: np.ndarray) -> np.ndarray:
    p = np.round(points, 3)
    return p[np.lexsort(p.T[::-1])]


def _nifti_cloud(study):
    import nibabel as nib

    return _nifti_to_cloud(nib.Nifti1Image(study["labels"], study["affine"]), None, 2_000_000)


def test_seg_reads_as_the_equivalent_nifti_in_lps(study):
    seg = load_point_cloud(study["seg"])
    nii = _nifti_cloud(study)
    assert seg.source_format == "dicom"
    assert len(seg.points) == len(nii.points) > 10_000
    # same voxels, in LPS: (x, y, z)_LPS = (-x, -y, z)_RAS
    np.testing.assert_allclose(_sorted_rows(seg.points), _sorted_rows(nii.points * [-1, -1, 1]), atol=1e-3)
    assert [seg.label_names[n] for n in sorted(seg.label_names)] == RIBS
    spacing = np.linalg.norm(seg.nifti_affine[:3, :3], axis=0)
    np.testing.assert_allclose(spacing, dicomkit.PHANTOM_SPACING_MM)
    src = seg.dicom_source
    assert src.study_uid == study["ct_datasets"][0].StudyInstanceUID
    assert src.referenced_series[0][0] == study["ct_datasets"][0].SeriesInstanceUID


def test_fractional_seg_with_frames_in_any_order(study, tmp_path):
    frac = dicomkit.phantom_study(tmp_path / "frac", fractional=True)["seg_dataset"]
    assert frac.SegmentationType == "FRACTIONAL"
    n, rows, cols = int(frac.NumberOfFrames), int(frac.Rows), int(frac.Columns)
    pixels = np.frombuffer(frac.PixelData, np.uint8).reshape(n, rows, cols)
    order = np.random.default_rng(0).permutation(n)
    items = list(frac.PerFrameFunctionalGroupsSequence)
    frac.PerFrameFunctionalGroupsSequence = [items[i] for i in order]
    frac.PixelData = pixels[order].tobytes()
    path = tmp_path / "shuffled.dcm"
    frac.save_as(path)
    got = load_point_cloud(path)
    want = load_point_cloud(study["seg"])
    np.testing.assert_allclose(_sorted_rows(got.points), _sorted_rows(want.points), atol=1e-3)
    assert sorted(got.label_names.values()) == sorted(RIBS)


def test_segments_chosen_by_number(study):
    cloud = load_point_cloud(study["seg"], labels=[7, 19])
    assert sorted(cloud.label_names.values()) == ["L7", "R7"]
    assert set(np.unique(cloud.labels)) == {7, 19}


def _broken(study, tmp_path, edit) -> RibPullInputError:
    ds = copy.deepcopy(study["seg_dataset"])
    edit(ds)
    path = tmp_path / "broken.dcm"
    ds.save_as(path)
    with pytest.raises(RibPullInputError) as info:
        load_point_cloud(path)
    return info.value


def test_seg_without_geometry_is_refused(study, tmp_path):
    def edit(ds):
        del ds.PerFrameFunctionalGroupsSequence[3].PlanePositionSequence
    err = _broken(study, tmp_path, edit)
    assert err.code == "seg_no_geometry" and "frame 4" in err.message


def test_seg_with_mixed_orientations_is_refused(study, tmp_path):
    def edit(ds):
        from pydicom.dataset import Dataset

        ori = Dataset()
        ori.ImageOrientationPatient = [1, 0, 0, 0, 0, -1]
        ds.PerFrameFunctionalGroupsSequence[5].PlaneOrientationSequence = [ori]
    assert _broken(study, tmp_path, edit).code == "seg_mixed_orientation"


def test_seg_without_rib_segments_is_refused(study, tmp_path):
    def edit(ds):
        from pydicom.sr.codedict import codes

        for i, item in enumerate(ds.SegmentSequence):
            item.SegmentLabel = f"organ {i}"
            item.TrackingID = f"organ {i}"
            item.SegmentedPropertyTypeCodeSequence[0].CodeValue = codes.SCT.Liver.value
    err = _broken(study, tmp_path, edit)
    assert err.code == "no_labels" and "organ 0" in err.message and "labels=" in err.message


def test_seg_without_referenced_series_is_refused(study, tmp_path):
    def edit(ds):
        del ds.ReferencedSeriesSequence
    assert _broken(study, tmp_path, edit).code == "seg_no_reference"


def test_a_ct_slice_is_not_a_segmentation(study):
    with pytest.raises(RibPullInputError) as info:
        load_point_cloud(study["ct"][0])
    assert info.value.code == "not_segmentation" and "CT Image Storage" in info.value.message


# --- writers -------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def outputs(study, tmp_path_factory):
    """The writers on the input mask as the 'reconstruction' (mesh = its marching-cubes surface)."""
    import trimesh
    from skimage.measure import marching_cubes

    from ribpull_core.dicom.export import write_dicom_outputs

    cloud = load_point_cloud(study["seg"])
    inside = np.zeros(cloud.nifti_shape, bool)
    from ribpull_core.pointcloud import mask_voxel_indices

    inside[tuple(mask_voxel_indices(cloud).T)] = True
    sdf = np.where(inside, -1.0, 1.0).astype(np.float32)
    verts, faces, _, _ = marching_cubes(np.pad(inside, 1).astype(np.float32), 0.5)
    verts = (verts - 1) @ cloud.nifti_affine[:3, :3].T + cloud.nifti_affine[:3, 3]
    mesh = trimesh.Trimesh(verts, faces, process=False)
    curves = [{"label": n, "length_mm": 100.0 + i, "mean_radius_mm": 4.0, "min_radius_mm": 2.5}
              for i, n in enumerate(RIBS)]
    metrics = {"skeleton": {"curves": curves}, "surface": {"cd_l1_mm": 0.3, "hausdorff_mm": 1.8, "fscore": 0.99,
                                                          "normal_consistency": 0.97}}
    out = tmp_path_factory.mktemp("out")
    paths = write_dicom_outputs(out, cloud, mesh, sdf, cloud.nifti_affine, metrics)
    return {"paths": paths, "cloud": cloud, "mesh": mesh, "inside": inside}


def test_output_seg_has_24_coded_rib_segments_on_the_source_geometry(study, outputs):
    import highdicom as hd

    seg = hd.seg.segread(outputs["paths"]["seg.dcm"])
    assert seg.SOPClassUID == SEG_SOP_CLASS_UID
    assert seg.number_of_segments == 24
    for n in seg.segment_numbers:
        d = seg.get_segment_description(n)
        assert d.SegmentLabel == RIBS[n - 1]
        assert d.segmented_property_type.value == "113197003"  # Rib
        assert d.anatomic_regions[0].value == ("7771000" if d.SegmentLabel[0] == "L" else "24028007")
        assert d.TrackingID.startswith("rib_left_" if d.SegmentLabel[0] == "L" else "rib_right_")
    src = outputs["cloud"].dicom_source
    assert seg.StudyInstanceUID == src.study_uid and seg.FrameOfReferenceUID == src.frame_of_reference_uid
    assert seg.SeriesInstanceUID != src.series_uid
    refs = {item.SeriesInstanceUID for item in seg.ReferencedSeriesSequence}
    assert {src.series_uid, study["ct_datasets"][0].SeriesInstanceUID} <= refs
    # the same voxels as the stand-in reconstruction, same grid: it reads back as the input
    back = load_point_cloud(outputs["paths"]["seg.dcm"])
    np.testing.assert_allclose(back.nifti_affine, outputs["cloud"].nifti_affine, atol=1e-4)
    np.testing.assert_allclose(_sorted_rows(back.points), _sorted_rows(outputs["cloud"].points), atol=1e-3)


def test_output_sr_is_a_tid1500_report_with_24_rib_measurements(outputs):
    import highdicom as hd

    sr = hd.sr.srread(outputs["paths"]["measurements_sr.dcm"])
    assert isinstance(sr, hd.sr.Comprehensive3DSR)
    groups = sr.content.get_volumetric_roi_measurement_groups()
    assert len(groups) == 24
    seg = pydicom.dcmread(outputs["paths"]["seg.dcm"])
    by_name = {}
    for g in groups:
        names = {m.name.meaning: m for m in g.get_measurements()}
        length = g.get_measurements(name=hd.sr.CodedConcept("410668003", "SCT", "Length"))[0]
        assert length.unit.value == "mm"
        radii = g.get_measurements(name=hd.sr.CodedConcept("131190003", "SCT", "Radius"))
        assert sorted(r.derivation.meaning for r in radii) == ["Mean", "Minimum"]
        assert all(r.unit.value == "mm" for r in radii)
        assert g.referenced_segment.referenced_sop_instance_uid == seg.SOPInstanceUID
        by_name[g.tracking_identifier] = (length.value, g.referenced_segment.referenced_segment_numbers[0], names)
    assert sorted(by_name) == sorted(RIBS)
    assert by_name["L1"][0] == pytest.approx(100.0) and by_name["R12"][0] == pytest.approx(123.0)
    assert by_name["R1"][1] == 13  # each rib's group points at its own segment
    assert not sr.content.get_planar_roi_measurement_groups()
    text = str(pydicom.dcmread(outputs["paths"]["measurements_sr.dcm"]))
    assert "Chamfer distance L1 to input" in text and "Hausdorff distance to input" in text


def test_output_stl_is_encapsulated_in_patient_coordinates(study, outputs):
    import io

    import trimesh

    ds = pydicom.dcmread(outputs["paths"]["mesh_stl.dcm"])
    assert ds.SOPClassUID == ENCAPSULATED_STL_SOP_CLASS_UID and ds.Modality == "M3D"
    assert ds.MIMETypeOfEncapsulatedDocument == "model/stl"
    assert ds.MeasurementUnitsCodeSequence[0].CodeValue == "mm"
    data = bytes(ds.EncapsulatedDocument)[: int(ds.EncapsulatedDocumentLength)]
    mesh = trimesh.load(io.BytesIO(data), file_type="stl")
    np.testing.assert_allclose(mesh.bounds, outputs["mesh"].bounds, atol=1e-3)  # float32 STL, LPS mm
    src = outputs["cloud"].dicom_source
    assert ds.FrameOfReferenceUID == src.frame_of_reference_uid and ds.StudyInstanceUID == src.study_uid
    assert ds.PatientID == study["ct_datasets"][0].PatientID
    assert ds.SourceInstanceSequence[0].ReferencedSOPInstanceUID == src.sop_instance_uid
    refs = [item.SeriesInstanceUID for item in ds.ReferencedSeriesSequence]
    assert refs == [src.series_uid, study["ct_datasets"][0].SeriesInstanceUID]


def test_outputs_parse_with_dcmtk(outputs):
    orthanckit.require_dcmtk()  # installs Debian's dcmtk when missing (root), else skips
    for path in outputs["paths"].values():
        r = subprocess.run(["dcmdump", "-q", "+E", str(path)], check=False, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and "E:" not in r.stderr, (path.name, r.stderr[-2000:])
