"""Fast static checks: the OpenAPI file, Docker files, Makefile and settings agree with the code."""

from __future__ import annotations

import importlib
import json
import re
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))

from app.jobs import QUEUE
from app.settings import Settings, env_var_names
from app.storage import ARTIFACT_MEDIA_TYPES


def test_openapi_file_matches_app():
    import export_openapi

    committed = json.loads((ROOT / "openapi" / "openapi.json").read_text())
    current = json.loads(export_openapi.render())
    assert committed == current, "openapi/openapi.json is stale: run `make openapi`"


def test_openapi_documents_the_contract():
    doc = json.loads((ROOT / "openapi" / "openapi.json").read_text())
    paths = doc["paths"]
    for p in ("/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/artifacts/{name}", "/v1/jobs/{job_id}/query",
              "/healthz", "/readyz"):
        assert p in paths
    body = paths["/v1/jobs"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert body["required"] == ["file"] and body["properties"]["file"]["format"] == "binary"
    assert "JobParams" in doc["components"]["schemas"] and "Problem" in doc["components"]["schemas"]
    params = doc["components"]["schemas"]["JobParams"]["properties"]
    assert params["iterations"]["anyOf"][0]["maximum"] == 100_000
    assert "application/problem+json" in paths["/v1/jobs"]["post"]["responses"]["422"]["content"]


def test_api_enums_match_the_core():
    from app.schemas import METHODS, PRESETS
    from ribpull_core.methods import METHOD_CLASSES, RUN_PRESETS

    assert set(PRESETS) == set(RUN_PRESETS)
    assert set(METHODS) == set(METHOD_CLASSES)


def test_every_artifact_has_a_media_type():
    from ribpull_core.pipeline import ARTIFACT_NAMES

    assert set(ARTIFACT_MEDIA_TYPES) == set(ARTIFACT_NAMES)


def test_settings_read_documented_env_vars(monkeypatch):
    monkeypatch.setenv("DATABASE_URL", "postgres://u:p@db/x")
    monkeypatch.setenv("PORT", "9123")
    monkeypatch.setenv("RIBPULL_API_KEYS", "a, b ,")
    monkeypatch.setenv("RIBPULL_MAX_UPLOAD_MB", "3")
    s = Settings()
    assert s.db_url == "postgresql+psycopg2://u:p@db/x" and s.port == 9123
    assert len(s.key_hashes) == 2 and s.max_upload_bytes == 3 * 1024 * 1024
    monkeypatch.setenv("RIBPULL_DATABASE_URL", "sqlite:////tmp/x.db")
    assert Settings().db_url == "sqlite:////tmp/x.db"
    names = env_var_names()
    for n in ("RIBPULL_REDIS_URL", "RIBPULL_STORAGE_DIR", "RIBPULL_MAX_UPLOAD_MB", "RIBPULL_API_KEYS",
              "RIBPULL_WEBHOOK_SECRET", "RIBPULL_JOB_TIMEOUT_S", "RIBPULL_TORCH_THREADS", "PORT", "DATABASE_URL"):
        assert n in names
    doc = (ROOT / "docs" / "service.md").read_text()
    for n in sorted(names):
        assert f"`{n}`" in doc, f"{n} is not documented in docs/service.md"


def test_webhook_signature_matches_standard_webhooks_vector():
    from worker.webhooks import sign, verify

    # the reference example of the Standard Webhooks specification
    sig = sign("whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw", "msg_p5jXN8AQM9LWM0D4loKWxJek", 1614265330,
               b'{"test": 2432232314}')
    assert sig == "v1,g0hM9SsE+OTPJTGt/tmIKtSyZlE3uFJELVlNIOLJ1OE="
    assert not verify("whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw", {"webhook-id": "x", "webhook-timestamp": "1",
                                                                  "webhook-signature": sig}, b"{}")


def test_celery_settings_for_long_jobs():
    from worker.celery_app import celery_app

    conf = celery_app.conf
    assert conf.task_acks_late is True and conf.task_reject_on_worker_lost is True
    assert conf.worker_prefetch_multiplier == 1
    s = Settings()
    assert conf.broker_transport_options["visibility_timeout"] >= s.job_timeout_s
    importlib.import_module("worker.tasks")
    assert "ribpull.run_job" in celery_app.tasks and "ribpull.deliver_webhook" in celery_app.tasks


def test_worker_parent_does_not_import_torch():
    import subprocess

    code = "import sys, worker.celery_app; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


# --------------------------------------------------------------------------------------------------
# Docker
# --------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def compose():
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _cmd(service) -> list[str]:
    c = service.get("command")
    return c if isinstance(c, list) else c.split()


def test_compose_services_and_healthchecks(compose):
    svcs = compose["services"]
    assert {"redis", "postgres", "api", "worker"} <= set(svcs)
    assert "redis-cli" in svcs["redis"]["healthcheck"]["test"] and "ping" in svcs["redis"]["healthcheck"]["test"]
    assert "pg_isready" in " ".join(svcs["postgres"]["healthcheck"]["test"])
    assert "/healthz" in " ".join(svcs["api"]["healthcheck"]["test"])
    for name in ("api", "worker"):
        vols = svcs[name]["volumes"]
        assert any(v.startswith("artifacts:") for v in vols), "api and worker must share the artifacts volume"
        assert svcs[name]["depends_on"]["redis"]["condition"] == "service_healthy"
        assert svcs[name]["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert "artifacts" in compose["volumes"]


def test_compose_commands_reference_real_modules(compose):
    svcs = compose["services"]
    api = _cmd(svcs["api"])
    target = api[api.index("uvicorn") + 1]
    mod, _, attr = target.partition(":")
    assert hasattr(importlib.import_module(mod), attr)
    for name in [n for n in svcs if n.startswith("worker")]:
        w = _cmd(svcs[name])
        mod = w[w.index("-A") + 1]
        m = importlib.import_module(mod)
        from celery import Celery

        assert isinstance(m.app, Celery)
        assert w[w.index("-Q") + 1] == QUEUE


def test_compose_ports_and_env_match_settings(compose):
    svcs = compose["services"]
    api = _cmd(svcs["api"])
    port = api[api.index("--port") + 1]
    assert any(str(p).split(":")[-1] == port for p in svcs["api"]["ports"])
    assert f":{port}/healthz" in " ".join(svcs["api"]["healthcheck"]["test"])
    names = env_var_names()
    for svc in ("api", "worker"):
        env = svcs[svc]["environment"]
        unknown = [k for k in env if k not in names]
        assert not unknown, f"{svc}: env vars the settings do not read: {unknown}"
        assert env.get("PORT", port) == port
        assert env["RIBPULL_REDIS_URL"].startswith("redis://redis:")
        assert env["RIBPULL_DATABASE_URL"].startswith("postgresql+psycopg2://")
        assert "@postgres:" in env["RIBPULL_DATABASE_URL"]
    pg = svcs["postgres"]["environment"]
    assert f"{pg['POSTGRES_USER']}:{pg['POSTGRES_PASSWORD']}@postgres:5432/{pg['POSTGRES_DB']}" in \
        svcs["api"]["environment"]["RIBPULL_DATABASE_URL"]
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert "psycopg2-binary" in pyproject


def test_dockerfile_agrees_with_code(compose):
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^ARG BASE_IMAGE=python:3\.11-slim$", text, re.MULTILINE)
    assert re.search(r"^FROM \$\{BASE_IMAGE\}$", text, re.MULTILINE)
    assert "download.pytorch.org/whl/cpu" in text  # CPU torch by default
    expose = re.search(r"^EXPOSE (\d+)$", text, re.MULTILINE).group(1)
    api = _cmd(compose["services"]["api"])
    assert expose == api[api.index("--port") + 1]
    assert "app.main:app" in text
    for src in re.findall(r"^COPY (\S+) ", text, re.MULTILINE):
        if src not in ("README.md",):  # README.md is written from docs/service.md
            assert (ROOT / src).exists(), src
    names = env_var_names()
    for var in re.findall(r"\b(RIBPULL_[A-Z_]+|PORT)=", text):
        assert var in names, var
    ignore = (ROOT / ".dockerignore").read_text().split()
    assert ".venv" in ignore and ".git" in ignore
    # numba's kernels compiled into the image, in a cache the unprivileged runtime user owns
    cache = re.search(r"NUMBA_CACHE_DIR=(\S+)", text).group(1)
    warm = re.search(r"^RUN .*ribpull warmup.*$", text, re.MULTILINE).group(0)
    assert f"chown -R ribpull {cache}" in warm and text.index("pip install .") < text.index(warm)


# --------------------------------------------------------------------------------------------------
# Make / CI
# --------------------------------------------------------------------------------------------------

def test_makefile_and_ci():
    mk = (ROOT / "Makefile").read_text()
    for target in ("install:", "run: install", "test: install", "openapi:", "sample:"):
        assert target in mk
    assert "scripts/serve.py" in mk and "pyproject.toml" in mk and "pip install -e '.[dev]'" in mk
    assert mk.index("pip install -e '.[dev]'") < mk.index("ribpull warmup")  # kernels compiled at install
    from ribpull_core.cli import build_parser

    assert build_parser().parse_args(["warmup"]).func.__name__ == "cmd_warmup"
    ci = (ROOT / ".ci" / "run").read_text()
    assert ci.startswith("#!/usr/bin/env bash\nset -euo pipefail\n") and "make test" in ci


def test_serve_script_finds_redis():
    from app.launcher import find_redis_server

    assert Path(find_redis_server()).is_file()
