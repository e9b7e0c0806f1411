"""Typed FastAPI dependencies shared by the routers (`Annotated[..., Depends(...)]` aliases).

The per-process singletons (session factory, Celery producer, Redis client, field cache) live on
`app.state` and are created on first use, so importing the app never connects to anything.
"""

from __future__ import annotations

from typing import Annotated

import redis
from celery import Celery
from fastapi import Depends, Path, Request
from sqlalchemy.orm import sessionmaker

from .auth import current_owner
from .db import Job, get_job, make_sessionmaker
from .jobs import celery_client
from .problems import ProblemError
from .query import FieldCache
from .settings import Settings
from .storage import JOB_ID_RE, ensure_dirs


def get_app_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_sessions(request: Request) -> sessionmaker:
    st = request.app.state
    if st._sm is None:
        ensure_dirs(st.settings)
        st._sm = make_sessionmaker(st.settings)
    return st._sm


def get_celery(request: Request) -> Celery:
    st = request.app.state
    if st._celery is None:
        st._celery = celery_client(st.settings)
    return st._celery


def get_redis(request: Request) -> redis.Redis:
    st = request.app.state
    if st._redis is None:
        st._redis = redis.Redis.from_url(
            st.settings.redis_url, socket_timeout=2, socket_connect_timeout=2, health_check_interval=10
        )
    return st._redis


def get_field_cache(request: Request) -> FieldCache:
    return request.app.state.field_cache


SettingsDep = Annotated[Settings, Depends(get_app_settings)]
SessionsDep = Annotated[sessionmaker, Depends(get_sessions)]
CeleryDep = Annotated[Celery, Depends(get_celery)]
RedisDep = Annotated[redis.Redis, Depends(get_redis)]
FieldCacheDep = Annotated[FieldCache, Depends(get_field_cache)]
OwnerDep = Annotated[str, Depends(current_owner)]
JobIdPath = Annotated[str, Path(description="Job id (32 lowercase hex characters).", max_length=64)]


def read_job(sm: sessionmaker, job_id: str, owner: str) -> Job:
    """The caller's job, or 404 (also for another key's job: ids are not disclosed across keys)."""
    if not JOB_ID_RE.match(job_id):
        raise ProblemError(404, "job_not_found", f"no job with id '{job_id[:64]}'")
    with sm() as s:
        job = get_job(s, job_id, owner)
    if job is None:
        raise ProblemError(404, "job_not_found", f"no job with id '{job_id}'")
    return job


def owned_job(job_id: JobIdPath, owner: OwnerDep, sm: SessionsDep) -> Job:
    return read_job(sm, job_id, owner)


JobDep = Annotated[Job, Depends(owned_job)]
