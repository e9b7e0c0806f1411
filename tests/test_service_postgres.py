"""The service's end-to-end flows against a real PostgreSQL job store.

The flows are test_service_e2e.py's own tests, imported and collected here again with `service`
overridden by a stack (tests/servicekit.py) whose RIBPULL_DATABASE_URL is a fresh database in a
throw-away cluster (tests/pgcluster.py): submit, poll, download, signed webhook, idempotency, key
isolation, cancel running and queued jobs, API restart, pagination, delete. The worker-kill flow runs
on Postgres with several workers in test_service_scaleout.py; the field query (files only, the
database is not involved beyond the job lookup) is not repeated. test_jobs_live_in_postgres then looks
at the rows in Postgres itself.
"""

from __future__ import annotations

import pytest
import sqlalchemy as sa
import test_service_e2e as e2e
from servicekit import Stack, make_sample

from app import migrate

pytestmark = pytest.mark.service

# test_service_e2e.py's flows, in its order (they share its STATE: the smoke job comes first)
receiver = e2e.receiver
test_smoke_job_end_to_end = e2e.test_smoke_job_end_to_end
test_idempotency_key = e2e.test_idempotency_key
test_keys_isolate_jobs = e2e.test_keys_isolate_jobs
test_webhook_signed_and_retried = e2e.test_webhook_signed_and_retried
test_cancel_running_job = e2e.test_cancel_running_job
test_cancel_queued_job = e2e.test_cancel_queued_job
test_api_restart_keeps_jobs_and_artifacts = e2e.test_api_restart_keeps_jobs_and_artifacts
test_list_pagination_and_filter = e2e.test_list_pagination_and_filter


@pytest.fixture(scope="module")
def service(tmp_path_factory, postgres):
    """Redis + worker + API with the job store in Postgres (a bare postgresql:// URL, as users write it)."""
    postgres.create_database("e2e")
    stack = Stack(tmp_path_factory.mktemp("service-pg"), database_url=postgres.url("e2e", "postgresql"))
    yield from stack.serve()


@pytest.fixture(scope="module")
def smoke_params():
    """A lighter smoke job than test_service_e2e.py's (the backend is under test here, not the fit)."""
    return {"preset": "smoke", "iterations": 60, "resolution": 48, "preview": False}


@pytest.fixture(scope="module")
def sample_ply(tmp_path_factory):
    """A smaller phantom (6k points) for the same reason."""
    return make_sample(tmp_path_factory.mktemp("sample-pg"), n_points=6000)


def test_jobs_live_in_postgres(service, postgres):
    """Every job the API lists is a row in Postgres (none in a SQLite file), at the head revision."""
    eng = sa.create_engine(postgres.url("e2e"), poolclass=sa.pool.NullPool)
    try:
        with eng.connect() as conn:
            rows = {r.id: r for r in conn.execute(sa.text(
                "SELECT id, status, attempts, artifacts_ref, artifacts_deleted FROM jobs"))}
            version = conn.execute(sa.text("SELECT version_num FROM alembic_version")).scalar_one()
    finally:
        eng.dispose()
    assert version == migrate.head_revision()
    listed = service.client().get("/v1/jobs", params={"limit": 100}).json()["items"]
    assert listed and {j["id"] for j in listed} <= set(rows)
    for j in listed:
        assert rows[j["id"]].status == j["status"] and rows[j["id"]].attempts == j["attempts"]
    succeeded = [r for r in rows.values() if r.status == "succeeded"]
    assert succeeded and all(r.artifacts_ref for r in succeeded)  # published under the winning attempt
    assert not (service.root / "storage" / "ribpull.db").exists()


test_delete_finished_job_removes_files = e2e.test_delete_finished_job_removes_files  # last: it deletes the smoke job's files
