"""Issue 10: what a new user or an attacker sent to a fresh service, against the real running stack
(Redis, a Celery worker and uvicorn on loopback; see servicekit.py). Each test reproduces one of the
reported failures and checks the fix: resource bounds (inflate bombs, NIfTI header dims, query body
budget, resolution / iterations caps), slow clients (408), webhook targets, units, problem+json on
every error, nosniff, no server paths, and one log line for a client that disconnects mid-upload.

The API's peak memory (VmHWM) is recorded around the memory-hostile cases and must stay small.
"""

from __future__ import annotations

import gzip
import json
import struct
import time
import zlib

import numpy as np
import pytest
from servicekit import (
    BODY_TIMEOUT_S,
    KEY_A,
    MAX_INFLATED_MB,
    MAX_QUERY_POINTS,
    SMOKE,
    assert_problem,
    host_ip,
    parse_raw_response,
    proc_status,
    raw_http,
    submit,
    wait_job,
)

pytestmark = pytest.mark.service

RNG = np.random.default_rng(10)
GOOD = RNG.normal(size=(400, 3)) * 40.0  # ~250 mm across: a plausible ribcage extent
FAST = {**SMOKE, "iterations": 20, "skeleton": False, "preview": False}
RSS: dict[str, dict] = {}


def _xyz(points) -> bytes:
    return "\n".join(" ".join(repr(float(v)) for v in p) for p in points).encode()


def _nifti(vol=None, affine=None, dims=None, bitpix=None) -> bytes:
    """A NIfTI-1 (.nii) byte string; `affine` is written raw into the sform (NaN / zero kept);
    `dims`/`bitpix` overwrite the header only (the data stays small: a lying header)."""
    import nibabel as nib

    if vol is None:
        vol = np.zeros((24, 24, 24), np.uint8)
        vol[4:20, 4:20, 4:20] = 1
    b = bytearray(nib.Nifti1Image(vol, np.diag([10.0, 10.0, 10.0, 1.0])).to_bytes())
    if affine is not None:
        struct.pack_into("<hh", b, 252, 0, 1)  # qform_code 0, sform_code 1
        struct.pack_into("<12f", b, 280, *np.asarray(affine, float)[:3].reshape(-1))
    if dims is not None:
        struct.pack_into("<8h", b, 40, len(dims), *dims, *([1] * (7 - len(dims))))
    if bitpix is not None:
        struct.pack_into("<hh", b, 70, {8: 2, 16: 4, 32: 16}[bitpix], bitpix)
    return bytes(b)


def _gzip_bomb(head: bytes, inflated_mb: int) -> bytes:
    """gzip of `head` + `inflated_mb` MiB of zeros, built 1 MiB at a time (~1 KB per inflated MiB)."""
    c = zlib.compressobj(9, zlib.DEFLATED, 31)
    out = [c.compress(head)]
    zeros = bytes(1 << 20)
    for _ in range(inflated_mb):
        out.append(c.compress(zeros))
    out.append(c.flush())
    return b"".join(out)


def _api_hwm(service) -> int:
    return proc_status(service.api.pid).get("VmHWM", 0)


def _jobs(service) -> int:
    return len(service.client().get("/v1/jobs", params={"limit": 100}).json()["items"])


def _no_paths(service, text: str) -> None:
    for leak in (str(service.root), "/uploads/", "/storage/", "/tmp/", "/work/", "site-packages"):
        assert leak not in text, f"server path {leak!r} in {text[:300]}"


# ------------------------------------------------------------------------------------------------
# 1. memory bounds
# ------------------------------------------------------------------------------------------------

