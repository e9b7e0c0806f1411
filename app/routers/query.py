"""POST /v1/jobs/{id}/query: occupancy, U and SDF of a finished job's field at points (mm)."""

from __future__ import annotations

from fastapi import APIRouter

from ..deps import FieldCacheDep, JobIdPath, OwnerDep, SessionsDep, SettingsDep, read_job
from ..problems import ProblemError
from ..query import run_query
from ..schemas import QueryIn, QueryOut
from ..storage import artifact_store
from . import problems

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])


@router.post(
    "/{job_id}/query",
    response_model=QueryOut,
    responses=problems(401, 404, 408, 409, 413, 422),
    summary="Occupancy, U and SDF (mm) of the fitted field at points in mm",
)
def query_job(job_id: JobIdPath, body: QueryIn, owner: OwnerDep, settings: SettingsDep, sm: SessionsDep,
              cache: FieldCacheDep):
    if len(body.points_mm) > settings.max_query_points:
        raise ProblemError(422, "too_many_points",
                           f"{len(body.points_mm)} points; the limit is {settings.max_query_points} per request "
                           "(RIBPULL_MAX_QUERY_POINTS)")
    job = read_job(sm, job_id, owner)
    if job.status != "succeeded":
        raise ProblemError(409, "job_not_succeeded", f"job is {job.status}; query it once it has succeeded")
    if job.artifacts_deleted:
        raise ProblemError(409, "artifacts_deleted", "this job's files were deleted")
    adir = artifact_store(settings).local_dir(job_id, job.artifacts_ref)
    if not (adir / "model.safetensors").is_file():
        raise ProblemError(409, "no_model", "this job has no stored weights")
    return run_query(cache, job_id, adir, body.points_mm)
