"""Jobs that name a DICOM SEG series on a real PACS and store their DICOM results back into it:
a real Orthanc (Debian packages orthanc + orthanc-dicomweb, installed when missing) on loopback, the
real service (Redis + Celery worker + API, tests/servicekit.py) with RIBPULL_DICOMWEB_URLS set.

The phantom study (a synthetic CT series + a TotalSegmentator-style rib SEG of it) and a study made
from the real TotalSegmentator label map in ../shared/data go into Orthanc; jobs reference them by
UID; the study afterwards holds RibPull's SEG, SR and STL instances, checked object by object.
"""

from __future__ import annotations

import copy
import io
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import dicomkit
import httpx
import numpy as np
import orthanckit
import pydicom
import pytest
import servicekit
import shareddata

from ribpull_core.dicom import ENCAPSULATED_STL_SOP_CLASS_UID, SEG_SOP_CLASS_UID

pytestmark = pytest.mark.service

TOTALSEG = shareddata.TOTALSEG_EXAMPLE
RIBS = [f"L{i}" for i in range(1, 13)] + [f"R{i}" for i in range(1, 13)]
SMOKE = {"preset": "smoke", "preview": False}
SR_SOP_CLASS_UID = "1.2.840.10008.5.1.4.1.1.88.34"


class FlakyProxy:
    """A loopback HTTP proxy to Orthanc that answers 503 to the first `fail_posts` POSTs (a PACS that
    is briefly down when the results arrive) and forwards everything else."""

    def __init__(self, target: str | None = None, fail_posts: int = 1):
        proxy = self
        self.target, self.fail_posts, self.posts = target, fail_posts, 0

        class Handler(BaseHTTPRequestHandler):
            def _forward(self, method: str):
                body = self._body()
                if method == "POST":
                    proxy.posts += 1
                    if proxy.posts <= proxy.fail_posts:
                        self.send_response(503)
                        self.send_header("content-length", "0")
                        self.end_headers()
                        return
                headers = {k: v for k, v in self.headers.items()
                           if k.lower() not in ("host", "content-length", "transfer-encoding")}
                r = httpx.request(method, proxy.target + self.path, content=body, headers=headers, timeout=60)
                self.send_response(r.status_code)
                for k, v in r.headers.items():
                    if k.lower() not in ("transfer-encoding", "content-length", "connection", "content-encoding"):
                        self.send_header(k, v)
                self.send_header("content-length", str(len(r.content)))
                self.end_headers()
                self.wfile.write(r.content)

            def _body(self) -> bytes:
                if "chunked" not in self.headers.get("transfer-encoding", "").lower():
                    return self.rfile.read(int(self.headers.get("content-length") or 0))
                out = []
                while True:  # dicomweb-client streams STOW-RS bodies chunked
                    size = int(self.rfile.readline().split(b";")[0].strip() or b"0", 16)
                    if size == 0:
                        self.rfile.readline()
                        return b"".join(out)
                    out.append(self.rfile.read(size))
                    self.rfile.readline()

            def do_GET(self):
                self._forward("GET")

            def do_POST(self):
                self._forward("POST")

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def stop(self):
        self.server.shutdown()


@pytest.fixture(scope="module")
def orthanc(tmp_path_factory):
    why = orthanckit.ensure_orthanc()
    if why:
        pytest.skip(f"NO REAL PACS FOR THE DICOMWEB TESTS: {why}")
    o = orthanckit.Orthanc(tmp_path_factory.mktemp("orthanc"))
    yield o
    o.stop()