def test_gzip_bomb_refused_while_streaming(service):
    before, jobs = _api_hwm(service), _jobs(service)
    bomb = _gzip_bomb(_nifti(), 4 * MAX_INFLATED_MB)  # ~260 KB that inflates to 256 MiB
    assert len(bomb) < 1024 * 1024
    t = time.monotonic()
    r = submit(service.client(), content=bomb, filename="seg.nii.gz")
    body = assert_problem(r, 413)
    assert f"{MAX_INFLATED_MB:g} MiB" in body["detail"] and "RIBPULL_MAX_INFLATED_MB" in body["detail"]
    assert time.monotonic() - t < 15
    after = _api_hwm(service)
    RSS["gzip_bomb"] = {"api_hwm_before_mib": before, "api_hwm_after_mib": after}
    assert after - before < 200, RSS
    assert _jobs(service) == jobs
    assert not any((service.root / "storage" / "uploads").iterdir())


def test_nifti_header_dims_checked_before_voxels(service):
    before = _api_hwm(service)
    # a 350-byte header that claims 2048^3 int16 voxels (16 GiB) over a tiny gzip stream
    lie = gzip.compress(_nifti(dims=(2048, 2048, 2048), bitpix=16))
    r = submit(service.client(), content=lie, filename="big.nii.gz")
    body = assert_problem(r, 413)
    assert "2048" in body["detail"] and "limit" in body["detail"], body
    RSS["nifti_dims"] = {"api_hwm_before_mib": before, "api_hwm_after_mib": _api_hwm(service)}
    assert _api_hwm(service) - before < 100


