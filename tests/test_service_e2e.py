"""End-to-end service tests on real processes: Redis, a Celery worker, uvicorn, HTTP on loopback.

Order matters a little (one worker, jobs run one at a time): the module runs top to bottom.
"""

from __future__ import annotations

import io
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest
from servicekit import (
    KEY_A,
    KEY_B,
    LONG,
    MAX_QUERY_POINTS,
    SMOKE,
    WEBHOOK_SECRET,
    assert_problem,
    host_ip,
    submit,
    wait_job,
)

pytestmark = pytest.mark.service

STATE: dict = {}


@pytest.fixture(scope="module")
def receiver():
    rx = _Receiver(fail_first=1)
    yield rx
    rx.close()


@pytest.fixture(scope="module")
def smoke_params():
    """Params of the end-to-end smoke job (test_service_postgres.py, which reruns these flows, overrides it)."""
    return SMOKE


def _smoke_job(service, sample_ply, params, **extra):
    c = service.client()
    r = submit(c, sample_ply, {**params, **extra})
    assert r.status_code == 202, r.text
    return c, r


def test_smoke_job_end_to_end(service, sample_ply, receiver, smoke_params):
    c, r = _smoke_job(service, sample_ply, smoke_params, webhook_url=receiver.url)
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert job["status"] in ("queued", "running")
    assert job["input"]["points"] > 1000 and job["input"]["format"] == "ply"
    done = wait_job(c, job["id"], "succeeded", timeout=400, stack=service)
    assert done["started_at"] and done["finished_at"] and done["error"] is None
    assert done["progress"]["fraction"] == pytest.approx(1.0)
    names = {a["name"] for a in done["artifacts"]}
    assert {"mesh.ply", "skeleton.glb"} <= names, names
    STATE["job"] = done

    # mesh.ply is a real triangle mesh
    import trimesh

    r = c.get(f"/v1/jobs/{job['id']}/artifacts/mesh.ply")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/x-ply")
    mesh = trimesh.load(io.BytesIO(r.content), file_type="ply", process=False)
    assert len(mesh.faces) > 100

    # skeleton.glb: a glTF binary with a LINES primitive (mode 1)
    import pygltflib

    r = c.get(f"/v1/jobs/{job['id']}/artifacts/skeleton.glb")
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
    gltf = pygltflib.GLTF2.load_from_bytes(r.content)
    modes = {p.mode for m in gltf.meshes for p in m.primitives}
    assert 1 in modes, modes

    for a in done["artifacts"]:  # every advertised link downloads with its media type
        r = c.get(a["href"])
        assert r.status_code == 200, a
        assert r.headers["content-type"].split(";")[0] == a["media_type"]
        assert len(r.content) == a["bytes"]
        if a["media_type"] == "application/json":
            json.loads(r.content)


def test_query_field(service):
    job = STATE.get("job") or pytest.skip("smoke job did not run")
    c = service.client()
    lo = np.array([-200.0, -200.0, -200.0])
    pts = np.vstack([np.zeros(3), lo * 10, np.random.default_rng(0).uniform(-150, 150, size=(20, 3))])
    r = c.post(f"/v1/jobs/{job['id']}/query", json={"points_mm": pts.tolist()})
    assert r.status_code == 200, r.text
    out = r.json()
    for k in ("occupancy", "U", "inside"):
        assert len(out[k]) == len(pts)
    assert all(o is None or 0.0 <= o <= 1.0 for o in out["occupancy"])
    assert out["inside"][1] is False  # far outside
    if out.get("sdf_mm") is not None:
        assert len(out["sdf_mm"]) == len(pts) and out["sdf_mm"][1] > 100
    # limits and validation
    r = c.post(f"/v1/jobs/{job['id']}/query", json={"points_mm": [[0, 0, 0]] * (MAX_QUERY_POINTS + 1)})
    assert_problem(r, 422)
    r = c.post(f"/v1/jobs/{job['id']}/query", content=b'{"points_mm": [[0, 0, NaN]]}',
               headers={"content-type": "application/json"})
    assert_problem(r, 422)


