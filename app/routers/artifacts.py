"""GET /v1/jobs/{id}/artifacts/{name}: one output file (Range requests supported)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path
from fastapi.responses import FileResponse

from ..deps import JobIdPath, OwnerDep, SessionsDep, SettingsDep, read_job
from ..problems import ProblemError
from ..storage import ARTIFACT_MEDIA_TYPES, artifact_store, media_type
from . import problems

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

ARTIFACT_NAMES = tuple(ARTIFACT_MEDIA_TYPES)  # == ribpull_core.pipeline.ARTIFACT_NAMES (a test checks)


@router.get(
    "/{job_id}/artifacts/{name}",
    response_class=FileResponse,
    responses={
        200: {
            "description": "The file. Media types: " + ", ".join(
                f"{n} {t}" for n, t in ARTIFACT_MEDIA_TYPES.items()),
            "content": {t: {"schema": {"type": "string", "format": "binary"}}
                        for t in sorted(set(ARTIFACT_MEDIA_TYPES.values()))},
        },
        **problems(400, 401, 404, 410, 416),
    },
    summary="Download one artifact",
)
def get_artifact(
    job_id: JobIdPath,
    name: Annotated[str, Path(max_length=64, description="One of: " + ", ".join(ARTIFACT_NAMES))],
    owner: OwnerDep,
    settings: SettingsDep,
    sm: SessionsDep,
):
    if name not in ARTIFACT_MEDIA_TYPES:
        raise ProblemError(404, "unknown_artifact",
                           f"'{name[:64]}' is not an artifact name; names: {', '.join(ARTIFACT_NAMES)}")
    job = read_job(sm, job_id, owner)
    if job.artifacts_deleted:
        raise ProblemError(410, "artifacts_deleted", "this job's files were deleted")
    if job.status != "succeeded":
        raise ProblemError(404, "artifact_not_found", f"job is {job.status}; artifacts exist once it succeeded")
    path = artifact_store(settings).local_dir(job_id, job.artifacts_ref) / name
    if name not in (job.artifacts or []) or not path.is_file():
        raise ProblemError(404, "artifact_not_found", f"this job did not produce {name}")
    return FileResponse(path, media_type=media_type(name), filename=f"{name}")