@pytest.fixture(scope="module")
def dicom_stack(tmp_path_factory, orthanc):
    """The service, allowed to talk to the Orthanc; plus `autoroute`: a second Orthanc that runs the
    auto-route recipe (scripts/orthanc_autoroute.py in Orthanc's Python plugin) against this service
    and gets the results through a proxy whose first POST fails (None without the plugin)."""
    stack = servicekit.Stack(tmp_path_factory.mktemp("dicomweb-service"))
    proxy = FlakyProxy(fail_posts=1)
    auto = None
    why = orthanckit.ensure_orthanc(("orthanc-python",))
    if why is None:
        auto = orthanckit.Orthanc(
            tmp_path_factory.mktemp("orthanc-autoroute"), plugins=[orthanckit.PLUGIN_DIR / "libOrthancPython.so"],
            extra_config={"PythonScript": str(servicekit.ROOT / "scripts" / "orthanc_autoroute.py")},
            env={"RIBPULL_URL": stack.url, "RIBPULL_API_KEY": servicekit.KEY_A,
                 "RIBPULL_PACS_DICOMWEB": "http://127.0.0.1:{port}/dicom-web",
                 "RIBPULL_DELIVER_DICOMWEB": proxy.url + "/dicom-web",
                 "RIBPULL_PARAMS": '{"preset": "smoke", "preview": false}'})
        proxy.target = auto.url
    else:
        print(f"\nNO ORTHANC PYTHON PLUGIN, the auto-route recipe is not tested: {why}")
    stack.env.update({
        "RIBPULL_DICOMWEB_URLS": ",".join([orthanc.dicomweb, proxy.url + "/dicom-web"]
                                          + ([auto.dicomweb] if auto else [])),
        "RIBPULL_DICOMWEB_BACKOFF_S": "0.5", "RIBPULL_DICOMWEB_MAX_ATTEMPTS": "3", "RIBPULL_DICOMWEB_TIMEOUT_S": "30",
    })
    stack.autoroute, stack.proxy = auto, proxy
    try:
        yield from stack.serve()
    finally:
        proxy.stop()
        if auto is not None:
            auto.stop()


@pytest.fixture(scope="module")
def phantom_in_pacs(orthanc, tmp_path_factory):
    study = dicomkit.phantom_study(tmp_path_factory.mktemp("phantom-study"))
    orthanc.upload(study["ct"] + [study["seg"]])
    return study


def _job_body(orthanc_url: str, seg_ds, deliver: str | None, params: dict | None = None) -> dict:
    body = {"source": {"dicomweb": {"url": orthanc_url, "study_uid": str(seg_ds.StudyInstanceUID),
                                    "series_uid": str(seg_ds.SeriesInstanceUID)}},
            "params": params or SMOKE}
    if deliver:
        body["deliver"] = {"dicomweb": {"url": deliver}}
    return body


def _submit(stack, body: dict) -> dict:
    with stack.client() as c:
        r = c.post("/v1/jobs", json=body)
    assert r.status_code == 202, r.text
    assert r.headers["location"] == f"/v1/jobs/{r.json()['id']}"
    return r.json()


def _wait_delivery(stack, job_id: str, timeout: float = 120) -> dict:
    def finished():
        job = c.get(f"/v1/jobs/{job_id}").json()
        return job if (job["delivery"] or {}).get("status") in ("delivered", "failed") else None

    with stack.client() as c:
        return orthanckit.wait_until(finished, timeout, "the DICOMweb delivery")


def _new_instances(orthanc, study_uid: str, known_series: set[str]) -> dict[str, pydicom.Dataset]:
    """WADO-RS every instance of the series RibPull added to the study, by SOP class."""
    from dicomweb_client.api import DICOMwebClient

    web = DICOMwebClient(orthanc.dicomweb)
    out = {}
    for series in orthanc.study_series(study_uid):
        uid = series["0020000E"]["Value"][0]
        if uid in known_series:
            continue
        for ds in web.retrieve_series(study_uid, uid):
            out[str(ds.SOPClassUID)] = ds
    return out


