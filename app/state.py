"""THE job state machine: every transition of a job's status, called by the API and the worker alike.

    submit:  (new) -> queued                     insert_queued          (API)
             queued -> failed (queue down)       fail_unqueued          (API)
    cancel:  queued -> canceled                  cancel                 (API, DELETE)
             running: cancel_requested = True    cancel                 (API, DELETE; the worker stops)
    delete:  succeeded|failed|canceled: files    cancel                 (API, DELETE on a finished job)
    run:     queued|stale running -> running     claim_job              (worker; redelivery takes over)
             running -> succeeded|failed|canceled   finish              (worker)
    sweep:   stale running -> queued (re-queue) | failed (worker_lost) | canceled   sweep (worker)

Every transition is one conditional UPDATE (compare-and-swap on status + claim_token), so two
deliveries of the same job, a sweep and an API cancel can race safely on SQLite and Postgres.
"""

from __future__ import annotations

import logging
import os
import socket
import uuid
from dataclasses import dataclass
from datetime import timedelta

from sqlalchemy import or_, select, update
from sqlalchemy.orm import sessionmaker

from .db import TERMINAL, Job, utcnow
from .settings import Settings

log = logging.getLogger("ribpull.state")

HOSTNAME = socket.gethostname()


def worker_id() -> str:
    """host:pid of the process running the task (a prefork child, or the solo worker)."""
    return f"{HOSTNAME}:{os.getpid()}"


def _local_process_dead(worker: str | None) -> bool:
    """True when `worker` names a process on this host that no longer exists."""
    if not worker or ":" not in worker:
        return False
    host, _, pid = worker.rpartition(":")
    if host != HOSTNAME or not pid.isdigit():
        return False
    if int(pid) == os.getpid():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False
    return False


def _cas(job: Job):
    """WHERE clause matching `job` exactly as it was read (status and claim token)."""
    cond = [Job.id == job.id, Job.status == job.status]
    cond.append(Job.claim_token.is_(None) if job.claim_token is None else Job.claim_token == job.claim_token)
    return cond


@dataclass
class Claim:
    token: str | None
    outcome: str  # "claimed" | "unknown" | "finished" | "busy" | "canceled" | "failed" | "lost_race"
    job: Job | None = None


def claim_job(sm: sessionmaker, settings: Settings, job_id: str) -> Claim:
    """Take ownership of a queued job, or of a running job whose worker is gone (redelivery)."""
    with sm() as s:
        job = s.scalars(select(Job).where(Job.id == job_id)).first()
        if job is None:
            return Claim(None, "unknown")
        if job.status in TERMINAL:
            return Claim(None, "finished", job)
        now = utcnow()
        if job.status == "running":
            fresh = job.heartbeat_at is not None and job.heartbeat_at > now - timedelta(seconds=settings.stale_after)
            if fresh and not _local_process_dead(job.worker):
                return Claim(None, "busy", job)
        if job.cancel_requested:
            n = s.execute(update(Job).where(*_cas(job)).values(
                status="canceled", finished_at=now, updated_at=now, claim_token=None,
                message="canceled before the worker started it",
            )).rowcount
            s.commit()
            return Claim(None, "canceled" if n else "lost_race", job)
        if job.attempts >= settings.max_attempts:
            n = s.execute(update(Job).where(*_cas(job)).values(
                status="failed", finished_at=now, updated_at=now, claim_token=None,
                error_code="worker_lost",
                error_message=f"the job was started {job.attempts} times and its worker stopped each time "
                              f"(RIBPULL_MAX_ATTEMPTS={settings.max_attempts}); the input may need more memory "
                              "or time than a worker has",
            )).rowcount
            s.commit()
            return Claim(None, "failed" if n else "lost_race", job)
        token = uuid.uuid4().hex
        n = s.execute(update(Job).where(*_cas(job)).values(
            status="running", claim_token=token, attempts=Job.attempts + 1, worker=worker_id(),
            started_at=now, heartbeat_at=now, updated_at=now, finished_at=None,
            stage="load", fraction=0.0, iteration=None, iterations=None, loss=None,
            message=("restarted after its worker stopped" if job.attempts else "started"),
            error_code=None, error_message=None, artifacts=[], metrics=None,
        )).rowcount
        s.commit()
        if not n:
            return Claim(None, "lost_race", job)
        return Claim(token, "claimed", s.scalars(select(Job).where(Job.id == job_id)).first())


def update_running(sm: sessionmaker, job_id: str, token: str, **values) -> bool:
    """Write progress/heartbeat of the attempt holding `token`; False when it no longer holds the job."""
    values.setdefault("updated_at", utcnow())
    with sm() as s:
        n = s.execute(update(Job).where(Job.id == job_id, Job.claim_token == token, Job.status == "running")
                      .values(**values)).rowcount
        s.commit()
    return bool(n)


