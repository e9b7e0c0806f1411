"""RibPull HTTP API (FastAPI): upload a ribcage, follow the job, download artifacts, query the field.

Run: `uvicorn app.main:app --http app.httpserver:HardenedH11Protocol` (or `make run`). Everything is
configured by environment variables (app/settings.py); the job store is shared with the Celery worker
(worker/celery_app.py), and every job-status change goes through app/state.py.

Layout: routers in app/routers/ (health, jobs, artifacts, query; web: the page at `/`, files in app/web/)
with typed dependencies (app/deps.py);
middleware (nosniff, problem+json for every error, body timeout, body budgets) in app/middleware.py.
"""

from __future__ import annotations

import logging
import time
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from . import __version__
from .db import make_engine
from .middleware import BodyLimit, BodyTimeout, Hardening, query_body_budget
from .problems import install_handlers
from .query import FieldCache
from .routers import artifacts, health, jobs, query, web
from .routers.artifacts import ARTIFACT_NAMES  # noqa: F401  (re-exported: == ribpull_core.pipeline.ARTIFACT_NAMES)
from .schemas import DicomwebJobIn, JobParams, Problem
from .settings import Settings, get_settings
from .storage import ensure_dirs, rmtree_quiet

log = logging.getLogger("ribpull.api")


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
    for r in (health.router, jobs.router, artifacts.router, query.router, web.router):
        app.include_router(r)

    def custom_openapi():
        """Add the schemas referenced from the hand-written multipart body and the problem responses."""
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(
            title=app.title, version=app.version, summary=app.summary, description=app.description,
            routes=app.routes,
        )
        comps = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in (JobParams, DicomwebJobIn, Problem):
            js = model.model_json_schema(ref_template="#/components/schemas/{model}")
            for name, sub in js.pop("$defs", {}).items():
                comps.setdefault(name, sub)
            comps[model.__name__] = js
        app.openapi_schema = schema
        return schema

    app.openapi = custom_openapi
    return app


def _clean_stale_uploads(settings: Settings, older_than_s: float = 3600) -> None:
    try:
        now = time.time()
        for d in settings.uploads_dir.iterdir():
            if now - d.stat().st_mtime > older_than_s:
                rmtree_quiet(d)
    except OSError:
        pass


app = create_app()
