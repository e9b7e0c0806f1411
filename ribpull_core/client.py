"""HTTP client of the RibPull service (httpx only): submit a file, follow the job, download artifacts.

    from ribpull_core.client import RibPullClient
    with RibPullClient("http://127.0.0.1:8000", key="...") as c:
        job = c.submit("points.ply", {"preset": "smoke"})
        job = c.wait(job["id"], on_progress=print)
        c.download(job, "out/")

Every non-2xx answer raises `ServiceError` with the problem+json `status`, `code` and `detail`; a job
that ends failed/canceled is returned as is (the caller decides). The `ribpull submit/status/download`
commands (ribpull_core/cli.py) are thin wrappers. This module imports nothing from the service.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Self

import httpx

TERMINAL = ("succeeded", "failed", "canceled")


class ServiceError(Exception):
    """A non-2xx answer (or no answer) from the service."""

    def __init__(self, status: int, code: str, detail: str):
        super().__init__(f"HTTP {status} [{code}]: {detail}" if status else f"[{code}] {detail}")
        self.status, self.code, self.detail = status, code, detail


def _raise_for(r: httpx.Response) -> None:
    if r.is_success:
        return
    code, detail = "http_error", (r.text or r.reason_phrase)[:500]
    try:
        body = r.json()
        if isinstance(body, dict):
            code = str(body.get("code") or code)
            detail = str(body.get("detail") or detail)
    except ValueError:
        pass
    raise ServiceError(r.status_code, code, detail)


class RibPullClient:
    def __init__(self, url: str, key: str | None = None, *, timeout: float = 60.0,
                 transport: httpx.BaseTransport | None = None):
        headers = {"User-Agent": "ribpull-client/1"}
        if key:
            headers["Authorization"] = f"Bearer {key}"
        self.url = url.rstrip("/")
        self._http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout, transport=transport)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _call(self, method: str, path: str, **kw) -> httpx.Response:
        try:
            r = self._http.request(method, path, **kw)
        except httpx.HTTPError as exc:
            raise ServiceError(0, "unreachable", f"{self.url}: {type(exc).__name__}: {exc}") from None
        _raise_for(r)
        return r

    # --- jobs ------------------------------------------------------------------------------------
    def submit(self, path: str | os.PathLike, params: dict[str, Any] | None = None, *,
               idempotency_key: str | None = None) -> dict:
        """Upload `path` with `params`; the job resource (status queued)."""
        path = Path(path)
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        data = {"params": json.dumps(params)} if params else {}
        with open(path, "rb") as fh:
            r = self._call("POST", "/v1/jobs", files={"file": (path.name, fh, "application/octet-stream")},
                           data=data, headers=headers)
        return r.json()

    def job(self, job_id: str) -> dict:
        return self._call("GET", f"/v1/jobs/{job_id}").json()

    def cancel(self, job_id: str) -> dict:
        return self._call("DELETE", f"/v1/jobs/{job_id}").json()

    def wait(self, job_id: str, *, poll_s: float = 1.0, timeout_s: float | None = None,
             on_progress: Callable[[dict], None] | None = None) -> dict:
        """Poll until the job is succeeded, failed or canceled; `on_progress(job)` on each change."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        last = None
        while True:
            job = self.job(job_id)
            seen = (job["status"], json.dumps(job.get("progress"), sort_keys=True))
            if on_progress is not None and seen != last:
                on_progress(job)
            last = seen
            if job["status"] in TERMINAL:
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise ServiceError(0, "timeout", f"job {job_id} is still {job['status']} after {timeout_s:g} s")
            time.sleep(poll_s)

    def download(self, job: dict | str, outdir: str | os.PathLike, names: list[str] | None = None) -> list[Path]:
        """Save the job's artifacts (all, or `names`) into `outdir`; a file appears only when complete."""
        if isinstance(job, str):
            job = self.job(job)
        if job["status"] != "succeeded":
            raise ServiceError(0, "not_succeeded", f"job {job['id']} is {job['status']}; nothing to download")
        outdir = Path(outdir)
        outdir.mkdir(parents=True, exist_ok=True)
        available = {a["name"]: a for a in job.get("artifacts", [])}
        wanted = names or list(available)
        missing = [n for n in wanted if n not in available]
        if missing:
            raise ServiceError(0, "artifact_not_found", f"job {job['id']} has no {', '.join(missing)}")
        saved = []
        for name in wanted:
            dest = outdir / Path(name).name
            tmp = dest.with_name(dest.name + ".part")
            try:
                with self._http.stream("GET", available[name]["href"]) as r:
                    if not r.is_success:
                        r.read()
                        _raise_for(r)
                    with open(tmp, "wb") as fh:
                        fh.writelines(r.iter_bytes(1 << 20))
            except httpx.HTTPError as exc:
                tmp.unlink(missing_ok=True)
                raise ServiceError(0, "unreachable", f"{self.url}: {type(exc).__name__}: {exc}") from None
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
            os.replace(tmp, dest)
            saved.append(dest)
        return saved


def describe(job: dict) -> str:
    """One progress line: `running fit 120/250 loss 0.0123 (48%)`."""
    p = job.get("progress") or {}
    parts = [job["status"]]
    if p.get("stage"):
        parts.append(str(p["stage"]))
    if p.get("iteration") is not None and p.get("iterations"):
        parts.append(f"{p['iteration']}/{p['iterations']}")
    if p.get("loss") is not None:
        parts.append(f"loss {p['loss']:.4g}")
    parts.append(f"({100 * float(p.get('fraction') or 0):.0f}%)")
    return " ".join(parts)
