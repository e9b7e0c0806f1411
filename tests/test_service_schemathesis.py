"""Property-based API tests (schemathesis over the app's OpenAPI schema, in-process ASGI):
whatever the generated request, the answer is never a 5xx. A real redis-server (started by the
module fixture) backs the queue so a valid upload can be queued (nobody consumes that queue)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from app import launcher
from app.main import create_app
from app.settings import Settings

pytestmark = pytest.mark.service

_ROOT = Path(tempfile.mkdtemp(prefix="ribpull-schemathesis-"))
SETTINGS = Settings(
    storage_dir=_ROOT / "storage", redis_url="redis://127.0.0.1:1/0", api_keys="",
    max_upload_mb=2, max_query_points=1000, readyz_require_worker=False,
)
APP = create_app(SETTINGS)
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)


@pytest.fixture(scope="module", autouse=True)
def _redis():
    port = launcher.free_port()
    redis = launcher.start_redis(port, _ROOT / "redis")
    SETTINGS.redis_url = f"redis://127.0.0.1:{port}/0"  # the app builds its clients lazily
    try:
        yield
    finally:
        launcher.stop(redis)
        shutil.rmtree(_ROOT, ignore_errors=True)


@schema.parametrize()
@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
def test_no_server_errors(case):
    case.call_and_validate(checks=[not_a_server_error])
