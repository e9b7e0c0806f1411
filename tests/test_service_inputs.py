"""Malformed files, parameters and requests: every one gets a 4xx application/problem+json at once
(nothing is queued), never a 5xx, and the service keeps answering."""

from __future__ import annotations

import gzip
import io
import json
import struct

import numpy as np
import pytest
from servicekit import MAX_UPLOAD_MB, SMOKE, assert_problem, submit

pytestmark = pytest.mark.service

RNG = np.random.default_rng(0)
GOOD = RNG.normal(size=(400, 3)) * 40.0


def _xyz(points) -> bytes:
    return "\n".join(" ".join(repr(float(v)) for v in p) for p in points).encode()


def _npy(arr) -> bytes:
    b = io.BytesIO()
    np.save(b, arr, allow_pickle=True)
    return b.getvalue()


def _ply_binary(points, declared: int) -> bytes:
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {declared}\n"
            "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    return head + np.asarray(points, dtype="<f4").tobytes()


_coplanar = GOOD.copy()
_coplanar[:, 2] = 0.0
_nan = GOOD.copy()
_nan[5, 1] = np.nan
_inf = GOOD.copy()
_inf[7, 0] = np.inf

# (id, filename, content, params-json-text or None, expected status or None for any 4xx)
BAD_FILES = [
    ("empty", "empty.ply", b"", None, None),
    ("garbage_ply", "garbage.ply", bytes(RNG.integers(0, 256, 4000, dtype=np.uint8)), None, None),
    ("lying_ply_header_ascii", "lie.ply",
     b"ply\nformat ascii 1.0\nelement vertex 100000\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n" + _xyz(GOOD[:150]), None, None),
    ("lying_ply_header_binary", "lie_bin.ply", _ply_binary(GOOD, 10_000), None, None),
    ("ply_header_only", "hdr.ply", b"ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\n", None, None),
    ("nan_coordinates", "nan.xyz", _xyz(_nan), None, None),
    ("inf_coordinates", "inf.npy", _npy(_inf), None, None),
    ("three_points", "three.xyz", _xyz(GOOD[:3]), None, None),
    ("coplanar", "flat.xyz", _xyz(_coplanar), None, None),
    ("all_identical", "same.csv", b"\n".join([b"1,2,3"] * 300), None, None),
    ("collinear", "line.xyz", _xyz(np.outer(np.arange(300), [1.0, 2.0, 3.0])), None, None),
    ("unknown_extension", "ribs.docx", b"this is not a point cloud at all " * 20, None, 415),
    ("no_extension_text", "ribs", b"hello world\n" * 50, None, None),
    ("csv_with_words", "words.csv", b"x,y,z\n" + b"a,b,c\n" * 200, None, None),
    ("npy_pickled_objects", "obj.npy", _npy(np.array([{"a": 1}] * 10, dtype=object)), None, None),
    ("npy_wrong_shape", "shape.npy", _npy(RNG.normal(size=(100, 2))), None, None),
    ("npz_garbage", "x.npz", b"PK\x03\x04" + b"\x00" * 200, None, None),
    ("nifti_garbage", "seg.nii.gz", gzip.compress(b"\x00" * 300), None, None),
    ("nifti_truncated", "seg.nii", struct.pack("<i", 348) + b"\x00" * 100, None, None),
    ("pcd_garbage", "c.pcd", b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nPOINTS 999\nDATA ascii\n1 2 3\n", None, None),
    ("bad_json_params", "ok.xyz", _xyz(GOOD), "{not json", 422),
    ("params_not_object", "ok.xyz", _xyz(GOOD), "[1, 2, 3]", 422),
    ("unknown_preset", "ok.xyz", _xyz(GOOD), json.dumps({"preset": "turbo"}), 422),
    ("unknown_method", "ok.xyz", _xyz(GOOD), json.dumps({"method": "magic"}), 422),
    ("iterations_zero", "ok.xyz", _xyz(GOOD), json.dumps({"iterations": 0}), 422),
    ("iterations_huge", "ok.xyz", _xyz(GOOD), json.dumps({"iterations": 10**9}), 422),
    ("iterations_string", "ok.xyz", _xyz(GOOD), json.dumps({"iterations": "100"}), 422),
    ("negative_resolution", "ok.xyz", _xyz(GOOD), json.dumps({"resolution": -5}), 422),
    ("resolution_float", "ok.xyz", _xyz(GOOD), json.dumps({"resolution": 64.5}), 422),
    ("labels_not_ints", "ok.xyz", _xyz(GOOD), json.dumps({"labels": ["rib", 2]}), 422),
    ("labels_fractional", "ok.xyz", _xyz(GOOD), json.dumps({"labels": [1.5]}), 422),
    ("labels_out_of_range", "ok.xyz", _xyz(GOOD), json.dumps({"labels": [0, 300]}), 422),
    ("labels_empty", "ok.xyz", _xyz(GOOD), json.dumps({"labels": []}), 422),
    ("skeleton_not_bool", "ok.xyz", _xyz(GOOD), json.dumps({"skeleton": "maybe"}), 422),
    ("unknown_param", "ok.xyz", _xyz(GOOD), json.dumps({"preset": "smoke", "turbo": True}), 422),
    ("webhook_not_http", "ok.xyz", _xyz(GOOD), json.dumps({"webhook_url": "ftp://example.org/x"}), 422),
    ("webhook_relative", "ok.xyz", _xyz(GOOD), json.dumps({"webhook_url": "/hooks"}), 422),
    ("seed_negative", "ok.xyz", _xyz(GOOD), json.dumps({"seed": -1}), 422),
    ("oversize", "big.xyz", b"1 2 3\n" * ((MAX_UPLOAD_MB * 1024 * 1024) // 6 + 10), None, 413),
]


@pytest.fixture(scope="module")
def jobs_before(service):
    return len(service.client().get("/v1/jobs", params={"limit": 100}).json()["items"])


@pytest.mark.parametrize("name,filename,content,params,status", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_bad_upload_is_refused(service, jobs_before, name, filename, content, params, status):
    c = service.client()
    r = submit(c, content=content, filename=filename, raw_params=params)
    body = assert_problem(r, status)
    assert body["detail"]


def _raw_post(service, body: bytes, content_type: str, extra_headers=None, stream=False):
    c = service.client()
    headers = {"content-type": content_type, **(extra_headers or {})}
    if stream:
        def gen():
            for i in range(0, len(body), 65536):
                yield body[i:i + 65536]
        return c.post("/v1/jobs", content=gen(), headers=headers)
    return c.post("/v1/jobs", content=body, headers=headers)


def test_oversize_streamed_without_length_stops_at_cap(service):
    boundary = "xYzBoUnDaRy"
    big = b"1 2 3\n" * ((MAX_UPLOAD_MB * 1024 * 1024) // 6 + 50_000)
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"big.xyz\"\r\n\r\n"
            .encode() + big + f"\r\n--{boundary}--\r\n".encode())
    r = _raw_post(service, body, f"multipart/form-data; boundary={boundary}", stream=True)
    assert_problem(r, 413)


@pytest.mark.parametrize("case", [
    "missing_file", "not_multipart_json", "no_boundary", "truncated_multipart", "duplicate_file",
    "idempotency_key_too_long",
])
def test_bad_request_shapes(service, case):
    boundary = "b0undary"
    ok_part = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"ok.xyz\"\r\n\r\n"
               .encode() + _xyz(GOOD) + b"\r\n")
    if case == "missing_file":
        body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"params\"\r\n\r\n"
                f"{json.dumps(SMOKE)}\r\n--{boundary}--\r\n").encode()
        assert_problem(_raw_post(service, body, f"multipart/form-data; boundary={boundary}"), 422)
    elif case == "not_multipart_json":
        # JSON is the body of a job that names a DICOMweb source: without `source` it is a 422 naming it
        r = _raw_post(service, json.dumps({"file": "x"}).encode(), "application/json")
        assert "source" in assert_problem(r, 422)["detail"]
        assert_problem(_raw_post(service, b"file=x", "application/x-www-form-urlencoded"), 415)
    elif case == "no_boundary":
        assert_problem(_raw_post(service, ok_part, "multipart/form-data"), 400)
    elif case == "truncated_multipart":
        assert_problem(_raw_post(service, ok_part[: len(ok_part) // 2], f"multipart/form-data; boundary={boundary}"))
    elif case == "duplicate_file":
        body = ok_part + ok_part + f"--{boundary}--\r\n".encode()
        assert_problem(_raw_post(service, body, f"multipart/form-data; boundary={boundary}"), 422)
    elif case == "idempotency_key_too_long":
        body = ok_part + f"--{boundary}--\r\n".encode()
        r = _raw_post(service, body, f"multipart/form-data; boundary={boundary}",
                      extra_headers={"Idempotency-Key": "k" * 300})
        assert_problem(r, 422)


@pytest.mark.parametrize("method,path,status", [
    ("GET", "/v1/jobs/not-a-job-id", 404),
    ("GET", "/v1/jobs/" + "0" * 32, 404),
    ("GET", "/v1/jobs/..%2F..%2Fetc%2Fpasswd", 404),
    ("GET", "/v1/jobs/" + "0" * 32 + "/artifacts/mesh.ply", 404),
    ("GET", "/v1/jobs/" + "0" * 32 + "/artifacts/..%2Fribpull.db", 404),
    ("GET", "/v1/jobs/" + "0" * 32 + "/artifacts/secrets.txt", 404),
    ("DELETE", "/v1/jobs/nope", 404),
    ("POST", "/v1/jobs/" + "0" * 32 + "/query", 422),
    ("GET", "/v1/jobs?limit=0", 422),
    ("GET", "/v1/jobs?limit=abc", 422),
    ("GET", "/v1/jobs?status=sleeping", 422),
    ("GET", "/v1/nothing-here", 404),
    ("PUT", "/v1/jobs", 405),
    ("PATCH", "/healthz", 405),
])
def test_bad_routes_and_params(service, method, path, status):
    r = service.client().request(method, path)
    assert_problem(r, status)


def test_query_body_errors(service):
    c = service.client()
    jid = "0" * 32
    for body in (b"", b"{", b'{"points_mm": "x"}', b'{"points_mm": [[1, 2]]}', b'{"points_mm": []}',
                 b'{"points_mm": [[1, 2, "a"]]}', b'{"points_mm": [[1, 2, Infinity]]}', b'[]'):
        r = c.post(f"/v1/jobs/{jid}/query", content=body, headers={"content-type": "application/json"})
        assert_problem(r, 422)


def test_unknown_artifact_name_on_real_job_and_nothing_queued(service, jobs_before):
    c = service.client()
    after = c.get("/v1/jobs", params={"limit": 100}).json()["items"]
    assert len(after) == jobs_before, "a refused upload created a job"
    r = submit(c, content=_xyz(GOOD), filename="ok.xyz", params={**SMOKE, "iterations": 1})
    assert r.status_code == 202, r.text
    jid = r.json()["id"]
    assert_problem(c.get(f"/v1/jobs/{jid}/artifacts/notes.txt"), 404)
    assert_problem(c.get(f"/v1/jobs/{jid}/artifacts/..%2F..%2Fribpull.db"), 404)
    c.delete(f"/v1/jobs/{jid}")
    assert c.get("/healthz").status_code == 200
    assert service.client(None).get("/readyz").status_code == 200
