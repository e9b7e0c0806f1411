"""Alembic owns the job store's schema (app/migrate.py), on SQLite and on a real PostgreSQL.

* the migrations build exactly app/db.py's models (a model change without a revision fails here);
* a database at the baseline (today's schema before migrations) with jobs in it is upgraded to head
  by `ribpull-db upgrade` and loses nothing: every row, every column, the old artifact directory;
* the pre-Alembic table (no alembic_version) is recognised and adopted;
* the API and the worker refuse to start against an old schema with a message naming the command;
  several processes creating an empty database at once do not race; `make run` upgrades its SQLite.
"""

from __future__ import annotations

import subprocess
import sys
import uuid
from datetime import datetime, timedelta
from pathlib import Path

import pytest
import sqlalchemy as sa
from servicekit import ROOT, Stack

from app import launcher, migrate
from app.settings import Settings

pytestmark = pytest.mark.service

BASELINE_ONLY = ("artifacts_ref",)  # columns added after the baseline (they start NULL on old rows)


@pytest.fixture(params=["sqlite", "postgres"])
def db_url(request, tmp_path):
    """An empty database: a SQLite file, or a fresh database in the session's Postgres cluster."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'ribpull.db'}"
    pg = request.getfixturevalue("postgres")
    return pg.create_database("m_" + uuid.uuid4().hex[:10])


def _engine(url: str) -> sa.Engine:
    return sa.create_engine(url, poolclass=sa.pool.NullPool)


def _revision(url: str) -> str | None:
    eng = _engine(url)
    try:
        with eng.connect() as conn:
            return migrate.schema_state(conn).revision
    finally:
        eng.dispose()


def _cli(*args: str, url: str, storage: Path | None = None) -> subprocess.CompletedProcess:
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "RIBPULL_DATABASE_URL": url,
           "RIBPULL_STORAGE_DIR": str(storage or ROOT / "var" / "storage")}
    return subprocess.run([sys.executable, "-m", "app.migrate", *args], env=env, capture_output=True, text=True,
                          timeout=120, check=False, cwd=ROOT)


def _baseline_jobs(n: int) -> list[dict]:
    """Rows as the baseline-era code wrote them: every status, JSON params/artifacts/metrics, times."""
    t0 = datetime(2026, 11, 1, 12, 0, 0)
    statuses = ["queued", "running", "succeeded", "failed", "canceled"]
    rows = []
    for i in range(n):
        st = statuses[i % len(statuses)]
        rows.append({
            "id": uuid.uuid4().hex, "owner": "a" * 64 if i % 2 else "", "status": st,
            "params": {"preset": "smoke", "seed": i, "labels": [1, 2, 3]},
            "input_name": f"scan-{i}.ply", "input_format": "ply", "input_bytes": 1000 + i,
            "input_sha256": f"{i:064x}", "input_points": 20_000 + i,
            "idempotency_key": f"idem-{i}" if i % 3 == 0 else None, "fingerprint": f"{i:064x}",
            "created_at": t0 + timedelta(minutes=i), "updated_at": t0 + timedelta(minutes=i, seconds=5),
            "started_at": t0 + timedelta(minutes=i, seconds=1) if st != "queued" else None,
            "finished_at": t0 + timedelta(minutes=i, seconds=9) if st in ("succeeded", "failed", "canceled") else None,
            "heartbeat_at": t0 + timedelta(minutes=i, seconds=4) if st == "running" else None,
            "stage": "done" if st == "succeeded" else ("fit" if st == "running" else None),
            "fraction": 1.0 if st == "succeeded" else 0.25 * (i % 4), "iteration": 100 + i, "iterations": 250,
            "loss": 0.125 + i / 1000, "message": f"message {i} \u00b5m ok",
            "error_code": "degenerate" if st == "failed" else None,
            "error_message": "the points lie on one plane" if st == "failed" else None,
            "cancel_requested": st == "canceled", "attempts": 1 + i % 3,
            "claim_token": uuid.uuid4().hex if st != "queued" else None,
            "worker": f"host-{i % 2}:{1000 + i}" if st != "queued" else None,
            "artifacts": ["mesh.ply", "metrics.json"] if st == "succeeded" else [],
            "artifacts_deleted": False, "metrics": {"chamfer_l1_mm": 0.3 + i / 100} if st == "succeeded" else None,
            "webhook_url": "https://hooks.example.org/x" if i % 4 == 0 else None,
            "webhook_status": "delivered" if i % 4 == 0 else None, "webhook_attempts": 1 if i % 4 == 0 else 0,
            "webhook_error": None,
        })
    return rows


def _insert(url: str, rows: list[dict]) -> None:
    eng = _engine(url)
    try:
        jobs = sa.Table("jobs", sa.MetaData(), autoload_with=eng)  # the table as the database has it
        with eng.begin() as conn:
            conn.execute(jobs.insert(), rows)
    finally:
        eng.dispose()


def _read(url: str) -> dict[str, dict]:
    eng = _engine(url)
    try:
        jobs = sa.Table("jobs", sa.MetaData(), autoload_with=eng)
        with eng.connect() as conn:
            return {r["id"]: dict(r) for r in conn.execute(sa.select(jobs)).mappings()}
    finally:
        eng.dispose()


def _same(before: dict, after: dict) -> None:
    assert set(after) == set(before), "jobs were lost or added by the upgrade"
    for jid, row in before.items():
        new = after[jid]
        for col, val in row.items():
            got = new[col]
            if isinstance(val, datetime) and isinstance(got, datetime):  # naive UTC either way
                val, got = val.replace(tzinfo=None), got.replace(tzinfo=None)
            assert got == val, (jid, col, val, got)
        for col in BASELINE_ONLY:
            assert new[col] is None, (jid, col)


def test_models_match_the_migrations(db_url):
    """Running every revision on an empty database yields exactly the models of app/db.py."""
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from app.db import Base

    before, after = migrate.upgrade(db_url)
    assert before is None and after == migrate.head_revision()
    eng = _engine(db_url)
    try:
        with eng.connect() as conn:
            diff = compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata)
    finally:
        eng.dispose()
    assert diff == [], f"app/db.py and app/migrations differ (add a revision: ribpull-db revision -m ...): {diff}"
    assert migrate.upgrade(db_url) == (after, after)  # a second upgrade is a no-op


def test_baseline_database_with_jobs_upgrades_to_head_and_loses_none(db_url, tmp_path):
    migrate.upgrade(db_url, migrate.BASELINE)
    rows = _baseline_jobs(25)
    _insert(db_url, rows)
    before = _read(db_url)
    assert len(before) == 25

    # the API (and the worker: test_processes_refuse_an_old_schema) refuse it, naming the command
    with pytest.raises(migrate.SchemaError, match="ribpull-db upgrade"):
        migrate.ensure_schema_at(db_url)
    out = _cli("check", url=db_url, storage=tmp_path)
    assert out.returncode == 1 and "ribpull-db upgrade" in out.stderr, out

    if db_url.startswith("postgresql"):  # what a DBA would review first
        out = _cli("upgrade", "--sql", url=db_url, storage=tmp_path)
        assert out.returncode == 0 and "ALTER TABLE jobs ADD COLUMN artifacts_ref" in out.stdout, out
        assert _revision(db_url) == migrate.BASELINE  # printed, not run
    out = _cli("upgrade", url=db_url, storage=tmp_path)  # the real CLI (`make migrate`)
    assert out.returncode == 0, out.stderr
    assert f"{migrate.BASELINE} -> {migrate.head_revision()}" in out.stdout, out.stdout
    assert _revision(db_url) == migrate.head_revision()
    _same(before, _read(db_url))
    assert _cli("check", url=db_url, storage=tmp_path).returncode == 0
    migrate.ensure_schema_at(db_url)


def test_upgraded_jobs_are_served_by_the_api(db_url, tmp_path):
    """A job finished before revision 0002 keeps its artifacts in jobs/<id>/artifacts/: still served."""
    from fastapi.testclient import TestClient

    from app.main import create_app

    migrate.upgrade(db_url, migrate.BASELINE)
    rows = [r for r in _baseline_jobs(5) if r["status"] == "succeeded"]
    rows[0]["owner"] = ""  # the anonymous owner: no API keys configured below
    _insert(db_url, rows)
    jid = rows[0]["id"]
    storage = tmp_path / "storage"
    adir = storage / "jobs" / jid / "artifacts"
    adir.mkdir(parents=True)
    (adir / "mesh.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    (adir / "metrics.json").write_text('{"chamfer_l1_mm": 0.3}')
    assert _cli("upgrade", url=db_url, storage=tmp_path).returncode == 0

    settings = Settings(storage_dir=storage, database_url=db_url, readyz_require_worker=False)
    with TestClient(create_app(settings)) as client:
        job = client.get(f"/v1/jobs/{jid}").json()
        assert job["status"] == "succeeded" and {a["name"] for a in job["artifacts"]} == {"mesh.ply", "metrics.json"}
        r = client.get(f"/v1/jobs/{jid}/artifacts/metrics.json")
        assert r.status_code == 200 and r.json() == {"chamfer_l1_mm": 0.3}


def test_pre_migration_table_is_adopted(db_url, tmp_path):
    """A database made by create_all before migrations existed (no alembic_version) is stamped at the
    baseline, then upgraded; its jobs survive."""
    migrate.upgrade(db_url, migrate.BASELINE)
    eng = _engine(db_url)
    with eng.begin() as conn:
        conn.execute(sa.text("DROP TABLE alembic_version"))
    eng.dispose()
    _insert(db_url, _baseline_jobs(7))
    before = _read(db_url)
    with pytest.raises(migrate.SchemaError, match="before schema migrations existed"):
        migrate.ensure_schema_at(db_url)
    migrate.upgrade(db_url)
    assert _revision(db_url) == migrate.head_revision()
    _same(before, _read(db_url))


def test_unknown_revision_is_refused(tmp_path):
    url = f"sqlite:///{tmp_path / 'newer.db'}"
    migrate.upgrade(url)
    eng = _engine(url)
    with eng.begin() as conn:
        conn.execute(sa.text("UPDATE alembic_version SET version_num = '9999'"))
    eng.dispose()
    with pytest.raises(migrate.SchemaError, match="newer RibPull"):
        migrate.ensure_schema_at(url)
    with pytest.raises(migrate.SchemaError, match="newer RibPull"):
        migrate.upgrade(url)


def test_processes_refuse_an_old_schema(postgres, tmp_path):
    """The real worker and API processes exit at start-up against a database behind head, with the
    command to run in their output; after `ribpull-db upgrade` the whole stack starts."""
    url = postgres.create_database("old_" + uuid.uuid4().hex[:8])
    migrate.upgrade(url, migrate.BASELINE)
    stack = Stack(tmp_path, database_url=url)
    stack.redis = launcher.start_redis(stack.redis_port, tmp_path / "redis", log_path=stack.logs / "redis.log")
    try:
        worker = stack.start_worker()
        api = launcher.spawn(launcher.api_cmd("127.0.0.1", stack.api_port), env=stack.env,
                             log_path=stack.logs / "api-refused.log", cwd=ROOT)
        assert worker.wait(timeout=120) != 0
        assert api.wait(timeout=120) != 0
        for log in ("worker-1.log", "api-refused.log"):
            text = (stack.logs / log).read_text()
            assert f"is at schema revision {migrate.BASELINE}, this code needs {migrate.head_revision()}" in text, text
            assert "ribpull-db upgrade" in text
        assert _cli("upgrade", url=url, storage=tmp_path).returncode == 0
        stack.start_worker()
        stack.start_api()
        stack.wait_ready(timeout=120)
    finally:
        stack.stop()


def test_concurrent_first_start_creates_the_schema_once(postgres, tmp_path):
    """Four processes (API and workers starting together) against one empty database: one creates
    it under the advisory lock, the others wait and find it at head."""
    url = postgres.create_database("race_" + uuid.uuid4().hex[:8])
    code = "import sys; from app import migrate; migrate.ensure_schema_at(sys.argv[1]); print('ok')"
    procs = [subprocess.Popen([sys.executable, "-c", code, url], cwd=ROOT, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(4)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    assert sum("was empty: created the schema" in err for _out, err in outs) == 1, outs
    assert _revision(url) == migrate.head_revision()


def test_make_run_upgrades_its_own_sqlite(tmp_path, monkeypatch):
    """scripts/serve.py (make run): the embedded SQLite is upgraded; an external old database is
    left alone and refused with the command to run."""
    sys.path.insert(0, str(ROOT / "scripts"))
    import serve

    storage = tmp_path / "storage"
    storage.mkdir()
    own = f"sqlite:///{storage / 'ribpull.db'}"
    migrate.upgrade(own, migrate.BASELINE)
    _insert(own, _baseline_jobs(3))
    serve.prepare_database(Settings(storage_dir=storage, database_url=None))
    assert _revision(own) == migrate.head_revision() and len(_read(own)) == 3

    external = f"sqlite:///{tmp_path / 'external.db'}"
    migrate.upgrade(external, migrate.BASELINE)
    with pytest.raises(migrate.SchemaError, match="ribpull-db upgrade"):
        serve.prepare_database(Settings(storage_dir=storage, database_url=external))
    assert _revision(external) == migrate.BASELINE


def test_compose_migrates_before_api_and_workers():
    """docker-compose.yml: a `migrate` service runs `ribpull-db upgrade` (a console script of the
    package) against the same database, and every api/worker service waits for it to succeed."""
    import tomllib
    import yaml

    svcs = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["ribpull-db"] == "app.migrate:main"
    assert svcs["migrate"]["command"] == ["ribpull-db", "upgrade"]
    url = svcs["migrate"]["environment"]["RIBPULL_DATABASE_URL"]
    for name in [n for n in svcs if n == "api" or n.startswith("worker")]:
        assert svcs[name]["depends_on"]["migrate"]["condition"] == "service_completed_successfully", name
        assert svcs[name]["environment"]["RIBPULL_DATABASE_URL"] == url, name
