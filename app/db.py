"""The durable job store (SQLAlchemy 2): the ONE authoritative record of every job.

Shared by the API and the worker. SQLite (WAL mode, busy timeout) by default, Postgres through
DATABASE_URL. The schema is owned by Alembic (app/migrate.py, revisions in app/migrations/versions/):
a change to these models needs a revision (`ribpull-db revision -m ... --autogenerate`). State transitions that can race (claim, cancel, finish, sweep) are single conditional
UPDATE statements, so they are atomic on both databases and never need row locks.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from datetime import datetime, timezone
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    Integer,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    create_engine,
    event,
    select,
    text,
)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker

from .settings import Settings

STATUSES = ("queued", "running", "succeeded", "failed", "canceled")
TERMINAL = ("succeeded", "failed", "canceled")


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC datetimes on every backend (SQLite stores naive values)."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if value is None:
            return None
        if value.tzinfo is None:
            value = value.replace(tzinfo=timezone.utc)
        return value.astimezone(timezone.utc).replace(tzinfo=None)

    def process_result_value(self, value, dialect):
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=timezone.utc)
        return value.astimezone(timezone.utc)


class Base(DeclarativeBase):
    pass


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (UniqueConstraint("owner", "idempotency_key", name="uq_jobs_owner_idem"),)

    seq: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)  # list order / cursor
    id: Mapped[str] = mapped_column(String(32), unique=True, index=True)
    owner: Mapped[str] = mapped_column(String(64), index=True, default="")  # sha256(api key) or ""
    status: Mapped[str] = mapped_column(String(16), index=True, default="queued")

    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    input_name: Mapped[str] = mapped_column(String(255), default="")
    input_format: Mapped[str] = mapped_column(String(16), default="")
    input_bytes: Mapped[int] = mapped_column(Integer, default=0)
    input_sha256: Mapped[str] = mapped_column(String(64), default="")
    input_points: Mapped[int] = mapped_column(Integer, default=0)

    idempotency_key: Mapped[str | None] = mapped_column(String(255), nullable=True)
    fingerprint: Mapped[str] = mapped_column(String(64), default="")

    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True, index=True)

    stage: Mapped[str | None] = mapped_column(String(32), nullable=True)
    fraction: Mapped[float] = mapped_column(Float, default=0.0)
    iteration: Mapped[int | None] = mapped_column(Integer, nullable=True)
    iterations: Mapped[int | None] = mapped_column(Integer, nullable=True)
    loss: Mapped[float | None] = mapped_column(Float, nullable=True)
    message: Mapped[str] = mapped_column(Text, default="")

    error_code: Mapped[str | None] = mapped_column(String(64), nullable=True)
    error_message: Mapped[str | None] = mapped_column(Text, nullable=True)

    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    claim_token: Mapped[str | None] = mapped_column(String(32), nullable=True)
    worker: Mapped[str | None] = mapped_column(String(255), nullable=True)

    artifacts: Mapped[list[str]] = mapped_column(JSON, default=list)
    artifacts_deleted: Mapped[bool] = mapped_column(Boolean, default=False)
    # which attempt's published outputs the job's artifacts are (app/storage.ArtifactStore key), set in
    # the same UPDATE that marks it succeeded; None = jobs/<id>/artifacts/ (jobs from before revision 0002)
    artifacts_ref: Mapped[str | None] = mapped_column(String(64), nullable=True)
    metrics: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)

    webhook_url: Mapped[str | None] = mapped_column(Text, nullable=True)
    webhook_status: Mapped[str | None] = mapped_column(String(16), nullable=True)  # pending|delivered|failed
    webhook_attempts: Mapped[int] = mapped_column(Integer, default=0)
    webhook_error: Mapped[str | None] = mapped_column(Text, nullable=True)

    # a job whose input is a DICOMweb series (revision 0003): {"dicomweb": {url, study_uid, series_uid}}
    source: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    deliver_url: Mapped[str | None] = mapped_column(Text, nullable=True)  # STOW-RS base URL of the results
    delivery_status: Mapped[str | None] = mapped_column(String(16), nullable=True)  # pending|delivered|failed
    delivery_attempts: Mapped[int] = mapped_column(Integer, default=0)
    delivery_error: Mapped[str | None] = mapped_column(Text, nullable=True)


# ------------------------------------------------------------------------------------------------
# engines and sessions
# ------------------------------------------------------------------------------------------------

_engines: dict[str, Engine] = {}
_lock = threading.Lock()


def _set_wal_mode(cursor, wait_s: float = 30.0) -> None:
    """PRAGMA journal_mode=WAL, retried: switching needs an exclusive lock, and while another process
    holds a write transaction (a worker creating the schema as the API starts) SQLite answers
    "database is locked" at once instead of waiting in the busy handler."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            cursor.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def make_engine(settings: Settings) -> Engine:
    url = settings.db_url
    with _lock:
        eng = _engines.get(url)
        if eng is not None:
            return eng
        if url.startswith("sqlite"):
            settings.storage_path.mkdir(parents=True, exist_ok=True)
            eng = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})

            @event.listens_for(eng, "connect")
            def _sqlite_pragmas(dbapi_conn, _record):
                cur = dbapi_conn.cursor()
                cur.execute("PRAGMA busy_timeout=30000")
                _set_wal_mode(cur)
                cur.execute("PRAGMA synchronous=NORMAL")
                cur.close()
        else:
            eng = create_engine(url, pool_pre_ping=True, pool_size=5, max_overflow=10)
        # Alembic owns the schema: an empty database is created by the migrations, one at head is
        # used, anything else raises migrate.SchemaError naming the command to run
        from .migrate import ensure_schema

        try:
            ensure_schema(eng)
        except Exception:
            eng.dispose()
            raise
        _engines[url] = eng
        return eng


def make_sessionmaker(settings: Settings) -> sessionmaker:
    return sessionmaker(bind=make_engine(settings), expire_on_commit=False)


def db_ping(engine: Engine) -> None:
    with engine.connect() as conn:
        conn.execute(text("SELECT 1"))


def get_job(session, job_id: str, owner: str | None = None) -> Job | None:
    q = select(Job).where(Job.id == job_id)
    if owner is not None:
        q = q.where(Job.owner == owner)
    return session.scalars(q).first()
