"""The Celery tasks: `run_job` (one thin call of ribpull_core.pipeline.run_pipeline) and
`deliver_webhook` (retries of a completion webhook).

`run_job` is idempotent: it claims the job in the database (compare-and-swap), starts every attempt
from a clean output directory and moves the finished outputs into place with one rename. It never
raises for a job's own failure: RibPullInputError -> failed(code), JobCanceled -> canceled (or
failed "timeout"), anything else -> failed("internal_error"); the worker survives.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import time
import traceback

from app import state
from app.db import TERMINAL, Job, get_job, make_sessionmaker, utcnow
from app.jobs import TASK_WEBHOOK, enqueue
from app.problems import scrub_paths
from app.schemas import finite_or_none, json_safe
from app.settings import Settings
from app.storage import artifact_store, input_file

from . import celery_app as _capp
from .celery_app import celery_app, configure_torch, settings
from .webhooks import backoff_s, deliver_once

log = logging.getLogger("ribpull.worker")

MAX_METRICS_JSON = 256 * 1024


class _InputMissing(Exception):
    pass


class _SourceFailed(Exception):
    """The job's DICOMweb source could not be fetched (worker.dicomweb.DicomwebError inside)."""


class Reporter:
    """progress -> throttled DB writes; should_cancel -> cancel flag / timeout / lost claim;
    plus a heartbeat thread so a long stage without progress calls still looks alive."""

    def __init__(self, sm, settings: Settings, job_id: str, token: str):
        self.sm, self.settings, self.job_id, self.token = sm, settings, job_id, token
        self.deadline = time.monotonic() + settings.job_timeout_s
        self.lost = False
        self.canceled = False
        self.timed_out = False
        self._last_write = 0.0
        self._last_stage: str | None = None
        self._last_check = 0.0
        self._stop = threading.Event()
        self._hb = threading.Thread(target=self._heartbeat, name=f"hb-{job_id[:8]}", daemon=True)
        self._hb.start()
        self._watch = threading.Thread(target=self._cancel_watch, name=f"cw-{job_id[:8]}", daemon=True)
        self._watch.start()

    def _cancel_watch(self) -> None:
        """Enforce a cancel the running stage does not honour within RIBPULL_CANCEL_GRACE_S: record the
        job canceled and end this pool process (the Celery master starts a fresh one; the redelivered
        message finds the job finished). Only in a prefork child: a solo worker is never killed."""
        poll = max(0.1, min(0.5, self.settings.cancel_check_interval_s or 0.5))
        seen_at = None
        while not self._stop.wait(poll):
            try:
                status, token, cancel = state.read_flags(self.sm, self.job_id)
            except Exception as exc:  # noqa: BLE001
                log.debug("job %s: cancel watch read failed: %s", self.job_id, exc)
                continue
            if status != "running" or token != self.token or not cancel:
                continue
            now = time.monotonic()
            seen_at = seen_at or now
            if now - seen_at < self.settings.cancel_grace_s or not _capp.IN_POOL_CHILD:
                continue
            if state.finish(self.sm, self.job_id, self.token, "canceled",
                            message="canceled on request (the running stage was stopped)"):
                log.warning("job %s: cancel not honoured within %.1f s; ending this pool process",
                            self.job_id, self.settings.cancel_grace_s)
                try:
                    artifact_store(self.settings).discard(self.job_id, self.token)
                    notify(self.job_id, self.settings)
                finally:
                    os._exit(0)
            return

    def _heartbeat(self) -> None:
        while not self._stop.wait(self.settings.heartbeat_s):
            try:
                if not state.update_running(self.sm, self.job_id, self.token, heartbeat_at=utcnow()):
                    self.lost = True
                    return
            except Exception as exc:  # noqa: BLE001
                log.warning("job %s: heartbeat write failed: %s", self.job_id, exc)

    def stop(self) -> None:
        self._stop.set()
        self._hb.join(timeout=5)
        if threading.current_thread() is not self._watch:
            self._watch.join(timeout=5)

    def progress(self, p) -> None:
        try:
            now = time.monotonic()
            stage = getattr(p, "stage", None)
            if stage == self._last_stage and now - self._last_write < self.settings.progress_interval_s:
                return
            self._last_stage = stage
            self._last_write = now
            ok = state.update_running(
                self.sm, self.job_id, self.token, heartbeat_at=utcnow(),
                stage=str(stage)[:32] if stage is not None else None,
                fraction=min(1.0, max(0.0, finite_or_none(getattr(p, "fraction", 0.0)) or 0.0)),
                iteration=_int_or_none(getattr(p, "iteration", None)),
                iterations=_int_or_none(getattr(p, "iterations", None)),
                loss=finite_or_none(getattr(p, "loss", None)),
                message=str(getattr(p, "message", "") or "")[:500],
            )
            if not ok:
                self.lost = True
        except Exception as exc:  # noqa: BLE001 - progress must never break a fit
            log.warning("job %s: progress write failed: %s", self.job_id, exc)

    def should_cancel(self) -> bool:
        if self.lost or self.canceled or self.timed_out:
            return True
        now = time.monotonic()
        if now > self.deadline:
            self.timed_out = True
            return True
        if now - self._last_check < self.settings.cancel_check_interval_s:
            return False
        self._last_check = now
        try:
            status, token, cancel = state.read_flags(self.sm, self.job_id)
        except Exception as exc:  # noqa: BLE001
            log.warning("job %s: cancel check failed: %s", self.job_id, exc)
            return False
        if status != "running" or token != self.token:
            self.lost = True
            return True
        if cancel:
            self.canceled = True
            return True
        return False