def _check_results(stack, study, job, results: dict[str, pydicom.Dataset], ribs: list[str]) -> dict:
    """SEG, SR and STL in the study: references, segments / measurements per rib, SEG vs mesh."""
    import highdicom as hd
    import trimesh

    in_seg = study["seg_dataset"]
    ct_series = str(study["ct_datasets"][0].SeriesInstanceUID)
    assert set(results) == {SEG_SOP_CLASS_UID, SR_SOP_CLASS_UID, ENCAPSULATED_STL_SOP_CLASS_UID}, sorted(results)
    for ds in results.values():  # same patient, study, frame of reference as the source
        assert ds.StudyInstanceUID == in_seg.StudyInstanceUID and ds.PatientID == in_seg.PatientID
    seg = hd.seg.Segmentation.from_dataset(results[SEG_SOP_CLASS_UID])
    assert seg.FrameOfReferenceUID == in_seg.FrameOfReferenceUID
    assert {in_seg.SeriesInstanceUID, ct_series} <= {s.SeriesInstanceUID for s in seg.ReferencedSeriesSequence}
    labels = [str(seg.get_segment_description(n).SegmentLabel) for n in seg.segment_numbers]
    assert labels == ribs
    assert all(seg.get_segment_description(n).segmented_property_type.value == "113197003"
               for n in seg.segment_numbers)

    sr = hd.sr.Comprehensive3DSR.from_dataset(results[SR_SOP_CLASS_UID])
    groups = sr.content.get_volumetric_roi_measurement_groups()
    assert sorted(g.tracking_identifier for g in groups) == sorted(ribs)
    for g in groups:
        assert g.referenced_segment.referenced_sop_instance_uid == seg.SOPInstanceUID
        (length,) = g.get_measurements(name=hd.sr.CodedConcept("410668003", "SCT", "Length"))
        assert length.unit.value == "mm" and 20 < length.value < 600
    curves = {c["label"]: c["length_mm"] for c in job["metrics"]["skeleton"]["curves"]}
    for g in groups:  # the SR's numbers are the job's own
        (length,) = g.get_measurements(name=hd.sr.CodedConcept("410668003", "SCT", "Length"))
        assert length.value == pytest.approx(curves[g.tracking_identifier], rel=1e-6)

    stl = results[ENCAPSULATED_STL_SOP_CLASS_UID]
    assert stl.MIMETypeOfEncapsulatedDocument == "model/stl" and stl.FrameOfReferenceUID == in_seg.FrameOfReferenceUID
    assert stl.SourceInstanceSequence[0].ReferencedSOPInstanceUID == in_seg.SOPInstanceUID
    assert ct_series in {s.SeriesInstanceUID for s in stl.ReferencedSeriesSequence}
    mesh = trimesh.load(io.BytesIO(bytes(stl.EncapsulatedDocument)[: int(stl.EncapsulatedDocumentLength)]),
                        file_type="stl")

    # the SEG's ribs lie within a voxel of the fitted mesh (both ways), in LPS mm
    vol = seg.get_volume(dtype=np.uint8, combine_segments=True)
    ijk = np.argwhere(vol.array.reshape(vol.spatial_shape) > 0)
    centres = ijk @ vol.affine[:3, :3].T + vol.affine[:3, 3]
    voxel = float(np.linalg.norm(vol.spacing))  # the voxel diagonal
    from scipy.spatial import cKDTree

    surface = trimesh.sample.sample_surface(mesh, 100_000, seed=0)[0]
    d_seg_to_mesh = cKDTree(surface).query(centres, workers=-1)[0]
    d_mesh_to_seg = cKDTree(centres).query(surface, workers=-1)[0]
    # and they are inside the fitted field: the job's own /query at the SEG's voxel centres (LPS mm)
    sample = centres[np.linspace(0, len(centres) - 1, min(len(centres), 4000)).astype(int)]
    with stack.client() as c:
        r = c.post(f"/v1/jobs/{job['id']}/query", json={"points_mm": sample.tolist()})
    assert r.status_code == 200, r.text
    sdf = np.array([np.inf if v is None else v for v in r.json()["sdf_mm"]])
    assert np.mean(sdf <= 0.5 * voxel) > 0.99, np.percentile(sdf, [50, 99, 100])
    assert np.percentile(d_seg_to_mesh, 99.5) <= voxel and np.percentile(d_mesh_to_seg, 99.5) <= voxel, (
        np.percentile(d_seg_to_mesh, [50, 99.5, 100]), np.percentile(d_mesh_to_seg, [50, 99.5, 100]), voxel)
    return {"seg_voxels": len(centres), "voxel_mm": voxel}