def test_idempotency_key(service, sample_ply):
    job = STATE.get("job") or pytest.skip("smoke job did not run")
    c = service.client()
    key = {"Idempotency-Key": "idem-" + job["id"]}
    r1 = submit(c, sample_ply, SMOKE, headers=key)
    assert r1.status_code == 202, r1.text
    r2 = submit(c, sample_ply, SMOKE, headers=key)
    assert r2.status_code in (200, 202) and r2.json()["id"] == r1.json()["id"]
    assert r2.headers["location"] == f"/v1/jobs/{r1.json()['id']}"
    r3 = submit(c, sample_ply, {**SMOKE, "seed": 7}, headers=key)
    assert_problem(r3, 422)
    # the same key is another key's business: key B gets its own job
    r4 = submit(service.client(KEY_B), sample_ply, SMOKE, headers=key)
    assert r4.status_code == 202 and r4.json()["id"] != r1.json()["id"]
    for jid in (r1.json()["id"], r4.json()["id"]):  # don't let them hold the worker
        client = c if jid == r1.json()["id"] else service.client(KEY_B)
        client.delete(f"/v1/jobs/{jid}")
    STATE["b_job"] = r4.json()["id"]


def test_keys_isolate_jobs(service):
    job = STATE.get("job") or pytest.skip("smoke job did not run")
    a, b = service.client(KEY_A), service.client(KEY_B)
    assert_problem(b.get(f"/v1/jobs/{job['id']}"), 404)
    assert_problem(b.get(f"/v1/jobs/{job['id']}/artifacts/mesh.ply"), 404)
    assert_problem(b.delete(f"/v1/jobs/{job['id']}"), 404)
    assert_problem(b.post(f"/v1/jobs/{job['id']}/query", json={"points_mm": [[0, 0, 0]]}), 404)
    ids_b = {j["id"] for j in b.get("/v1/jobs", params={"limit": 100}).json()["items"]}
    ids_a = {j["id"] for j in a.get("/v1/jobs", params={"limit": 100}).json()["items"]}
    assert job["id"] in ids_a and job["id"] not in ids_b
    if STATE.get("b_job"):
        assert STATE["b_job"] in ids_b and STATE["b_job"] not in ids_a
    r = service.client(None).get("/v1/jobs")
    assert_problem(r, 401)
    assert "bearer" in r.headers.get("www-authenticate", "").lower()
    assert_problem(service.client("not-a-key").get(f"/v1/jobs/{job['id']}"), 401)
    assert service.client(None).get("/healthz").status_code == 200


class _Receiver:
    """A tiny webhook receiver on this host's non-loopback address (allowlisted by servicekit); answers 503 to the first `fail_first` requests."""

    def __init__(self, fail_first: int = 1):
        self.requests: list[tuple[dict, bytes]] = []
        self.fail_first = fail_first
        outer = self

        class H(BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers.get("content-length", 0)))
                outer.requests.append(({k.lower(): v for k, v in self.headers.items()}, body))
                code = 503 if len(outer.requests) <= outer.fail_first else 204
                self.send_response(code)
                self.end_headers()

            def log_message(self, *a):
                pass

        ip = host_ip()
        if ip is None:
            pytest.skip("no non-loopback address for a webhook receiver (loopback targets are refused)")
        self.server = ThreadingHTTPServer((ip, 0), H)
        self.url = f"http://{ip}:{self.server.server_address[1]}/hooks/ribpull"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()


def test_webhook_signed_and_retried(service, receiver):
    from worker.webhooks import verify

    job = STATE.get("job") or pytest.skip("smoke job did not run")
    c = service.client()
    deadline = time.monotonic() + 60
    while len(receiver.requests) < 2 and time.monotonic() < deadline:
        time.sleep(0.2)
    rx = receiver.requests
    assert len(rx) >= 2, f"webhook not retried: {len(rx)}\n{service.tail()}"
    headers, body = rx[-1]
    assert headers["webhook-id"] == rx[0][0]["webhook-id"]  # the same id on every retry
    assert verify(WEBHOOK_SECRET, headers, body)
    assert not verify(WEBHOOK_SECRET, headers, body + b" ")
    assert not verify("whsec_" + "A" * 32, headers, body)
    assert headers["webhook-signature"].startswith("v1,")
    event = json.loads(body)
    assert event["type"] == "job.succeeded" and event["data"]["id"] == job["id"]
    assert event["data"]["status"] == "succeeded" and event["data"]["artifacts"]
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        wh = c.get(f"/v1/jobs/{job['id']}").json()["webhook"]
        if wh["status"] == "delivered":
            break
        time.sleep(0.2)
    assert wh["status"] == "delivered" and wh["attempts"] >= 2, wh


def _wait_fitting(c, jid, service):
    return wait_job(c, jid, "running", timeout=120, stack=service,
                    predicate=lambda j: j["progress"]["stage"] == "fit" and (j["progress"]["iteration"] or 0) > 0)