@pytest.mark.parametrize("name,affine", [
    ("nan", [[np.nan, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
    ("zero", np.zeros((4, 4))),
])
def test_bad_nifti_affine_is_named(service, name, affine):
    r = submit(service.client(), content=_nifti(affine=affine), filename=f"{name}.nii")
    body = assert_problem(r, 422)
    assert body["code"] == "bad_affine" and "affine" in body["detail"], body


def test_query_body_budget(service):
    before = _api_hwm(service)
    path = "/v1/jobs/" + "0" * 32 + "/query"
    # a declared 60 MB body: refused from the header, before any of it is read or parsed
    head = (f"POST {path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {KEY_A}\r\n"
            "Content-Type: application/json\r\nContent-Length: 60000000\r\n\r\n").encode()
    status, headers, raw = parse_raw_response(raw_http(service.api_port, head + b'{"points_mm": [[1,2,3],', wait=10))
    assert status == 413 and headers["content-type"].startswith("application/problem+json"), (status, raw[:300])
    assert "limit" in json.loads(raw)["detail"]
    # the same without Content-Length (chunked): stops at the budget
    def chunks():
        yield b'{"points_mm": ['
        row = b"[1.0, 2.0, 3.0]," * 65536
        for _ in range(60):
            yield row
        yield b"[1,2,3]]}"
    r = service.client().post(path, content=chunks(), headers={"content-type": "application/json"})
    body = assert_problem(r, 413)
    assert "bytes" in body["detail"]
    # within the byte budget but over the point count: 422 that names the limit
    pts = [[1, 2, 3]] * (MAX_QUERY_POINTS + 1)
    r = service.client().post(path, content=json.dumps({"points_mm": pts}, separators=(",", ":")),
                              headers={"content-type": "application/json"})
    body = assert_problem(r, 422)
    assert str(MAX_QUERY_POINTS) in body["detail"], body
    RSS["query_body"] = {"api_hwm_before_mib": before, "api_hwm_after_mib": _api_hwm(service)}
    assert _api_hwm(service) - before < 150, RSS


@pytest.mark.parametrize("params,limit", [
    ({"resolution": 1024}, "512"),
    ({"resolution": 528}, "512"),
    ({"iterations": 100000}, "40000"),
])
def test_resolution_and_iterations_capped(service, params, limit):
    jobs = _jobs(service)
    r = submit(service.client(), content=_xyz(GOOD), filename="ok.xyz", params={**SMOKE, **params})
    body = assert_problem(r, 422)
    assert body["code"] == "limit_exceeded" and limit in body["detail"], body
    assert _jobs(service) == jobs


# ------------------------------------------------------------------------------------------------
# 2. slow clients
# ------------------------------------------------------------------------------------------------

def _multipart_head(length: int, boundary: str = "sl0w") -> bytes:
    return (f"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {KEY_A}\r\n"
            f"Content-Type: multipart/form-data; boundary={boundary}\r\nContent-Length: {length}\r\n\r\n"
            f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"slow.xyz\"\r\n\r\n"
            ).encode() + _xyz(GOOD[:50])


def test_body_slower_than_its_content_length_gets_408(service):
    t = time.monotonic()
    raw = raw_http(service.api_port, _multipart_head(200_000), wait=BODY_TIMEOUT_S + 20)
    took = time.monotonic() - t
    status, headers, _body = parse_raw_response(raw)
    assert status == 408, raw[:300]
    assert headers["content-type"].startswith("application/problem+json")
    assert BODY_TIMEOUT_S - 0.5 <= took < BODY_TIMEOUT_S + 10
    time.sleep(0.3)
    assert not any((service.root / "storage" / "uploads").iterdir()), "the partial upload was kept"


def test_headers_slower_than_the_timeout_get_408(service):
    t = time.monotonic()
    raw = raw_http(service.api_port, b"GET /healthz HTTP/1.1\r\nHost: x\r\n", wait=BODY_TIMEOUT_S + 20)
    status, headers, _ = parse_raw_response(raw)
    assert status == 408 and headers["content-type"].startswith("application/problem+json"), raw[:300]
    assert time.monotonic() - t < BODY_TIMEOUT_S + 10


def test_client_disconnect_mid_upload_logs_one_line(service):
    log = service.logs / f"api-{service.api_n}.log"
    start = log.stat().st_size
    raw_http(service.api_port, _multipart_head(500_000), close_after_send=True)
    time.sleep(1.5)
    new = log.read_bytes()[start:].decode(errors="replace")
    assert new.count("client disconnected") == 1, new
    assert "Traceback" not in new, new
    assert service.client().get("/healthz").status_code == 200
    assert not any((service.root / "storage" / "uploads").iterdir())


# ------------------------------------------------------------------------------------------------
# 3. webhook targets
# ------------------------------------------------------------------------------------------------

def _webhook_cases(service):
    cases = [
        f"http://127.0.0.1:{service.redis_port}/",  # the embedded Redis
        "http://localhost:9/hook",
        "http://[::1]/hook",
        "http://169.254.169.254/latest/meta-data",  # cloud metadata (link-local)
        "http://10.1.2.3/hook",  # private, not allowlisted
        "http://0.0.0.0:8080/",
    ]
    ip = host_ip()
    if ip:  # allowlisted by servicekit, but the service's own API port stays refused
        cases.append(f"http://{ip}:{service.api_port}/v1/jobs")
    return cases


def test_webhook_targets_refused_at_submission(service):
    jobs = _jobs(service)
    for url in _webhook_cases(service):
        r = submit(service.client(), content=_xyz(GOOD), filename="ok.xyz", params={**SMOKE, "webhook_url": url})
        body = assert_problem(r, 422)
        assert body["code"] == "webhook_refused", (url, body)
    assert _jobs(service) == jobs


# ------------------------------------------------------------------------------------------------
# 4. units
# ------------------------------------------------------------------------------------------------

def test_cloud_in_metres_is_refused_with_a_units_hint(service):
    r = submit(service.client(), content=_xyz(GOOD / 1000.0), filename="metres.xyz", params=SMOKE)
    body = assert_problem(r, 422)
    assert body["code"] == "implausible_extent" and '"units": "m"' in body["detail"], body
    r = submit(service.client(), content=_xyz(GOOD * 1e28), filename="huge.xyz", params=SMOKE)
    body = assert_problem(r, 422)
    assert body["code"] == "implausible_extent" and "no unit" in body["detail"], body


def test_units_m_converts_to_mm_and_outputs_are_in_mm(service, sample_ply):
    from ribpull_core.io import load_point_cloud

    pts = load_point_cloud(sample_ply).points
    metres = _xyz(pts[::4] / 1000.0)
    c = service.client()
    r = submit(c, content=metres, filename="ribs_m.xyz", params={**FAST, "units": "m"})
    assert r.status_code == 202, r.text
    job = wait_job(c, r.json()["id"], "succeeded", timeout=300, stack=service)
    assert job["params"]["units"] == "m"
    import trimesh

    mesh = trimesh.load(trimesh.util.wrap_as_stream(c.get(job["links"]["mesh.ply"]).content), file_type="ply")
    ext_in = np.ptp(pts, axis=0)
    ext_out = np.ptp(mesh.vertices, axis=0)
    assert np.all(ext_out > 0.5 * ext_in) and np.all(ext_out < 1.5 * ext_in), (ext_in, ext_out)
    pytest.units_job = job


# ------------------------------------------------------------------------------------------------
# 5. problem+json everywhere, nosniff, no server paths
# ------------------------------------------------------------------------------------------------

def test_range_errors_are_problem_json(service):
    job = getattr(pytest, "units_job", None) or pytest.skip("the units job did not run")
    c = service.client()
    href = job["links"]["mesh.ply"]
    ok = c.get(href)
    assert ok.status_code == 200 and ok.headers["x-content-type-options"] == "nosniff"
    part = c.get(href, headers={"Range": "bytes=0-9"})
    assert part.status_code == 206 and len(part.content) == 10
    for rng, status in (("bytes=999999999-", 416), ("bytes=abc", 400), ("bytes=9-2", 400)):
        r = c.get(href, headers={"Range": rng})
        if r.status_code in (200, 206):  # a server may ignore a Range it cannot parse (RFC 9110)
            continue
        body = assert_problem(r, status)
        assert r.headers["x-content-type-options"] == "nosniff"
        assert body["detail"]


def test_protocol_errors_are_problem_json(service):
    for raw in (b"GARBAGE\r\n\r\n", b"GET / HTTP/1.1\r\nHost: x\r\nBad Header\r\n\r\n"):
        status, headers, body = parse_raw_response(raw_http(service.api_port, raw, wait=10))
        assert status == 400, body[:200]
        assert headers["content-type"].startswith("application/problem+json")
        assert headers.get("x-content-type-options") == "nosniff"
        assert json.loads(body)["status"] == 400


def test_every_error_has_nosniff_and_no_server_path(service):
    c = service.client()
    full = gzip.compress(_nifti(vol=RNG.integers(0, 2, (24, 24, 24)).astype(np.uint8)))
    trunc = full[: len(full) // 2]
    npz_bad = b"PK\x03\x04" + bytes(300)
    for r in (
        submit(c, content=trunc, filename="trunc.nii.gz"),
        submit(c, content=npz_bad, filename="x.npz"),
        submit(c, content=_nifti(dims=(24, 24, 24), bitpix=32)[:500], filename="short.nii"),
        c.get("/v1/jobs/" + "0" * 32),
        c.get("/v1/nothing"),
        service.client(None).get("/v1/jobs"),
    ):
        assert_problem(r)
        assert r.headers.get("x-content-type-options") == "nosniff", r.headers
        _no_paths(service, r.text)
    h = c.get("/healthz")
    assert h.headers.get("x-content-type-options") == "nosniff"


def test_memory_figures(service):
    """Not a check: prints the API / worker peak RSS after the hostile cases (pytest -s shows it)."""
    from servicekit import pool_children

    RSS["api_final"] = proc_status(service.api.pid)
    RSS["worker_children"] = {pid: proc_status(pid) for pid in pool_children(service.worker)}
    print("\nRSS (MiB):", json.dumps(RSS, indent=1, default=str))