def test_phantom_job_by_dicomweb_reference_lands_seg_sr_stl_in_the_study(dicom_stack, orthanc, phantom_in_pacs):
    t_start = time.monotonic()
    seg_in = phantom_in_pacs["seg_dataset"]
    known = {s["0020000E"]["Value"][0] for s in orthanc.study_series(seg_in.StudyInstanceUID)}
    t0 = time.monotonic()
    job = _submit(dicom_stack, _job_body(orthanc.dicomweb, seg_in, orthanc.dicomweb))
    assert job["status"] == "queued" and job["input"]["format"] == "dicomweb"
    assert job["source"]["dicomweb"]["series_uid"] == seg_in.SeriesInstanceUID
    assert job["delivery"] == {"url": orthanc.dicomweb, "status": "pending", "attempts": 0, "error": None}
    with dicom_stack.client() as c:
        done = servicekit.wait_job(c, job["id"], "succeeded", timeout=300, stack=dicom_stack)
    job = _wait_delivery(dicom_stack, job["id"])
    elapsed = time.monotonic() - t0
    assert job["delivery"]["status"] == "delivered", (job["delivery"], dicom_stack.tail())
    assert job["delivery"]["attempts"] == 1 and job["attempts"] == 1
    names = {a["name"]: a["bytes"] for a in done["artifacts"]}
    assert {"seg.dcm", "measurements_sr.dcm", "mesh_stl.dcm", "mesh.ply", "sdf.nii.gz"} <= set(names)
    assert done["metrics"]["input"]["format"] == "dicom" and done["metrics"]["skeleton"]["n_curves"] == 24
    t_done = time.monotonic()
    print(f"\njob done after {elapsed:.1f} s: timings {done['metrics']['timings_s']}")
    results = _new_instances(orthanc, seg_in.StudyInstanceUID, known)
    figures = _check_results(dicom_stack, phantom_in_pacs, done, results, RIBS)
    print(f"\nDICOMweb phantom job end to end (submit -> results in the PACS): {elapsed:.1f} s; "
          f"timings {done['metrics']['timings_s']}; outputs "
          + ", ".join(f"{n} {names[n]} B" for n in ("seg.dcm", "measurements_sr.dcm", "mesh_stl.dcm"))
          + f"; SEG voxels {figures['seg_voxels']}; test setup {t0 - t_start:.1f} s, checks "
          f"{time.monotonic() - t_done:.1f} s")


def _totalseg_study(tmp: Path) -> dict:
    """The real TotalSegmentator label map as a CT series + SEG: its 12 ribs as "rib_left_7" ...,
    plus its other structures as non-rib segments ("structure_<id>"), which must be left out."""
    import nibabel as nib

    from ribpull_core.dicom.synthetic import ct_series_from_labels, seg_from_labels, write_datasets
    from ribpull_core.io import totalseg_rib_names

    img = nib.load(str(TOTALSEG))
    vol = np.asarray(img.dataobj).astype(np.uint8)
    present = [int(v) for v in np.unique(vol) if v]
    ribs = totalseg_rib_names()
    names = {v: ribs.get(v, f"structure_{v}") for v in present}
    ct = ct_series_from_labels(vol, img.affine, patient_id="RIBPULL-TOTALSEG")
    seg = seg_from_labels(ct, vol, names)
    tmp.mkdir(parents=True, exist_ok=True)
    seg.save_as(tmp / "seg.dcm")
    return {"ct": write_datasets(ct, tmp / "ct", "ct"), "seg": tmp / "seg.dcm", "ct_datasets": ct,
            "seg_dataset": seg, "rib_names": [n for v, n in sorted(names.items()) if v in ribs]}