def test_cancel_running_job(service, sample_ply):
    c = service.client()
    r = submit(c, sample_ply, LONG)
    assert r.status_code == 202, r.text
    jid = r.json()["id"]
    _wait_fitting(c, jid, service)
    r = c.delete(f"/v1/jobs/{jid}")
    assert r.status_code == 202, r.text
    assert r.json()["cancel_requested"] is True
    t0 = time.monotonic()
    job = wait_job(c, jid, "canceled", timeout=60, stack=service)
    assert time.monotonic() - t0 < 30
    assert job["artifacts"] == [] and job["finished_at"]
    assert_problem(c.get(f"/v1/jobs/{jid}/artifacts/mesh.ply"), 404)
    assert_problem(c.post(f"/v1/jobs/{jid}/query", json={"points_mm": [[0, 0, 0]]}), 409)
    STATE["canceled"] = jid


def test_cancel_queued_job(service, sample_ply):
    c = service.client()
    blocker = submit(c, sample_ply, LONG).json()["id"]  # occupies the only worker process
    _wait_fitting(c, blocker, service)
    r = submit(c, sample_ply, SMOKE)
    jid = r.json()["id"]
    r = c.delete(f"/v1/jobs/{jid}")
    assert r.status_code == 200 and r.json()["status"] == "canceled", r.text
    c.delete(f"/v1/jobs/{blocker}")
    wait_job(c, blocker, "canceled", timeout=60, stack=service)
    time.sleep(1.0)  # the worker sees the queued-then-canceled message and skips it
    assert c.get(f"/v1/jobs/{jid}").json()["status"] == "canceled"


def test_worker_killed_mid_job_is_redelivered(service, sample_ply):
    c = service.client()
    r = submit(c, sample_ply, LONG)
    jid = r.json()["id"]
    _wait_fitting(c, jid, service)
    service.kill_worker()  # SIGKILL the worker and its pool process: no ack, no clean-up
    time.sleep(1.0)
    assert c.get(f"/v1/jobs/{jid}").json()["status"] == "running"
    service.start_worker()
    job = wait_job(c, jid, "succeeded", timeout=500, stack=service)
    assert job["attempts"] >= 2, job
    names = {a["name"] for a in job["artifacts"]}
    assert "mesh.ply" in names
    STATE["redelivered"] = jid


def test_api_restart_keeps_jobs_and_artifacts(service):
    c = service.client()
    before = c.get("/v1/jobs", params={"limit": 100}).json()["items"]
    assert len(before) >= 3
    service.restart_api()
    c = service.client()
    after = {j["id"]: j for j in c.get("/v1/jobs", params={"limit": 100}).json()["items"]}
    for j in before:
        assert j["id"] in after
        a = after[j["id"]]
        if j["status"] in ("succeeded", "failed", "canceled"):
            assert a["status"] == j["status"] and a["artifacts"] == j["artifacts"]
        for art in a["artifacts"]:
            r = c.get(art["href"])
            assert r.status_code == 200 and len(r.content) == art["bytes"]


def test_list_pagination_and_filter(service):
    c = service.client()
    all_items = c.get("/v1/jobs", params={"limit": 100}).json()["items"]
    assert len(all_items) >= 3
    created = [j["created_at"] for j in all_items]
    assert created == sorted(created, reverse=True)  # newest first
    seen, cursor = [], None
    while True:
        params = {"limit": 2, **({"cursor": cursor} if cursor else {})}
        page = c.get("/v1/jobs", params=params).json()
        assert len(page["items"]) <= 2
        seen += [j["id"] for j in page["items"]]
        cursor = page["next_cursor"]
        if not cursor:
            break
    assert seen == [j["id"] for j in all_items]
    canceled = c.get("/v1/jobs", params={"status": "canceled", "limit": 100}).json()["items"]
    assert canceled and all(j["status"] == "canceled" for j in canceled)
    assert_problem(c.get("/v1/jobs", params={"cursor": "garbage!"}), 422)


def test_delete_finished_job_removes_files(service):
    job = STATE.get("job") or pytest.skip("smoke job did not run")
    c = service.client()
    r = c.delete(f"/v1/jobs/{job['id']}")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["status"] == "succeeded" and body["artifacts_deleted"] is True and body["artifacts"] == []
    assert_problem(c.get(f"/v1/jobs/{job['id']}/artifacts/mesh.ply"), 410)
    assert_problem(c.post(f"/v1/jobs/{job['id']}/query", json={"points_mm": [[0, 0, 0]]}), 409)
    assert c.delete(f"/v1/jobs/{job['id']}").status_code == 200  # idempotent
    assert c.get(f"/v1/jobs/{job['id']}").json()["artifacts_deleted"] is True
