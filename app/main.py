"""RibPull HTTP API (FastAPI): upload a ribcage, follow the job, download artifacts, query the field.

Run: `uvicorn app.main:app` (or `make run`). Everything is configured by environment variables
(app/settings.py); the job store is shared with the Celery worker (worker/celery_app.py).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
import uuid
from contextlib import asynccontextmanager
from typing import Annotated

from fastapi import Depends, FastAPI, Header, Path, Query, Request, Response
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse
from pydantic import ValidationError
from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError
from starlette.concurrency import run_in_threadpool

from . import __version__
from .auth import current_owner
from .db import TERMINAL, Job, db_ping, get_job, make_engine, make_sessionmaker, utcnow
from .jobs import (
    TASK_RUN_JOB,
    TASK_WEBHOOK,
    WORKER_KEY_PREFIX,
    celery_client,
    decode_cursor,
    encode_cursor,
    enqueue,
    job_to_dict,
)
from .problems import (
    INPUT_ERROR_STATUS,
    PROBLEM_MEDIA_TYPE,
    ProblemError,
    install_handlers,
    problem_response,
    validation_problem,
)
from .query import FieldCache, run_query
from .schemas import (
    Health,
    JobList,
    JobOut,
    JobParams,
    Problem,
    QueryIn,
    QueryOut,
    Ready,
    Status,
)
from .settings import Settings, get_settings
from .storage import (
    ARTIFACT_MEDIA_TYPES,
    JOB_ID_RE,
    artifacts_dir,
    ensure_dirs,
    input_dir,
    job_dir,
    media_type,
    rmtree_quiet,
)
from .middleware import BodyLimit, BodyTimeout, Hardening, query_body_budget
from .netpolicy import webhook_target_problem
from .upload import receive_upload

log = logging.getLogger("ribpull.api")

ARTIFACT_NAMES = tuple(ARTIFACT_MEDIA_TYPES)  # == ribpull_core.pipeline.ARTIFACT_NAMES (a test checks)


def _problems(*codes: int) -> dict:
    desc = {
        400: "Malformed request", 401: "Missing or unknown API key", 404: "Not found", 409: "Conflict",
        410: "Gone", 413: "Too large", 415: "Unsupported media type or file format",
        422: "Invalid input (parameters, file content or Idempotency-Key reuse)", 503: "Unavailable",
    }
    return {
        c: {
            "description": desc.get(c, "Error"),
            "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
        for c in codes
    }


JobIdPath = Annotated[str, Path(description="Job id (32 lowercase hex characters).", max_length=64)]


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        ensure_dirs(settings)
        make_engine(settings)
        _clean_stale_uploads(settings)
        yield

    app = FastAPI(
        title="RibPull",
        version=__version__,
        summary="Neural occupancy surfaces and rib skeletons from ribcage point clouds / CT label maps, as jobs.",
        description=(
            "Upload a point cloud or a NIfTI label map, follow the job, download mesh / SDF / skeleton / "
            "weights, query the fitted field. Errors are `application/problem+json`. When API keys are "
            "configured, send `Authorization: Bearer <key>`; a key sees only its own jobs."
        ),
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.key_hashes = settings.key_hashes
    app.state.field_cache = FieldCache()
    app.state._sm = None
    app.state._celery = None
    app.state._redis = None
    install_handlers(app)
    # added innermost first: Hardening wraps BodyTimeout wraps BodyLimit
    app.add_middleware(BodyLimit, query_limit=query_body_budget(settings.max_query_points))
    app.add_middleware(BodyTimeout, timeout=settings.body_timeout_s)
    app.add_middleware(Hardening)

    def sessions():
        if app.state._sm is None:
            ensure_dirs(settings)
            app.state._sm = make_sessionmaker(settings)
        return app.state._sm

    def celery():
        if app.state._celery is None:
            app.state._celery = celery_client(settings)
        return app.state._celery

    def redis_client():
        if app.state._redis is None:
            import redis

            app.state._redis = redis.Redis.from_url(
                settings.redis_url, socket_timeout=2, socket_connect_timeout=2, health_check_interval=10
            )
        return app.state._redis

    def load_job(job_id: str, owner: str) -> Job:
        if not JOB_ID_RE.match(job_id):
            raise ProblemError(404, "job_not_found", f"no job with id '{job_id[:64]}'")
        with sessions()() as s:
            job = get_job(s, job_id, owner)
        if job is None:
            raise ProblemError(404, "job_not_found", f"no job with id '{job_id}'")
        return job

    def base_url() -> str:
        return ""

    # ------------------------------------------------------------------------------------------
    # health
    # ------------------------------------------------------------------------------------------

    @app.get("/healthz", response_model=Health, tags=["health"], summary="Liveness: the process answers")
    def healthz():
        return {"status": "ok"}

    @app.get(
        "/readyz", response_model=Ready, tags=["health"], responses=_problems(503),
        summary="Readiness: database, Redis and storage reachable, a worker heartbeat seen",
    )
    def readyz():
        checks: dict = {}
        ok = True
        try:
            db_ping(make_engine(settings))
            checks["database"] = "ok"
        except Exception as exc:  # noqa: BLE001
            ok = False
            checks["database"] = f"error: {type(exc).__name__}"
        workers = 0
        try:
            r = redis_client()
            r.ping()
            checks["redis"] = "ok"
            workers = sum(1 for _ in r.scan_iter(match=WORKER_KEY_PREFIX + "*", count=100))
        except Exception as exc:  # noqa: BLE001
            ok = False
            checks["redis"] = f"error: {type(exc).__name__}"
        checks["workers"] = workers
        if settings.readyz_require_worker and workers == 0:
            ok = False
        try:
            ensure_dirs(settings)
            with tempfile.NamedTemporaryFile(dir=settings.storage_path, prefix=".ready-"):
                pass
            checks["storage"] = "ok"
        except Exception as exc:  # noqa: BLE001
            ok = False
            checks["storage"] = f"error: {type(exc).__name__}"
        if not ok:
            return problem_response(503, "not_ready", "a dependency is not available", extra={"checks": checks})
        return {"status": "ready", "checks": checks}

    # ------------------------------------------------------------------------------------------
    # jobs
    # ------------------------------------------------------------------------------------------

    upload_body = {
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
                                               ".nii .nii.gz (size cap: RIBPULL_MAX_UPLOAD_MB).",
                            },
                            "params": {"$ref": "#/components/schemas/JobParams"},
                        },
                    },
                    "encoding": {"params": {"contentType": "application/json"}},
                }
            },
        }
    }

    @app.post(
        "/v1/jobs",
        status_code=202,
        response_model=JobOut,
        tags=["jobs"],
        summary="Submit a job (multipart: `file` + optional JSON `params`)",
        openapi_extra=upload_body,
        responses={
            200: {"description": "Idempotent replay: the job created earlier with this Idempotency-Key",
                  "model": JobOut},
            202: {"description": "Accepted; the job is queued. `Location` points at it."},
            **_problems(400, 401, 413, 415, 422, 503),
        },
    )
    async def create_job(
        request: Request,
        response: Response,
        owner: str = Depends(current_owner),
        idempotency_key: Annotated[
            str | None,
            Header(max_length=255, description="Same key + same payload returns the same job; "
                                               "same key + a different payload is 422."),
        ] = None,
    ):
        up = await receive_upload(request, settings)
        moved = False
        try:
            if up.path is None:
                raise ProblemError(422, "missing_file", "the multipart form needs a `file` part with the input")
            params = _parse_params(up.fields.get("params"))
            await _check_limits(params)
            stored = params.model_dump()
            stored["preset"] = params.preset or settings.default_preset
            fingerprint = hashlib.sha256(
                f"{up.sha256}|{up.path.name.lower()}|{json.dumps(stored, sort_keys=True)}".encode()
            ).hexdigest()
            key = idempotency_key.strip() if idempotency_key else None
            if key:
                existing = await run_in_threadpool(_find_idem, owner, key)
                if existing is not None:
                    return _replay(existing, fingerprint, response)
            cloud = await run_in_threadpool(_validate_input, up.path, params, settings)

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
            try:
                job = await run_in_threadpool(_insert, job)
            except IntegrityError:  # the same Idempotency-Key raced in: answer like a replay
                rmtree_quiet(jdir)
                existing = await run_in_threadpool(_find_idem, owner, key)
                if existing is None:
                    raise
                return _replay(existing, fingerprint, response)
            try:
                await run_in_threadpool(enqueue, celery(), TASK_RUN_JOB, job_id)
            except Exception as exc:  # noqa: BLE001
                log.error("could not enqueue job %s: %s", job_id, exc)
                await run_in_threadpool(_fail_unqueued, job_id)
                raise ProblemError(503, "queue_unavailable",
                                   "the job queue (Redis) is not reachable; the job was not started, try again",
                                   headers={"Retry-After": "10"}) from None
            response.headers["Location"] = f"/v1/jobs/{job_id}"
            response.status_code = 202
            return job_to_dict(job, settings, base_url())
        finally:
            if not moved:
                up.cleanup()
            else:
                rmtree_quiet(up.tmpdir)

    def _parse_params(raw: str | None) -> JobParams:
        if raw is None or not raw.strip():
            return JobParams()
        try:
            return JobParams.model_validate_json(raw)
        except ValidationError as exc:
            raise validation_problem(list(exc.errors()), "params") from None

    async def _check_limits(params: JobParams) -> None:
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

    def _find_idem(owner: str, key: str) -> Job | None:
        with sessions()() as s:
            return s.scalars(select(Job).where(Job.owner == owner, Job.idempotency_key == key)).first()

    def _replay(existing: Job, fingerprint: str, response: Response):
        if existing.fingerprint != fingerprint:
            raise ProblemError(
                422, "idempotency_key_reused",
                "this Idempotency-Key was already used with a different file or different params",
            )
        response.headers["Location"] = f"/v1/jobs/{existing.id}"
        response.status_code = 200
        return job_to_dict(existing, settings, base_url())

    def _insert(job: Job) -> Job:
        with sessions()() as s:
            s.add(job)
            s.commit()
            s.refresh(job)
            return job

    def _fail_unqueued(job_id: str) -> None:
        with sessions()() as s:
            s.execute(update(Job).where(Job.id == job_id, Job.status == "queued").values(
                status="failed", error_code="queue_unavailable", finished_at=utcnow(), updated_at=utcnow(),
                error_message="the job could not be queued (Redis unreachable)",
            ))
            s.commit()
        rmtree_quiet(input_dir(settings, job_id))

    @app.get(
        "/v1/jobs", response_model=JobList, tags=["jobs"], responses=_problems(401, 422),
        summary="List jobs, newest first (cursor pagination)",
    )
    def list_jobs(
        owner: str = Depends(current_owner),
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
        with sessions()() as s:
            rows = list(s.scalars(q))
        more = len(rows) > limit
        rows = rows[:limit]
        return {
            "items": [job_to_dict(j, settings, base_url()) for j in rows],
            "next_cursor": encode_cursor(rows[-1].seq) if more and rows else None,
            "limit": limit,
        }

    @app.get(
        "/v1/jobs/{job_id}", response_model=JobOut, tags=["jobs"], responses=_problems(401, 404),
        summary="A job: status, progress, error, artifact links",
    )
    def get_job_route(job_id: JobIdPath, owner: str = Depends(current_owner)):
        return job_to_dict(load_job(job_id, owner), settings, base_url())

    @app.delete(
        "/v1/jobs/{job_id}",
        response_model=JobOut,
        tags=["jobs"],
        responses={
            200: {"description": "Queued job canceled, or a finished job's files deleted (record kept)"},
            202: {"description": "Running job: cancellation requested; it turns `canceled` shortly",
                  "model": JobOut},
            **_problems(401, 404),
        },
        summary="Cancel a queued/running job, or delete a finished job's files",
    )
    def delete_job(job_id: JobIdPath, response: Response, owner: str = Depends(current_owner)):
        for _ in range(5):
            job = load_job(job_id, owner)
            now = utcnow()
            with sessions()() as s:
                if job.status == "queued":
                    n = s.execute(update(Job).where(Job.id == job_id, Job.status == "queued").values(
                        status="canceled", cancel_requested=True, finished_at=now, updated_at=now,
                        stage=job.stage, message="canceled before it started",
                    )).rowcount
                    s.commit()
                    if n:
                        rmtree_quiet(input_dir(settings, job_id))
                        job = load_job(job_id, owner)
                        _webhook_after_cancel(job)
                        response.status_code = 200
                        return job_to_dict(job, settings, base_url())
                elif job.status == "running":
                    n = s.execute(update(Job).where(Job.id == job_id, Job.status == "running").values(
                        cancel_requested=True, updated_at=now,
                    )).rowcount
                    s.commit()
                    if n:
                        response.status_code = 202
                        return job_to_dict(load_job(job_id, owner), settings, base_url())
                else:  # finished: delete files, keep the record
                    n = s.execute(update(Job).where(Job.id == job_id, Job.status.in_(TERMINAL)).values(
                        artifacts_deleted=True, updated_at=now,
                    )).rowcount
                    s.commit()
                    if n:
                        app.state.field_cache.drop(job_id)
                        shutil.rmtree(job_dir(settings, job_id), ignore_errors=True)
                        response.status_code = 200
                        return job_to_dict(load_job(job_id, owner), settings, base_url())
            time.sleep(0.05)  # the status changed under us: look again
        raise ProblemError(409, "conflict", "the job changed state repeatedly; try again")

    def _webhook_after_cancel(job: Job) -> None:
        if job.webhook_url:
            try:
                enqueue(celery(), TASK_WEBHOOK, job.id)
            except Exception as exc:  # noqa: BLE001
                log.warning("could not queue webhook for canceled job %s: %s", job.id, exc)

    @app.get(
        "/v1/jobs/{job_id}/artifacts/{name}",
        tags=["jobs"],
        response_class=FileResponse,
        responses={
            200: {
                "description": "The file. Media types: " + ", ".join(
                    f"{n} {t}" for n, t in ARTIFACT_MEDIA_TYPES.items()),
                "content": {t: {"schema": {"type": "string", "format": "binary"}}
                            for t in sorted(set(ARTIFACT_MEDIA_TYPES.values()))},
            },
            **_problems(401, 404, 410),
        },
        summary="Download one artifact",
    )
    def get_artifact(
        job_id: JobIdPath,
        name: Annotated[str, Path(max_length=64, description="One of: " + ", ".join(ARTIFACT_NAMES))],
        owner: str = Depends(current_owner),
    ):
        if name not in ARTIFACT_MEDIA_TYPES:
            raise ProblemError(404, "unknown_artifact",
                               f"'{name[:64]}' is not an artifact name; names: {', '.join(ARTIFACT_NAMES)}")
        job = load_job(job_id, owner)
        if job.artifacts_deleted:
            raise ProblemError(410, "artifacts_deleted", "this job's files were deleted")
        if job.status != "succeeded":
            raise ProblemError(404, "artifact_not_found", f"job is {job.status}; artifacts exist once it succeeded")
        path = artifacts_dir(settings, job_id) / name
        if name not in (job.artifacts or []) or not path.is_file():
            raise ProblemError(404, "artifact_not_found", f"this job did not produce {name}")
        return FileResponse(path, media_type=media_type(name), filename=f"{name}")

    @app.post(
        "/v1/jobs/{job_id}/query",
        response_model=QueryOut,
        tags=["jobs"],
        responses=_problems(401, 404, 409, 413, 422),
        summary="Occupancy, U and SDF (mm) of the fitted field at points in mm",
    )
    def query_job(job_id: JobIdPath, body: QueryIn, owner: str = Depends(current_owner)):
        if len(body.points_mm) > settings.max_query_points:
            raise ProblemError(422, "too_many_points",
                               f"{len(body.points_mm)} points; the limit is {settings.max_query_points} per request")
        job = load_job(job_id, owner)
        if job.status != "succeeded":
            raise ProblemError(409, "job_not_succeeded", f"job is {job.status}; query it once it has succeeded")
        if job.artifacts_deleted:
            raise ProblemError(409, "artifacts_deleted", "this job's files were deleted")
        adir = artifacts_dir(settings, job_id)
        if not (adir / "model.safetensors").is_file():
            raise ProblemError(409, "no_model", "this job has no stored weights")
        return run_query(app.state.field_cache, job_id, adir, body.points_mm)

    # ------------------------------------------------------------------------------------------
    # OpenAPI: add the schemas referenced from the hand-written multipart body / problem responses
    # ------------------------------------------------------------------------------------------

    def custom_openapi():
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(
            title=app.title, version=app.version, summary=app.summary, description=app.description,
            routes=app.routes,
        )
        comps = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in (JobParams, Problem):
            js = model.model_json_schema(ref_template="#/components/schemas/{model}")
            for name, sub in js.pop("$defs", {}).items():
                comps.setdefault(name, sub)
            comps[model.__name__] = js
        app.openapi_schema = schema
        return schema

    app.openapi = custom_openapi
    return app


def _validate_input(path, params: JobParams, settings: Settings):
    """Load the upload with the core's loader so bad files are refused before anything is queued."""
    from ribpull_core.errors import RibPullInputError
    from ribpull_core.io import load_point_cloud

    try:
        cloud = load_point_cloud(
            path, labels=params.labels, max_points=settings.max_points, max_file_bytes=settings.max_upload_bytes,
            units=params.units, max_nifti_bytes=settings.max_nifti_bytes,
        )
        _check_extent(cloud.points, params.units, settings)
        return cloud
    except ProblemError:
        raise
    except RibPullInputError as exc:
        raise ProblemError(INPUT_ERROR_STATUS.get(exc.code, 422), exc.code, exc.message) from None
    except MemoryError:
        raise ProblemError(413, "too_large", "the file needs more memory than this server has") from None
    except Exception as exc:
        log.exception("loader failed on %s", path.name)  # noqa: the detail below names no path
        raise ProblemError(422, "parse_error", f"could not read the file: {type(exc).__name__}") from None


def _check_extent(points, units: str, settings: Settings) -> None:
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


def _clean_stale_uploads(settings: Settings, older_than_s: float = 3600) -> None:
    try:
        now = time.time()
        for d in settings.uploads_dir.iterdir():
            if now - d.stat().st_mtime > older_than_s:
                rmtree_quiet(d)
    except OSError:
        pass


app = create_app()