@pytest.mark.skipif(not TOTALSEG.exists(), reason=f"{TOTALSEG} is missing")
def test_real_totalsegmentator_seg_auto_routed_by_orthanc_to_a_pacs_that_fails_the_first_store(
        dicom_stack, orthanc, tmp_path):
    """The auto-route recipe (docs/service.md): Orthanc's Python plugin posts the job when the SEG
    arrives (without the plugin, the test posts it). Ribs are picked by their labels among other
    structures; the first STOW-RS answer is a 503, the delivery is retried and lands, the fit ran once."""
    from ribpull_core.dicom.ribs import rib_side_number

    pacs, proxy = dicom_stack.autoroute or orthanc, dicom_stack.proxy
    proxy.target = pacs.url
    study = _totalseg_study(tmp_path / "ts")
    seg_in = study["seg_dataset"]
    posts_before = proxy.posts
    pacs.upload(study["ct"])
    known = {s["0020000E"]["Value"][0] for s in pacs.study_series(seg_in.StudyInstanceUID)}
    known.add(str(seg_in.SeriesInstanceUID))
    pacs.upload([study["seg"]])
    if dicom_stack.autoroute is not None:  # Orthanc posts the job once the SEG series is stable
        with dicom_stack.client() as c:
            job = orthanckit.wait_until(
                lambda: next((j for j in c.get("/v1/jobs").json()["items"]
                              if (j["source"] or {}).get("dicomweb", {}).get("series_uid") == seg_in.SeriesInstanceUID),
                             None), 60, "the job posted by Orthanc's auto-route", detail=pacs.log)
        assert job["delivery"]["url"] == proxy.url + "/dicom-web"
        assert job["source"]["dicomweb"]["url"] == pacs.dicomweb
    else:
        job = _submit(dicom_stack, _job_body(pacs.dicomweb, seg_in, proxy.url + "/dicom-web"))
    with dicom_stack.client() as c:
        done = servicekit.wait_job(c, job["id"], "succeeded", timeout=300, stack=dicom_stack)
    job = _wait_delivery(dicom_stack, job["id"])
    assert job["delivery"]["status"] == "delivered", (job["delivery"], dicom_stack.tail())
    assert job["delivery"]["attempts"] == 2 and proxy.posts - posts_before == 2  # 503, then stored
    assert job["attempts"] == 1  # delivered again without refitting
    ribs = sorted({f"{s}{n}" for s, n in (rib_side_number(x) for x in study["rib_names"])},
                  key=lambda r: (r[0], int(r[1:])))
    assert len(ribs) == 12
    rib_segments = {int(item.SegmentNumber) for item in seg_in.SegmentSequence if rib_side_number(item.SegmentLabel)}
    assert len(seg_in.SegmentSequence) > len(rib_segments) == 12  # other structures are in the SEG ...
    assert set(done["metrics"]["input"]["labels"]) == rib_segments  # ... and only the ribs were fitted
    results = _new_instances(pacs, seg_in.StudyInstanceUID, known)
    assert set(results) == {SEG_SOP_CLASS_UID, SR_SOP_CLASS_UID, ENCAPSULATED_STL_SOP_CLASS_UID}
    import highdicom as hd

    seg = hd.seg.Segmentation.from_dataset(results[SEG_SOP_CLASS_UID])
    found = [str(seg.get_segment_description(n).SegmentLabel) for n in seg.segment_numbers]
    assert set(found) <= set(ribs) and len(found) >= 10, found  # 3 mm voxels: a cut-off rib may vanish