def _int_or_none(v):
    try:
        return None if v is None else int(v)
    except (TypeError, ValueError):
        return None


def _pipeline_options(params: dict, settings: Settings):
    from ribpull_core.pipeline import PipelineOptions

    return PipelineOptions(
        preset=params.get("preset") or settings.default_preset,
        method=params.get("method"),
        iterations=params.get("iterations"),
        resolution=params.get("resolution"),
        labels=params.get("labels"),
        skeleton=bool(params.get("skeleton", True)),
        preview=bool(params.get("preview", True)),
        dicom_outputs=bool(params.get("dicom_outputs", False)),
        device=settings.device,
        seed=int(params.get("seed") or 0),
        max_points=settings.max_points,
        max_file_bytes=max(settings.max_upload_bytes, 1),
        units=params.get("units") or "mm",
    )


def _pipeline_function(settings: Settings):
    import importlib

    mod_name, _, fn_name = settings.pipeline.partition(":")
    return getattr(importlib.import_module(mod_name), fn_name or "run_pipeline")


def _metrics_for_db(metrics) -> dict | None:
    if not metrics:
        return None
    m = json_safe(metrics)
    if not isinstance(m, dict):
        return None
    if len(json.dumps(m)) > MAX_METRICS_JSON:  # the full file is an artifact; keep the DB row small
        m = {k: v for k, v in m.items() if not isinstance(v, (dict, list))}
    return m


