"""GET /healthz (liveness) and GET /readyz (database, Redis, storage, a worker heartbeat)."""

from __future__ import annotations

import tempfile

from fastapi import APIRouter

from ..db import db_ping, make_engine
from ..deps import RedisDep, SettingsDep
from ..jobs import WORKER_KEY_PREFIX
from ..problems import problem_response
from ..schemas import Health, Ready
from ..storage import ensure_dirs
from . import problems

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers")
def healthz():
    return {"status": "ok"}


@router.get(
    "/readyz", response_model=Ready, responses=problems(503),
    summary="Readiness: database, Redis and storage reachable, a worker heartbeat seen",
)
def readyz(settings: SettingsDep, r: RedisDep):
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
