"""POST /v1/jobs (streaming multipart upload, validated before anything is queued; or a JSON body that
names a DICOMweb series, fetched by the worker), GET /v1/jobs,
GET /v1/jobs/{id}, DELETE /v1/jobs/{id}. Status changes go through app/state.py."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import uuid
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response
from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from starlette.concurrency import run_in_threadpool

from .. import state
from ..db import Job, utcnow
from ..deps import CeleryDep, FieldCacheDep, JobDep, JobIdPath, OwnerDep, SessionsDep, SettingsDep, read_job
from ..jobs import TASK_RUN_JOB, TASK_WEBHOOK, decode_cursor, encode_cursor, enqueue, job_to_dict
from ..netpolicy import dicomweb_target_problem, webhook_target_problem
from ..problems import INPUT_ERROR_STATUS, ProblemError, validation_problem
from ..schemas import DicomwebJobIn, JobList, JobOut, JobParams, Status
from ..settings import Settings
from ..storage import artifact_store, input_dir, job_dir, rmtree_quiet
from ..upload import receive_upload
from . import problems

log = logging.getLogger("ribpull.api")

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {
                            "type": "string",
                            "format": "binary",
                            "description": "Point cloud or label map: .ply .xyz .txt .csv .npy .npz .pcd "
                                           ".nii .nii.gz (size cap: RIBPULL_MAX_UPLOAD_MB; a compressed file "
                                           "may inflate to RIBPULL_MAX_INFLATED_MB).",
                        },
                        "params": {"$ref": "#/components/schemas/JobParams"},
                    },
                },
                "encoding": {"params": {"contentType": "application/json"}},
            },
            "application/json": {"schema": {"$ref": "#/components/schemas/DicomwebJobIn"}},
        },
    }
}


def _base_url() -> str:
    return ""


@router.post(
    "",
    status_code=202,
    response_model=JobOut,
    summary="Submit a job (multipart: `file` + optional JSON `params`; or a JSON body naming a DICOMweb SEG series)",
    openapi_extra=UPLOAD_BODY,
    responses={
        200: {"description": "Idempotent replay: the job created earlier with this Idempotency-Key",
              "model": JobOut},
        202: {"description": "Accepted; the job is queued. `Location` points at it."},
        **problems(400, 401, 408, 413, 415, 422, 503),
    },
)
async def create_job(
    request: Request,
    response: Response,
    owner: OwnerDep,
    settings: SettingsDep,
    sm: SessionsDep,
    celery: CeleryDep,
    idempotency_key: Annotated[
        str | None,
        Header(max_length=255, description="Same key + same payload returns the same job; "
                                           "same key + a different payload is 422."),
    ] = None,
):
    if request.headers.get("content-type", "").split(";")[0].strip().lower() == "application/json":
        return await _create_dicomweb_job(request, response, owner, settings, sm, celery, idempotency_key)
    up = await receive_upload(request, settings)
    moved = False
    try:
        if up.path is None:
            raise ProblemError(422, "missing_file", "the multipart form needs a `file` part with the input")
        params = _parse_params(up.fields.get("params"))
        await _check_limits(params, settings)
        stored = params.model_dump()
        stored["preset"] = params.preset or settings.default_preset
        fingerprint = hashlib.sha256(
            f"{up.sha256}|{up.path.name.lower()}|{json.dumps(stored, sort_keys=True)}".encode()
        ).hexdigest()
        key = idempotency_key.strip() if idempotency_key else None
        replay = await _replay_if_seen(sm, owner, key, fingerprint, response, settings)
        if replay is not None:
            return replay
        cloud = await run_in_threadpool(validate_input, up.path, params, settings)

        job_id = uuid.uuid4().hex
        jdir = job_dir(settings, job_id)
        idir = input_dir(settings, job_id)
        idir.mkdir(parents=True)
        dest = idir / up.path.name
        os.replace(up.path, dest)
        moved = True
        now = utcnow()
        job = Job(
            id=job_id, owner=owner, status="queued", params=stored,
            input_name=up.filename[:255] or dest.name, input_format=str(getattr(cloud, "source_format", "")),
            input_bytes=up.size, input_sha256=up.sha256, input_points=len(cloud.points),
            idempotency_key=key, fingerprint=fingerprint, created_at=now, updated_at=now,
            webhook_url=params.webhook_url, webhook_status="pending" if params.webhook_url else None,
        )
        return await _queue_job(job, jdir, fingerprint, response, owner, settings, sm, celery)
    finally:
        if not moved:
            up.cleanup()
        else:
            rmtree_quiet(up.tmpdir)


async def _queue_job(job: Job, jdir, fingerprint: str, response: Response, owner: str, settings: Settings, sm,
                     celery):
    """Insert the queued row and send the task; 202 + Location (or the replay of a raced Idempotency-Key)."""
    try:
        job = await run_in_threadpool(state.insert_queued, sm, job)
    except IntegrityError:  # the same Idempotency-Key raced in: answer like a replay
        rmtree_quiet(jdir)
        existing = await run_in_threadpool(_find_idem, sm, owner, job.idempotency_key)
        if existing is None:
            raise
        return _replay(existing, fingerprint, response, settings)
    try:
        await run_in_threadpool(enqueue, celery, TASK_RUN_JOB, job.id)
    except Exception as exc:  # noqa: BLE001
        log.error("could not enqueue job %s: %s", job.id, exc)
        await run_in_threadpool(state.fail_unqueued, sm, job.id)
        rmtree_quiet(input_dir(settings, job.id))
        raise ProblemError(503, "queue_unavailable",
                           "the job queue (Redis) is not reachable; the job was not started, try again",
                           headers={"Retry-After": "10"}) from None
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    response.status_code = 202
    return job_to_dict(job, settings, _base_url())


async def _create_dicomweb_job(request: Request, response: Response, owner: str, settings: Settings, sm, celery,
                               idempotency_key: str | None):
    """POST /v1/jobs with a JSON body: the input is a SEG series on a PACS, fetched by the worker."""
    try:
        body = DicomwebJobIn.model_validate_json(await request.body())
    except ValidationError as exc:
        raise validation_problem(list(exc.errors()), "body") from None
    await _check_limits(body.params, settings)
    targets = [("source.dicomweb.url", body.source.dicomweb.url)]
    if body.deliver is not None:
        targets.append(("deliver.dicomweb.url", body.deliver.dicomweb.url))
    for where, url in targets:
        why = dicomweb_target_problem(url, settings)
        if why:
            raise ProblemError(422, "dicomweb_refused", f"{where} is not an allowed DICOMweb server: {why}")
    stored = body.params.model_dump()
    stored["preset"] = body.params.preset or settings.default_preset
    source = body.source.model_dump()
    deliver_url = body.deliver.dicomweb.url if body.deliver is not None else None
    fingerprint = hashlib.sha256(
        json.dumps({"source": source, "deliver": deliver_url, "params": stored}, sort_keys=True).encode()
    ).hexdigest()
    key = idempotency_key.strip() if idempotency_key else None
    replay = await _replay_if_seen(sm, owner, key, fingerprint, response, settings)
    if replay is not None:
        return replay
    job_id = uuid.uuid4().hex
    now = utcnow()
    job = Job(
        id=job_id, owner=owner, status="queued", params=stored, input_name=body.source.dicomweb.series_uid,
        input_format="dicomweb", idempotency_key=key, fingerprint=fingerprint, created_at=now, updated_at=now,
        webhook_url=body.params.webhook_url, webhook_status="pending" if body.params.webhook_url else None,
        source=source, deliver_url=deliver_url, delivery_status="pending" if deliver_url else None,
    )
    return await _queue_job(job, job_dir(settings, job_id), fingerprint, response, owner, settings, sm, celery)


def _parse_params(raw: str | None) -> JobParams:
    if raw is None or not raw.strip():
        return JobParams()
    try:
        return JobParams.model_validate_json(raw)
    except ValidationError as exc:
        raise validation_problem(list(exc.errors()), "params") from None


async def _check_limits(params: JobParams, settings: Settings) -> None:
    """Per-job resource bounds and the webhook target policy: 422 at submission, never a failed job."""
    if params.iterations is not None and params.iterations > settings.max_iterations:
        raise ProblemError(
            422, "limit_exceeded",
            f"params.iterations={params.iterations} is over this server's limit of {settings.max_iterations} "
            "(RIBPULL_MAX_ITERATIONS)")
    if params.resolution is not None and params.resolution > settings.resolution_limit:
        raise ProblemError(
            422, "limit_exceeded",
            f"params.resolution={params.resolution} is over this server's limit of {settings.resolution_limit} "
            f"(the largest grid that fits RIBPULL_WORKER_MEMORY_MB={settings.worker_memory_mb}, at most "
            f"RIBPULL_MAX_RESOLUTION={settings.max_resolution})")
    if params.webhook_url:
        why = await run_in_threadpool(webhook_target_problem, params.webhook_url, settings)
        if why:
            raise ProblemError(422, "webhook_refused", f"params.webhook_url is not an allowed target: {why}")


def _find_idem(sm, owner: str, key: str) -> Job | None:
    with sm() as s:
        return s.scalars(select(Job).where(Job.owner == owner, Job.idempotency_key == key)).first()


async def _replay_if_seen(sm, owner: str, key: str | None, fingerprint: str, response: Response,
                          settings: Settings) -> dict | None:
    """The replay of the job created earlier with this Idempotency-Key (422 when its payload
    differs), or None when there is no key or no such job yet."""
    if not key:
        return None
    existing = await run_in_threadpool(_find_idem, sm, owner, key)
    return None if existing is None else _replay(existing, fingerprint, response, settings)


def _replay(existing: Job, fingerprint: str, response: Response, settings: Settings):
    if existing.fingerprint != fingerprint:
        raise ProblemError(
            422, "idempotency_key_reused",
            "this Idempotency-Key was already used with a different file or different params",
        )
    response.headers["Location"] = f"/v1/jobs/{existing.id}"
    response.status_code = 200
    return job_to_dict(existing, settings, _base_url())


def validate_input(path, params: JobParams, settings: Settings):
    """Load the upload with the core's loader so bad files are refused before anything is queued."""
    from ribpull_core.errors import RibPullInputError
    from ribpull_core.io import load_point_cloud

    try:
        cloud = load_point_cloud(
            path, labels=params.labels, max_points=settings.max_points, max_file_bytes=settings.max_upload_bytes,
            units=params.units, max_nifti_bytes=settings.max_nifti_bytes,
        )
        check_extent(cloud.points, params.units, settings)
        if params.dicom_outputs:  # DICOM images need a voxel grid: refuse a point cloud before queuing
            from ribpull_core.dicom.nifti_source import require_voxel_grid

            require_voxel_grid(cloud)
        return cloud
    except ProblemError:
        raise
    except RibPullInputError as exc:
        raise ProblemError(INPUT_ERROR_STATUS.get(exc.code, 422), exc.code, exc.message) from None
    except MemoryError:
        raise ProblemError(413, "too_large", "the file needs more memory than this server has") from None
    except Exception as exc:
        log.exception("loader failed on %s", path.name)
        raise ProblemError(422, "parse_error", f"could not read the file: {type(exc).__name__}") from None