def execute_job(job_id: str, settings: Settings) -> str:
    """Run one job to a final state; returns an outcome word (for logs and tests)."""
    sm = make_sessionmaker(settings)
    claim = state.claim_job(sm, settings, job_id)
    if claim.token is None:
        log.info("job %s: not run (%s)", job_id, claim.outcome)
        if claim.outcome in ("canceled", "failed"):  # this delivery ended the job: nothing can win now
            artifact_store(settings).keep_only(job_id, None)
            notify(job_id, settings)
        return claim.outcome
    token = claim.token
    job = claim.job
    log.info("job %s: attempt %d started (%s)", job_id, job.attempts, state.worker_id())
    # this attempt writes only under its own token; earlier attempts' leftovers are removed once the
    # job is final (store.keep_only), never while another attempt might still be writing them
    store = artifact_store(settings)
    work = store.work_dir(job_id, token)
    reporter = None
    outcome = "failed"
    try:
        inp = input_file(settings, job_id)
        if inp is None and job.source:  # a DICOMweb job: its SEG is fetched from the PACS once
            inp = _fetch_source(job, settings)
        if inp is None:
            raise _InputMissing()
        work.mkdir(parents=True)
        configure_torch()
        from ribpull_core.errors import JobCanceled, RibPullInputError

        run_pipeline = _pipeline_function(settings)

        reporter = Reporter(sm, settings, job_id, token)
        options = _pipeline_options(job.params or {}, settings)
        try:
            result = run_pipeline(inp, work, options, reporter.progress, reporter.should_cancel)
        except RibPullInputError as exc:
            state.finish(sm, job_id, token, "failed", error_code=str(exc.code)[:64],
                         error_message=scrub_paths(exc.message))
            outcome = "failed"
        except JobCanceled:
            if reporter.lost:
                log.warning("job %s: another attempt owns it now; stopping this one", job_id)
                return "lost"
            if reporter.timed_out:
                state.finish(sm, job_id, token, "failed", error_code="timeout",
                             error_message=f"the job ran longer than RIBPULL_JOB_TIMEOUT_S={settings.job_timeout_s}")
                outcome = "failed"
            else:
                state.finish(sm, job_id, token, "canceled", message="canceled on request")
                outcome = "canceled"
        else:
            reporter.stop()
            if reporter.lost:
                return "lost"
            names = store.publish(job_id, token)  # one rename to a name only this attempt uses
            ok = state.finish(
                sm, job_id, token, "succeeded", artifacts=names, artifacts_ref=token,
                metrics=_metrics_for_db(getattr(result, "metrics", None)),
                stage="done", fraction=1.0, message="finished",
            )
            if not ok:  # another attempt owns the job: remove only this attempt's outputs
                store.discard(job_id, token)
                log.warning("job %s: finished but another attempt owns it now; outputs discarded", job_id)
            outcome = "succeeded" if ok else "lost"
    except _SourceFailed as exc:
        err = exc.args[0]
        state.finish(sm, job_id, token, "failed", error_code=err.code, error_message=scrub_paths(err.message)[:2000])
        outcome = "failed"
    except _InputMissing:
        state.finish(sm, job_id, token, "failed", error_code="input_missing",
                     error_message="the uploaded input is no longer on the server; submit the job again")
        outcome = "failed"
    except Exception as exc:  # noqa: BLE001 - a bug or an environment problem fails the job, not the worker
        log.error("job %s: internal error\n%s", job_id, traceback.format_exc())
        try:
            state.finish(sm, job_id, token, "failed", error_code="internal_error",
                         error_message=scrub_paths(f"{type(exc).__name__}: {exc}")[:2000])
        except Exception:
            log.exception("job %s: could not record the failure", job_id)
        outcome = "failed"
    finally:
        if reporter is not None:
            reporter.stop()
        if work.exists():
            shutil.rmtree(work, ignore_errors=True)
        _collect_leftovers(sm, store, job_id, token)
    log.info("job %s: %s", job_id, outcome)
    if outcome == "succeeded":
        deliver_results(job_id, settings)
    if outcome in ("succeeded", "failed", "canceled"):
        notify(job_id, settings)
    return outcome


def _fetch_source(job: Job, settings: Settings):
    """WADO-RS the job's SEG series into its input directory; a PACS problem -> _SourceFailed."""
    from app.storage import input_dir

    from .dicomweb import DicomwebError, fetch_seg

    try:
        return fetch_seg(job.source, settings, input_dir(settings, job.id))
    except DicomwebError as exc:
        log.warning("job %s: DICOMweb source failed: %s: %s", job.id, exc.code, exc.message)
        raise _SourceFailed(exc) from None


def deliver_results(job_id: str, settings: Settings) -> None:
    """First STOW-RS attempt of a finished DICOMweb job inline; retries go through the queue. Never raises."""
    try:
        attempt_delivery(job_id, settings, 1)
    except Exception as exc:  # noqa: BLE001
        log.warning("job %s: DICOMweb delivery scheduling failed: %s", job_id, exc)


def attempt_delivery(job_id: str, settings: Settings, attempt: int) -> str:
    """Store a succeeded job's DICOM results into its source study (STOW-RS), from its artifacts: a
    failed delivery is retried with back-off (RIBPULL_DICOMWEB_BACKOFF_S doubling, up to
    RIBPULL_DICOMWEB_MAX_ATTEMPTS) and never refits. Returns delivered | retrying | failed | nothing."""
    from sqlalchemy import update

    from app.jobs import TASK_DICOMWEB_DELIVER
    from app.storage import artifact_store

    from .dicomweb import DicomwebError, store_results

    sm = make_sessionmaker(settings)
    with sm() as s:
        job = get_job(s, job_id)
    if (job is None or not job.deliver_url or job.delivery_status in ("delivered", "failed")
            or job.status != "succeeded" or job.artifacts_deleted):
        return "nothing"
    retry = False
    try:
        adir = artifact_store(settings).local_dir(job.id, job.artifacts_ref)
        uids = store_results(job.deliver_url, job.source["dicomweb"]["study_uid"], adir, settings)
        err = None
    except DicomwebError as exc:
        err, retry = f"{exc.code}: {exc.message}"[:2000], exc.retryable
    final_failure = err is not None and (not retry or attempt >= settings.dicomweb_max_attempts)
    vals = {"delivery_attempts": Job.delivery_attempts + 1, "delivery_error": err}
    if err is None:
        vals["delivery_status"] = "delivered"
    elif final_failure:
        vals["delivery_status"] = "failed"
    with sm() as s:
        s.execute(update(Job).where(Job.id == job_id).values(**vals))
        s.commit()
    if err is None:
        log.info("job %s: results stored into study %s (attempt %d): %s", job_id,
                 job.source["dicomweb"]["study_uid"], attempt, ", ".join(uids))
        return "delivered"
    if final_failure:
        log.warning("job %s: DICOMweb delivery failed for good after %d attempts: %s", job_id, attempt, err)
        return "failed"
    delay = min(3600.0, settings.dicomweb_backoff_s * 2 ** (attempt - 1))
    log.info("job %s: DICOMweb delivery attempt %d failed (%s); retry in %.1f s", job_id, attempt, err, delay)
    celery_app.send_task(TASK_DICOMWEB_DELIVER, args=[job_id, attempt + 1], countdown=delay,
                         queue=celery_app.conf.task_default_queue)
    return "retrying"


