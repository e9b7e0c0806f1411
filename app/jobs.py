"""Job resource helpers shared by the API and the worker: serialisation and the Celery client."""

from __future__ import annotations

import base64
import logging
import re

from celery import Celery

from .db import Job
from .schemas import json_safe
from .settings import Settings
from .storage import artifact_store, media_type

log = logging.getLogger("ribpull.api")

#: Celery task names and queue (the worker registers these names; the API sends by name)
TASK_RUN_JOB = "ribpull.run_job"
TASK_WEBHOOK = "ribpull.deliver_webhook"
TASK_DICOMWEB_DELIVER = "ribpull.deliver_dicomweb"
QUEUE = "ribpull"
WORKER_KEY_PREFIX = "ribpull:worker:"


def celery_client(settings: Settings) -> Celery:
    """A producer-only Celery app with the same broker settings as the worker."""
    c = Celery("ribpull-api", broker=settings.redis_url)
    c.conf.update(
        broker_transport_options={"visibility_timeout": settings.visibility_timeout},
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=3,
        task_default_queue=QUEUE,
        task_ignore_result=True,
    )
    return c


def enqueue(client: Celery, task: str, *args, countdown: float | None = None) -> None:
    client.send_task(
        task, args=list(args), queue=QUEUE, countdown=countdown, retry=True,
        retry_policy={"max_retries": 2, "interval_start": 0.2, "interval_step": 0.5, "interval_max": 1.0},
    )


def job_links(job: Job, base: str = "") -> dict[str, str]:
    self_ = f"{base}/v1/jobs/{job.id}"
    links = {"self": self_}
    if job.status == "succeeded" and not job.artifacts_deleted:
        links["query"] = self_ + "/query"
        for name in job.artifacts or []:
            links[name] = f"{self_}/artifacts/{name}"
    return links


def job_to_dict(job: Job, settings: Settings, base: str = "") -> dict:
    """The public job resource (schemas.JobOut)."""
    artifacts = []
    if job.status == "succeeded" and not job.artifacts_deleted:
        adir = artifact_store(settings).local_dir(job.id, job.artifacts_ref)
        for name in job.artifacts or []:
            try:
                size = (adir / name).stat().st_size
            except OSError:
                continue
            artifacts.append({
                "name": name,
                "href": f"{base}/v1/jobs/{job.id}/artifacts/{name}",
                "media_type": media_type(name),
                "bytes": size,
            })
    d = {
        "id": job.id,
        "status": job.status,
        "created_at": job.created_at,
        "updated_at": job.updated_at,
        "started_at": job.started_at,
        "finished_at": job.finished_at,
        "params": job.params or {},
        "input": {
            "filename": job.input_name,
            "format": job.input_format,
            "bytes": job.input_bytes,
            "sha256": job.input_sha256,
            "points": job.input_points,
        },
        "progress": {
            "stage": job.stage,
            "fraction": job.fraction or 0.0,
            "iteration": job.iteration,
            "iterations": job.iterations,
            "loss": job.loss,
            "message": job.message or "",
        },
        "error": {"code": job.error_code, "message": job.error_message or ""} if job.error_code else None,
        "attempts": job.attempts or 0,
        "cancel_requested": bool(job.cancel_requested),
        "artifacts": artifacts,
        "artifacts_deleted": bool(job.artifacts_deleted),
        "metrics": job.metrics,
        "webhook": (
            {"url": job.webhook_url, "status": job.webhook_status, "attempts": job.webhook_attempts or 0,
             "error": job.webhook_error}
            if job.webhook_url else None
        ),
        "source": job.source,
        "delivery": (
            {"url": job.deliver_url, "status": job.delivery_status, "attempts": job.delivery_attempts or 0,
             "error": job.delivery_error}
            if job.deliver_url else None
        ),
        "links": job_links(job, base),
    }
    return _safe(d)


def _safe(d: dict) -> dict:
    # progress.loss and metrics may hold NaN/inf; datetimes stay datetimes for pydantic
    p = d["progress"]
    p["loss"] = json_safe(p["loss"])
    p["fraction"] = json_safe(p["fraction"]) or 0.0
    if d["metrics"] is not None:
        d["metrics"] = json_safe(d["metrics"])
    return d


_CURSOR_RE = re.compile(r"^[0-9]{1,18}$")


def encode_cursor(seq: int) -> str:
    return base64.urlsafe_b64encode(f"s{seq}".encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> int | None:
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode("ascii")
    except Exception:  # noqa: BLE001
        return None
    if not raw.startswith("s") or not _CURSOR_RE.match(raw[1:]):
        return None
    return int(raw[1:])
