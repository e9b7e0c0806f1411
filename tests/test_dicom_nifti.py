"""DICOM outputs on request for a NIfTI label map (params.dicom_outputs / `ribpull fit --dicom-outputs`):
a generated CT study on the map's grid (study_ct.zip) and seg.dcm, measurements_sr.dcm, mesh_stl.dcm
referencing it, in the LPS patient frame, consistent with the RAS outputs of the same fit.

Core: the phantom label map on 3 mm voxels (tests/dicomkit.py) fitted with a short smoke run (~17 s
on 2 cores) through run_pipeline. Service: the same map through the real stack over HTTP, and a point cloud with the
flag refused at submission.
"""

from __future__ import annotations

import io
import subprocess
import zipfile
from pathlib import Path

import dicomkit
import numpy as np
import orthanckit
import pydicom
import pytest
import servicekit

from ribpull_core.dicom import CT_SOP_CLASS_UID, LPS_FROM_RAS, SEG_SOP_CLASS_UID
from ribpull_core.errors import RibPullInputError

RIBS = [f"L{i}" for i in range(1, 13)] + [f"R{i}" for i in range(1, 13)]
#: a short smoke fit: the checks compare the DICOM objects with this fit's own mesh, not with the truth
FIT = {"preset": "smoke", "iterations": 120, "preview": False}
#: coarse voxels (the 2 mm study of test_dicom.py fits twice as long) still give 24 ribs in 120 iterations
SPACING_MM = 3.0
DICOM_OUTPUTS = ("seg.dcm", "measurements_sr.dcm", "mesh_stl.dcm", "study_ct.zip")


@pytest.fixture(scope="module")
def phantom_nifti(tmp_path_factory):
    import nibabel as nib

    vol, affine, _ = dicomkit.phantom_labels(SPACING_MM)
    path = tmp_path_factory.mktemp("nifti") / "ribs.nii.gz"
    nib.save(nib.Nifti1Image(vol, affine), path)
    return path


@pytest.fixture(scope="module")
def fitted(phantom_nifti, tmp_path_factory):
    from ribpull_core.pipeline import PipelineOptions, run_pipeline

    out = tmp_path_factory.mktemp("fit")
    result = run_pipeline(phantom_nifti, out, PipelineOptions(**FIT, dicom_outputs=True))
    return result.outdir


def _ct_slices(zip_path) -> list[pydicom.Dataset]:
    with zipfile.ZipFile(zip_path) as zf:
        return [pydicom.dcmread(io.BytesIO(zf.read(n))) for n in sorted(zf.namelist())]


def _stl_triangles(path) -> np.ndarray:
    """(F, 3, 3) mm triangles of an STL file, or of the STL inside an Encapsulated STL instance (.dcm)."""
    import trimesh

    data = Path(path).read_bytes()
    if Path(path).suffix == ".dcm":
        ds = pydicom.dcmread(path)
        data = bytes(ds.EncapsulatedDocument)[: int(ds.EncapsulatedDocumentLength)]
    return trimesh.load(io.BytesIO(data), file_type="stl", process=False).triangles