def _collect_leftovers(sm, store, job_id: str, token: str) -> None:
    """When THIS attempt ended the job (it is final and still carries our claim token), no other
    attempt can win any more: remove what crashed or lost attempts left in its storage."""
    try:
        with sm() as s:
            job = get_job(s, job_id)
        if job is not None and job.status in TERMINAL and job.claim_token == token:
            store.keep_only(job_id, job.artifacts_ref)
    except Exception as exc:  # noqa: BLE001 - housekeeping never fails a job
        log.warning("job %s: could not remove leftovers of earlier attempts: %s", job_id, exc)


def notify(job_id: str, settings: Settings) -> None:
    """First webhook attempt inline; retries go through the queue with back-off. Never raises."""
    try:
        sm = make_sessionmaker(settings)
        with sm() as s:
            job = get_job(s, job_id)
        if job is None or not job.webhook_url or job.webhook_status == "delivered":
            return
        attempt_webhook(job_id, settings, 1)
    except Exception as exc:  # noqa: BLE001
        log.warning("job %s: webhook scheduling failed: %s", job_id, exc)


def attempt_webhook(job_id: str, settings: Settings, attempt: int) -> str:
    from sqlalchemy import update

    sm = make_sessionmaker(settings)
    with sm() as s:
        job = get_job(s, job_id)
    if job is None or not job.webhook_url or job.webhook_status == "delivered":
        return "nothing"
    ok, err = deliver_once(job, settings)
    with sm() as s:
        vals = {"webhook_attempts": Job.webhook_attempts + 1, "webhook_error": err}
        if ok:
            vals["webhook_status"] = "delivered"
        elif attempt >= settings.webhook_max_attempts or (err or "").startswith("refused target"):
            vals["webhook_status"] = "failed"
        s.execute(update(Job).where(Job.id == job_id).values(**vals))
        s.commit()
    if ok:
        log.info("job %s: webhook delivered (attempt %d)", job_id, attempt)
        return "delivered"
    if attempt >= settings.webhook_max_attempts or (err or "").startswith("refused target"):
        log.warning("job %s: webhook failed for good after %d attempts: %s", job_id, attempt, err)
        return "failed"
    delay = backoff_s(settings, attempt)
    log.info("job %s: webhook attempt %d failed (%s); retry in %.1f s", job_id, attempt, err, delay)
    celery_app.send_task(TASK_WEBHOOK, args=[job_id, attempt + 1], countdown=delay,
                         queue=celery_app.conf.task_default_queue)
    return "retrying"


@celery_app.task(name="ribpull.run_job", bind=True, acks_late=True, reject_on_worker_lost=True, ignore_result=True)
def run_job(self, job_id: str) -> str:
    return execute_job(str(job_id), settings)


@celery_app.task(name=TASK_WEBHOOK, ignore_result=True, acks_late=True)
def deliver_webhook(job_id: str, attempt: int = 1) -> str:
    try:
        return attempt_webhook(str(job_id), settings, int(attempt))
    except Exception as exc:  # noqa: BLE001
        log.warning("job %s: webhook task error: %s", job_id, exc)
        return "error"


@celery_app.task(name="ribpull.deliver_dicomweb", ignore_result=True, acks_late=True)
def deliver_dicomweb(job_id: str, attempt: int = 1) -> str:
    try:
        return attempt_delivery(str(job_id), settings, int(attempt))
    except Exception as exc:  # noqa: BLE001
        log.warning("job %s: DICOMweb delivery task error: %s", job_id, exc)
        return "error"


__all__ = ["deliver_dicomweb", "deliver_webhook", "enqueue", "execute_job", "run_job"]