def read_flags(sm: sessionmaker, job_id: str) -> tuple[str | None, str | None, bool]:
    """(status, claim_token, cancel_requested) of a job."""
    with sm() as s:
        row = s.execute(select(Job.status, Job.claim_token, Job.cancel_requested).where(Job.id == job_id)).first()
    if row is None:
        return None, None, False
    return row[0], row[1], bool(row[2])


def finish(sm: sessionmaker, job_id: str, token: str, status: str, **values) -> bool:
    now = utcnow()
    values.update(status=status, finished_at=now, updated_at=now, heartbeat_at=now)
    with sm() as s:
        n = s.execute(update(Job).where(Job.id == job_id, Job.claim_token == token, Job.status == "running")
                      .values(**values)).rowcount
        s.commit()
    return bool(n)


def sweep(sm: sessionmaker, settings: Settings, requeue) -> dict[str, list[str]]:
    """Handle running jobs whose heartbeat is stale (their worker died or hung).

    cancel requested -> canceled; attempts used up -> failed (worker_lost); else -> queued again and
    `requeue(job_id)` is called. Returns {"requeued": [...], "failed": [...], "canceled": [...]}.
    """
    out: dict[str, list[str]] = {"requeued": [], "failed": [], "canceled": []}
    now = utcnow()
    cut = now - timedelta(seconds=settings.stale_after)
    with sm() as s:
        rows = list(s.scalars(select(Job).where(
            Job.status == "running", or_(Job.heartbeat_at.is_(None), Job.heartbeat_at < cut))))
        for job in rows:
            if job.cancel_requested:
                vals = {"status": "canceled", "finished_at": now, "message": "canceled (its worker had stopped)"}
                key = "canceled"
            elif job.attempts >= settings.max_attempts:
                vals = {"status": "failed", "finished_at": now, "error_code": "worker_lost",
                            "error_message": f"no heartbeat for {settings.stale_after:g} s after {job.attempts} "
                                          f"attempts (RIBPULL_MAX_ATTEMPTS={settings.max_attempts}); "
                                          "the worker running it stopped"}
                key = "failed"
            else:
                vals = {"status": "queued", "message": "re-queued: its worker stopped sending heartbeats"}
                key = "requeued"
            n = s.execute(update(Job).where(*_cas(job)).values(claim_token=None, updated_at=now, **vals)).rowcount
            s.commit()
            if n:
                out[key].append(job.id)
    for job_id in out["requeued"]:
        log.warning("sweep: job %s had a stale heartbeat; re-queued", job_id)
        try:
            requeue(job_id)
        except Exception as exc:  # noqa: BLE001
            log.error("sweep: could not re-queue %s: %s", job_id, exc)
    for job_id in out["failed"] + out["canceled"]:
        log.warning("sweep: job %s finished by the sweep", job_id)
    return out


# ------------------------------------------------------------------------------------------------
# API-side transitions
# ------------------------------------------------------------------------------------------------

def insert_queued(sm: sessionmaker, job: Job) -> Job:
    """(new) -> queued. Raises IntegrityError when the owner's Idempotency-Key is already taken."""
    job.status = "queued"
    with sm() as s:
        s.add(job)
        s.commit()
        s.refresh(job)
        return job


def fail_unqueued(sm: sessionmaker, job_id: str) -> bool:
    """queued -> failed(queue_unavailable): the job could not be sent to Redis."""
    now = utcnow()
    with sm() as s:
        n = s.execute(update(Job).where(Job.id == job_id, Job.status == "queued").values(
            status="failed", error_code="queue_unavailable", finished_at=now, updated_at=now,
            error_message="the job could not be queued (Redis unreachable)",
        )).rowcount
        s.commit()
    return bool(n)


@dataclass
class CancelOutcome:
    outcome: str  # "canceled" (was queued) | "cancel_requested" (running) | "files_deleted" (finished) | "raced"


def cancel(sm: sessionmaker, job: Job) -> CancelOutcome:
    """DELETE of a job as read in `job`: queued -> canceled; running -> cancel requested (the worker
    stops within RIBPULL_CANCEL_GRACE_S); finished -> artifacts_deleted. "raced" when the status changed
    meanwhile (read the job again and retry)."""
    now = utcnow()
    with sm() as s:
        if job.status == "queued":
            n = s.execute(update(Job).where(Job.id == job.id, Job.status == "queued").values(
                status="canceled", cancel_requested=True, finished_at=now, updated_at=now,
                stage=job.stage, message="canceled before it started",
            )).rowcount
            outcome = "canceled"
        elif job.status == "running":
            n = s.execute(update(Job).where(Job.id == job.id, Job.status == "running").values(
                cancel_requested=True, updated_at=now,
            )).rowcount
            outcome = "cancel_requested"
        else:
            n = s.execute(update(Job).where(Job.id == job.id, Job.status.in_(TERMINAL)).values(
                artifacts_deleted=True, updated_at=now,
            )).rowcount
            outcome = "files_deleted"
        s.commit()
    return CancelOutcome(outcome if n else "raced")