def test_generated_study_is_a_ct_series_on_the_label_maps_grid(fitted):
    vol, affine_ras, _ = dicomkit.phantom_labels(SPACING_MM)
    ct = _ct_slices(fitted / "study_ct.zip")
    assert len(ct) == vol.shape[2]
    assert {str(ds.SOPClassUID) for ds in ct} == {CT_SOP_CLASS_UID}
    assert len({ds.SeriesInstanceUID for ds in ct}) == 1 and len({ds.SOPInstanceUID for ds in ct}) == len(ct)
    aff = LPS_FROM_RAS @ affine_ras
    for k in (0, len(ct) // 2, len(ct) - 1):  # slice k is the map's k-th plane, in LPS mm
        ds = ct[k]
        np.testing.assert_allclose(ds.ImagePositionPatient, aff[:3, :3] @ [0, 0, k] + aff[:3, 3], atol=1e-3)
        assert (ds.Rows, ds.Columns) == (vol.shape[1], vol.shape[0])
        assert ((ds.pixel_array > 200) == (vol[:, :, k].T > 0)).all()  # bone HU where the map has a rib
    np.testing.assert_allclose(ct[0].ImageOrientationPatient, [-1, 0, 0, 0, -1, 0], atol=1e-6)  # RAS axes in LPS
    assert (fitted / "study_ct.zip").stat().st_size < 1_000_000  # deflated: the slices are mostly two values


def test_seg_has_one_coded_segment_per_rib_on_the_generated_ct(fitted):
    import highdicom as hd

    ct = _ct_slices(fitted / "study_ct.zip")
    seg = hd.seg.segread(fitted / "seg.dcm")
    assert seg.SOPClassUID == SEG_SOP_CLASS_UID
    assert sorted(seg.get_segment_description(n).SegmentLabel for n in seg.segment_numbers) == sorted(RIBS)
    for n in seg.segment_numbers:
        d = seg.get_segment_description(n)
        assert d.segmented_property_type.value == "113197003"  # Rib
        assert d.anatomic_regions[0].value == ("7771000" if d.SegmentLabel[0] == "L" else "24028007")
    assert seg.StudyInstanceUID == ct[0].StudyInstanceUID and seg.FrameOfReferenceUID == ct[0].FrameOfReferenceUID
    refs = {item.SeriesInstanceUID: {r.ReferencedSOPInstanceUID for r in item.ReferencedInstanceSequence}
            for item in seg.ReferencedSeriesSequence}
    assert refs == {ct[0].SeriesInstanceUID: {ds.SOPInstanceUID for ds in ct}}
    slices = {tuple(np.round(np.asarray(ds.ImagePositionPatient, float), 3)) for ds in ct}
    frames = {tuple(np.round(np.asarray(f.PlanePositionSequence[0].ImagePositionPatient, float), 3))
              for f in seg.PerFrameFunctionalGroupsSequence}
    assert frames <= slices and len(frames) > len(slices) // 2  # every frame lies on a CT slice
    assert str(seg.SharedFunctionalGroupsSequence[0].PlaneOrientationSequence[0].ImageOrientationPatient) \
        == str(ct[0].ImageOrientationPatient)


def test_seg_voxels_lie_within_a_voxel_of_the_fitted_mesh_in_lps(fitted):
    import highdicom as hd
    import trimesh
    from scipy.spatial import cKDTree

    seg = hd.seg.segread(fitted / "seg.dcm")
    v = seg.get_volume(dtype=np.uint8, combine_segments=True)
    ijk = np.argwhere(v.array.reshape(v.spatial_shape) > 0)
    centres = ijk @ v.affine[:3, :3].T + v.affine[:3, 3]
    voxel = float(np.linalg.norm(v.spacing))  # the voxel diagonal, as test_dicomweb.py measures a SEG input's
    mesh = trimesh.load(fitted / "mesh.ply", process=False)
    mesh.apply_transform(LPS_FROM_RAS)  # mesh.ply is RAS, the SEG LPS
    surface = mesh.sample(100_000, seed=0)
    d_seg_to_mesh = cKDTree(surface).query(centres, workers=-1)[0]
    d_mesh_to_seg = cKDTree(centres).query(surface, workers=-1)[0]
    assert len(centres) > 1000
    assert np.percentile(d_seg_to_mesh, 99.5) <= voxel and np.percentile(d_mesh_to_seg, 99.5) <= voxel, (
        np.percentile(d_seg_to_mesh, [50, 99.5, 100]), np.percentile(d_mesh_to_seg, [50, 99.5, 100]), voxel)
    # the check sees frames: the RAS mesh (x, y not negated) does not fit the SEG
    ras = trimesh.load(fitted / "mesh.ply", process=False).sample(100_000, seed=0)
    assert np.percentile(cKDTree(ras).query(centres, workers=-1)[0], 50) > voxel


def test_sr_measures_every_rib_and_references_the_seg_and_the_ct(fitted):
    import highdicom as hd

    ct = _ct_slices(fitted / "study_ct.zip")
    seg = pydicom.dcmread(fitted / "seg.dcm")
    sr = hd.sr.srread(fitted / "measurements_sr.dcm")
    assert sr.StudyInstanceUID == ct[0].StudyInstanceUID
    groups = sr.content.get_volumetric_roi_measurement_groups()
    assert sorted(g.tracking_identifier for g in groups) == sorted(RIBS)
    segment_of = {str(s.SegmentLabel): int(s.SegmentNumber) for s in seg.SegmentSequence}
    for g in groups:
        ref = g.referenced_segment
        assert ref.referenced_sop_instance_uid == seg.SOPInstanceUID
        assert ref.referenced_segment_numbers == [segment_of[g.tracking_identifier]]
        assert ref.source_series_for_segmentation.value == ct[0].SeriesInstanceUID
        length = g.get_measurements(name=hd.sr.CodedConcept("410668003", "SCT", "Length"))[0]
        assert length.unit.value == "mm" and 50 < length.value < 600
    evidence = {item.SeriesInstanceUID for study in sr.CurrentRequestedProcedureEvidenceSequence
                for item in study.ReferencedSeriesSequence}
    assert seg.SeriesInstanceUID in evidence


def test_stl_vertices_are_the_meshes_with_x_and_y_negated(fitted):
    import trimesh

    ct = _ct_slices(fitted / "study_ct.zip")
    ds = pydicom.dcmread(fitted / "mesh_stl.dcm")
    assert ds.StudyInstanceUID == ct[0].StudyInstanceUID and ds.FrameOfReferenceUID == ct[0].FrameOfReferenceUID
    assert [item.SeriesInstanceUID for item in ds.ReferencedSeriesSequence] == [ct[0].SeriesInstanceUID]
    assert ds.SourceInstanceSequence[0].ReferencedSOPInstanceUID == ct[0].SOPInstanceUID
    ply = trimesh.load(fitted / "mesh.ply", process=False)
    np.testing.assert_allclose(_stl_triangles(fitted / "mesh_stl.dcm"), ply.triangles * [-1, -1, 1], atol=1e-4)
    np.testing.assert_allclose(_stl_triangles(fitted / "mesh.stl"), ply.triangles, atol=1e-4)  # mesh.stl stays RAS


def test_nifti_outputs_stay_in_ras(fitted, phantom_nifti):
    import nibabel as nib

    assert np.allclose(nib.load(fitted / "sdf.nii.gz").affine, nib.load(phantom_nifti).affine)


def test_outputs_and_a_ct_slice_parse_with_dcmtk(fitted, tmp_path):
    orthanckit.require_dcmtk()  # installs Debian's dcmtk when missing (root), else skips
    with zipfile.ZipFile(fitted / "study_ct.zip") as zf:
        (tmp_path / "ct_0001.dcm").write_bytes(zf.read("ct_0001.dcm"))
    for path in [fitted / n for n in DICOM_OUTPUTS[:3]] + [tmp_path / "ct_0001.dcm"]:
        r = subprocess.run(["dcmdump", "-q", "+E", str(path)], check=False, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and "E:" not in r.stderr, (path.name, r.stderr[-2000:])


def test_dicom_outputs_of_a_point_cloud_are_refused(sample_ply, tmp_path):
    from ribpull_core.pipeline import PipelineOptions, run_pipeline

    with pytest.raises(RibPullInputError) as info:
        run_pipeline(sample_ply, tmp_path / "out", PipelineOptions(**FIT, dicom_outputs=True))
    assert info.value.code == "dicom_outputs_need_label_map"
    assert "label map" in info.value.message and "DICOM SEG" in info.value.message
    assert not (tmp_path / "out").exists()


def test_dicom_outputs_of_a_sheared_grid_are_refused(phantom_nifti, tmp_path):
    """DICOM rows and columns are perpendicular: a label map whose first two voxel axes are not
    fails at load with dicom_outputs_bad_grid, before any fitting, and writes nothing."""
    import nibabel as nib

    from ribpull_core.pipeline import PipelineOptions, run_pipeline

    img = nib.load(phantom_nifti)
    affine = img.affine.copy()
    affine[:3, 1] += 0.5 * affine[:3, 0]  # the column axis leans on the row axis
    sheared = tmp_path / "sheared.nii.gz"
    nib.save(nib.Nifti1Image(np.asarray(img.dataobj), affine), sheared)
    with pytest.raises(RibPullInputError) as info:
        run_pipeline(sheared, tmp_path / "out", PipelineOptions(**FIT, dicom_outputs=True))
    assert info.value.code == "dicom_outputs_bad_grid"
    assert "perpendicular" in info.value.message
    assert not (tmp_path / "out").exists()


def test_cli_flag(phantom_nifti):
    from ribpull_core.cli import build_parser

    args = build_parser().parse_args(["fit", str(phantom_nifti), "-o", "x", "--dicom-outputs"])
    assert args.dicom_outputs is True


# --- the service over HTTP -----------------------------------------------------------------------

@pytest.mark.service
def test_service_nifti_job_with_dicom_outputs(service, phantom_nifti, tmp_path):
    with service.client() as c:
        r = servicekit.submit(c, phantom_nifti, {**FIT, "dicom_outputs": True})
        assert r.status_code == 202, r.text
        job = servicekit.wait_job(c, r.json()["id"], "succeeded", timeout=420, stack=service)
        listed = {a["name"]: a for a in job["artifacts"]}
        assert set(DICOM_OUTPUTS) <= set(listed), sorted(listed)
        assert listed["study_ct.zip"]["media_type"] == "application/zip"
        for name in (*DICOM_OUTPUTS, "mesh.ply"):
            got = c.get(f"/v1/jobs/{job['id']}/artifacts/{name}")
            assert got.status_code == 200, got.text
            (tmp_path / name).write_bytes(got.content)
    ct = _ct_slices(tmp_path / "study_ct.zip")
    objects = [pydicom.dcmread(tmp_path / n) for n in DICOM_OUTPUTS[:3]]
    assert {ds.StudyInstanceUID for ds in objects} == {ct[0].StudyInstanceUID}
    assert int(objects[0].NumberOfFrames) > 0 and len(objects[0].SegmentSequence) == 24
    import trimesh

    ply = trimesh.load(tmp_path / "mesh.ply", process=False)
    np.testing.assert_allclose(_stl_triangles(tmp_path / "mesh_stl.dcm"), ply.triangles * [-1, -1, 1], atol=1e-4)


@pytest.mark.service
def test_service_refuses_dicom_outputs_for_a_point_cloud(service, sample_ply):
    with service.client() as c:
        r = servicekit.submit(c, sample_ply, {"preset": "smoke", "dicom_outputs": True})
        body = servicekit.assert_problem(r, 422)
    assert body["code"] == "dicom_outputs_need_label_map"
    assert "label map" in body["detail"] and "DICOM SEG" in body["detail"]