def check_extent(points, units: str, settings: Settings) -> None:
    """A ribcage spans RIBPULL_MIN_EXTENT_MM..RIBPULL_MAX_EXTENT_MM; anything else is almost always a unit
    mistake (metres, or garbage coordinates) that would run for minutes and fail: refuse it now."""
    import numpy as np

    from ribpull_core.io import UNIT_SCALE

    ext = float(np.max(np.ptp(points, axis=0)))
    lo, hi = settings.min_extent_mm, settings.max_extent_mm
    if lo <= ext <= hi:
        return
    raw = ext / UNIT_SCALE[units]
    fits = [u for u, f in UNIT_SCALE.items() if u != units and lo <= raw * f <= hi]
    hint = (f'; if the coordinates are in {"/".join(fits)}, send params {{"units": "{fits[0]}"}}' if fits
            else "; no unit (mm, cm, m) makes this a ribcage: check the coordinates")
    raise ProblemError(
        422, "implausible_extent",
        f"the input spans {ext:.4g} mm (params.units={units!r}); a ribcage spans {lo:g} to {hi:g} mm{hint}")


@router.get("", response_model=JobList, responses=problems(401, 422),
            summary="List jobs, newest first (cursor pagination)")
def list_jobs(
    owner: OwnerDep,
    settings: SettingsDep,
    sm: SessionsDep,
    limit: Annotated[int, Query(ge=1, le=100)] = 20,
    cursor: Annotated[str | None, Query(max_length=64, description="`next_cursor` of the previous page")] = None,
    status: Annotated[Status | None, Query(description="Only jobs with this status")] = None,
):
    q = select(Job).where(Job.owner == owner)
    if status:
        q = q.where(Job.status == status)
    if cursor:
        seq = decode_cursor(cursor)
        if seq is None:
            raise ProblemError(422, "bad_cursor", "cursor is not a value returned as next_cursor")
        q = q.where(Job.seq < seq)
    q = q.order_by(Job.seq.desc()).limit(limit + 1)
    with sm() as s:
        rows = list(s.scalars(q))
    more = len(rows) > limit
    rows = rows[:limit]
    return {
        "items": [job_to_dict(j, settings, _base_url()) for j in rows],
        "next_cursor": encode_cursor(rows[-1].seq) if more and rows else None,
        "limit": limit,
    }


