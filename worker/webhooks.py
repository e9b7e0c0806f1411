"""Completion webhooks signed per the Standard Webhooks convention (https://www.standardwebhooks.com).

Headers: `webhook-id` (the same on every retry of one event), `webhook-timestamp` (unix seconds of
the attempt) and `webhook-signature` = `v1,<base64 HMAC-SHA256(key, "<id>.<timestamp>.<body>")>`.
The key is the base64-decoded part of a `whsec_...` secret, or the secret's UTF-8 bytes otherwise.
Body: {"type": "job.succeeded|job.failed|job.canceled", "timestamp": ISO-8601, "data": <job resource>}.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import logging
import time

import httpx

from app.db import Job, utcnow
from app.jobs import job_to_dict
from app.netpolicy import webhook_target_problem
from app.schemas import JobOut
from app.settings import Settings

log = logging.getLogger("ribpull.webhooks")


def signing_key(secret: str) -> bytes:
    if secret.startswith("whsec_"):
        try:
            return base64.b64decode(secret[len("whsec_"):], validate=True)
        except ValueError:
            pass
    return secret.encode()


def sign(secret: str, msg_id: str, timestamp: int, body: bytes) -> str:
    mac = hmac.new(signing_key(secret), f"{msg_id}.{timestamp}.".encode() + body, hashlib.sha256).digest()
    return "v1," + base64.b64encode(mac).decode()


def verify(secret: str, headers: dict[str, str], body: bytes, tolerance_s: int = 300) -> bool:
    """Receiver-side check (used by the tests; handy for integrators)."""
    h = {k.lower(): v for k, v in headers.items()}
    msg_id, ts, sigs = h.get("webhook-id", ""), h.get("webhook-timestamp", ""), h.get("webhook-signature", "")
    if not (msg_id and ts.isdigit() and sigs):
        return False
    if abs(time.time() - int(ts)) > tolerance_s:
        return False
    expected = sign(secret, msg_id, int(ts), body)
    return any(hmac.compare_digest(expected, s) for s in sigs.split())


def event_payload(job: Job, settings: Settings) -> dict:
    data = JobOut.model_validate(job_to_dict(job, settings, settings.public_url.rstrip("/"))).model_dump(mode="json")
    return {"type": f"job.{job.status}", "timestamp": utcnow().isoformat(), "data": data}


def deliver_once(job: Job, settings: Settings) -> tuple[bool, str | None]:
    """One POST attempt. Returns (delivered, error message)."""
    url = job.webhook_url or ""
    why = webhook_target_problem(url, settings)
    if why:  # checked at submission too; again here in case the name now resolves elsewhere
        return False, f"refused target: {why}"
    body = json.dumps(event_payload(job, settings), separators=(",", ":")).encode()
    msg_id = f"msg_{job.id}_{job.status}"
    ts = int(time.time())
    headers = {
        "content-type": "application/json",
        "user-agent": "ribpull-webhooks/1",
        "webhook-id": msg_id,
        "webhook-timestamp": str(ts),
    }
    if settings.webhook_secret:
        headers["webhook-signature"] = sign(settings.webhook_secret, msg_id, ts, body)
    try:
        with httpx.Client(timeout=settings.webhook_timeout_s, follow_redirects=False) as client:
            r = client.post(url, content=body, headers=headers)
    except Exception as exc:  # noqa: BLE001 - a webhook must never crash a task
        return False, f"{type(exc).__name__}: {exc}"[:500]
    if 200 <= r.status_code < 300:
        return True, None
    return False, f"HTTP {r.status_code}"


def backoff_s(settings: Settings, attempt: int) -> float:
    """Delay before attempt `attempt + 1` (attempt >= 1): backoff, 2x backoff, 4x ... capped at 1 h."""
    return min(3600.0, settings.webhook_backoff_s * (2 ** max(0, attempt - 1)))