def test_refused_and_failing_sources(dicom_stack, orthanc, phantom_in_pacs, tmp_path):
    seg_in = phantom_in_pacs["seg_dataset"]
    ct0 = phantom_in_pacs["ct_datasets"][0]
    with dicom_stack.client() as c:
        # a PACS that is not configured: refused at submission, nothing queued
        body = _job_body("http://127.0.0.1:9/dicom-web", seg_in, None)
        servicekit.assert_problem(c.post("/v1/jobs", json=body), 422)
        assert c.post("/v1/jobs", json=body).json()["code"] == "dicomweb_refused"
        body = _job_body(orthanc.dicomweb, seg_in, "http://10.0.0.1/dicom-web")
        assert servicekit.assert_problem(c.post("/v1/jobs", json=body), 422)["code"] == "dicomweb_refused"
        bad = _job_body(orthanc.dicomweb, seg_in, None)
        bad["source"]["dicomweb"]["series_uid"] = "1.2.x"
        assert servicekit.assert_problem(c.post("/v1/jobs", json=bad), 422)["code"] == "validation_error"
        bad = _job_body(orthanc.dicomweb, seg_in, None)
        bad["source"]["dicomweb"]["password"] = "secret"
        assert servicekit.assert_problem(c.post("/v1/jobs", json=bad), 422)["code"] == "validation_error"

    # DICOM uploads are read by the same reader: a CT slice, a SEG without references -> 4xx at once
    no_refs = copy.deepcopy(seg_in)
    del no_refs.ReferencedSeriesSequence
    no_refs.save_as(tmp_path / "no_refs.dcm")
    with dicom_stack.client() as c:
        for path, code in ((phantom_in_pacs["ct"][0], "not_segmentation"), (tmp_path / "no_refs.dcm", "seg_no_reference")):
            assert servicekit.assert_problem(servicekit.submit(c, path, SMOKE), 422)["code"] == code

    # a SEG whose CT series is not on the PACS
    orphan = copy.deepcopy(seg_in)
    orphan.SeriesInstanceUID = pydicom.uid.generate_uid()
    orphan.SOPInstanceUID = orphan.file_meta.MediaStorageSOPInstanceUID = pydicom.uid.generate_uid()
    orphan.ReferencedSeriesSequence[0].SeriesInstanceUID = pydicom.uid.generate_uid()
    orphan.save_as(tmp_path / "orphan.dcm")
    orthanc.upload([tmp_path / "orphan.dcm"])
    cases = {
        "source_not_found": {"series_uid": pydicom.uid.generate_uid()},
        "source_not_seg": {"series_uid": str(ct0.SeriesInstanceUID)},
        "referenced_series_missing": {"series_uid": str(orphan.SeriesInstanceUID)},
    }
    # Idempotency-Key: the same body is the same job; another body with the same key is refused
    body = _job_body(orthanc.dicomweb, seg_in, None)
    body["source"]["dicomweb"]["series_uid"] = cases["source_not_found"]["series_uid"]
    with dicom_stack.client() as c:
        first = c.post("/v1/jobs", json=body, headers={"Idempotency-Key": "seg-job-1"})
        again = c.post("/v1/jobs", json=body, headers={"Idempotency-Key": "seg-job-1"})
        assert (first.status_code, again.status_code) == (202, 200) and first.json()["id"] == again.json()["id"]
        body["params"] = {"preset": "smoke", "seed": 1}
        reused = c.post("/v1/jobs", json=body, headers={"Idempotency-Key": "seg-job-1"})
        assert servicekit.assert_problem(reused, 422)["code"] == "idempotency_key_reused"
    jobs = {}
    for code, change in cases.items():
        body = _job_body(orthanc.dicomweb, seg_in, orthanc.dicomweb)
        body["source"]["dicomweb"].update(change)
        jobs[code] = _submit(dicom_stack, body)["id"]
    with dicom_stack.client() as c:
        for code, job_id in jobs.items():
            job = servicekit.wait_job(c, job_id, "failed", timeout=60, stack=dicom_stack)
            assert job["error"]["code"] == code, job["error"]
            assert job["delivery"]["status"] == "pending" and job["delivery"]["attempts"] == 0
        r = c.get(f"/v1/jobs/{jobs['referenced_series_missing']}")
        assert orphan.ReferencedSeriesSequence[0].SeriesInstanceUID in r.json()["error"]["message"]