@router.get("/{job_id}", response_model=JobOut, responses=problems(401, 404),
            summary="A job: status, progress, error, artifact links")
def get_job_route(job: JobDep, settings: SettingsDep):
    return job_to_dict(job, settings, _base_url())


@router.delete(
    "/{job_id}",
    response_model=JobOut,
    responses={
        200: {"description": "Queued job canceled, or a finished job's files deleted (record kept)"},
        202: {"description": "Running job: cancellation requested; it turns `canceled` within "
                             "RIBPULL_CANCEL_GRACE_S + 1 s", "model": JobOut},
        **problems(401, 404),
    },
    summary="Cancel a queued/running job, or delete a finished job's files",
)
def delete_job(job_id: JobIdPath, response: Response, owner: OwnerDep, settings: SettingsDep, sm: SessionsDep,
               celery: CeleryDep, cache: FieldCacheDep):
    for _ in range(5):
        job = read_job(sm, job_id, owner)
        result = state.cancel(sm, job)
        if result.outcome == "canceled":
            rmtree_quiet(input_dir(settings, job_id))
            job = read_job(sm, job_id, owner)
            if job.webhook_url:
                try:
                    enqueue(celery, TASK_WEBHOOK, job.id)
                except Exception as exc:  # noqa: BLE001
                    log.warning("could not queue webhook for canceled job %s: %s", job.id, exc)
            response.status_code = 200
            return job_to_dict(job, settings, _base_url())
        if result.outcome == "cancel_requested":
            response.status_code = 202
            return job_to_dict(read_job(sm, job_id, owner), settings, _base_url())
        if result.outcome == "files_deleted":
            cache.drop(job_id)
            artifact_store(settings).delete_job(job_id)
            response.status_code = 200
            return job_to_dict(read_job(sm, job_id, owner), settings, _base_url())
        time.sleep(0.05)  # the status changed under us: look again
    raise ProblemError(409, "conflict", "the job changed state repeatedly; try again")
