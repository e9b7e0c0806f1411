"""The job store's schema, owned by Alembic: revisions in app/migrations/versions/, run from here.

    ribpull-db upgrade [--sql]      bring the database of RIBPULL_DATABASE_URL to this code's head
                                    (`make migrate`); --sql prints the SQL instead of running it
    ribpull-db current              the database's revision and this code's head
    ribpull-db check                exit 0 when the database is at head, 1 (with the reason) otherwise
    ribpull-db revision -m "add x"  a new revision file on top of the head (--autogenerate: diffed
                                    against app/db.py's models on a throw-away SQLite database)

One policy, used by the API and the worker (`app.db.make_engine`) and by scripts/serve.py:

* an **empty** database (no tables) is created by running every revision; any process may do it,
  under a lock (a Postgres advisory lock, a file lock next to a SQLite file), so API and workers
  starting together against a fresh database do not race;
* a database **at head** is used as it is;
* a database **behind** (an older revision, or the pre-Alembic `jobs` table without
  `alembic_version`) or at a revision this code does not know is refused with `SchemaError`, whose
  message names the command to run. Only `ribpull-db upgrade` (and `make run` for its own embedded
  SQLite) changes a schema that holds data.
"""

from __future__ import annotations

import argparse
import fcntl
import logging
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine, inspect, pool
from sqlalchemy.engine import Connection, Engine

log = logging.getLogger("ribpull.migrate")
if logging.getLogger("alembic").level == logging.NOTSET:  # its per-connection INFO lines would flood the
    logging.getLogger("alembic").setLevel(logging.WARNING)  # API and worker logs; the CLI turns them on

MIGRATIONS_DIR = Path(__file__).resolve().parent / "migrations"
#: the revision equal to the schema app/db.py created with create_all before migrations existed
BASELINE = "0001"
#: what an operator runs to bring a database to this code's schema
UPGRADE_COMMAND = "ribpull-db upgrade (or `make migrate`), with the same RIBPULL_DATABASE_URL"
#: pg_advisory_xact_lock key serialising schema changes of one Postgres database (any constant)
PG_LOCK_KEY = 0x52_69_62_50  # "RibP"


class SchemaError(RuntimeError):
    """The database's schema is not the one this code needs; the message says what to run."""


@dataclass(frozen=True)
class SchemaState:
    """Where a database stands against this code: revision None = no alembic_version row."""

    revision: str | None
    head: str
    has_jobs_table: bool

    @property
    def status(self) -> str:
        """current | empty | legacy (pre-Alembic jobs table) | behind | unknown (newer code's revision)."""
        if self.revision == self.head:
            return "current"
        if self.revision is None:
            return "legacy" if self.has_jobs_table else "empty"
        if self.revision in _known_revisions():
            return "behind"
        return "unknown"

    def problem(self, url: str) -> str:
        """The operator-facing sentence for a database this code refuses."""
        where = _safe_url(url)
        if self.status == "legacy":
            return (f"the job database {where} was created before schema migrations existed (no "
                    f"alembic_version table); this code needs revision {self.head}: run {UPGRADE_COMMAND}")
        if self.status == "behind":
            return (f"the job database {where} is at schema revision {self.revision}, this code needs "
                    f"{self.head}: run {UPGRADE_COMMAND}")
        if self.status == "unknown":
            return (f"the job database {where} is at schema revision {self.revision}, which this code does "
                    f"not know (head {self.head}): it was upgraded by a newer RibPull; run that version")
        return f"the job database {where} is {self.status}"


def alembic_config(url: str) -> Config:
    """An Alembic Config for `url` without an alembic.ini (the environment ships in the package)."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    cfg.set_main_option("file_template", "%%(rev)s_%%(slug)s")
    cfg.set_main_option("truncate_slug_length", "40")
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return cfg


@lru_cache(maxsize=1)
def script_directory() -> ScriptDirectory:
    return ScriptDirectory.from_config(alembic_config("sqlite://"))


def head_revision() -> str:
    heads = script_directory().get_heads()
    if len(heads) != 1:  # two revisions with the same down_revision: the chain must stay linear
        raise SchemaError(f"app/migrations has {len(heads)} heads {sorted(heads)}; make one revision's "
                          "down_revision the other's id")
    return heads[0]


def _known_revisions() -> set[str]:
    return {s.revision for s in script_directory().walk_revisions()}


def _safe_url(url: str) -> str:
    """The URL without its password, for messages."""
    from sqlalchemy.engine import make_url

    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - a message helper never fails
        return "(unparsable URL)"


def schema_state(conn: Connection) -> SchemaState:
    ctx = MigrationContext.configure(conn)
    return SchemaState(ctx.get_current_revision(), head_revision(), inspect(conn).has_table("jobs"))


@contextmanager
def _migration_lock(engine: Engine) -> Iterator[Connection]:
    """One transaction holding the database's migration lock (concurrent starters wait here)."""
    if engine.dialect.name == "postgresql":
        with engine.begin() as conn:
            conn.exec_driver_sql(f"SELECT pg_advisory_xact_lock({PG_LOCK_KEY})")
            yield conn
        return
    db_file = engine.url.database if engine.dialect.name == "sqlite" else None
    if not db_file or db_file == ":memory:":
        with engine.begin() as conn:
            yield conn
        return
    with open(db_file + ".migrate-lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            with engine.begin() as conn:
                yield conn
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _baseline_columns() -> set[str]:
    """Column names the baseline revision creates (read from an empty SQLite built by it)."""
    with tempfile.TemporaryDirectory() as d:
        url = f"sqlite:///{d}/baseline.db"
        eng = create_engine(url, poolclass=pool.NullPool)
        try:
            with eng.begin() as conn:
                cfg = alembic_config(url)
                cfg.attributes["connection"] = conn
                command.upgrade(cfg, BASELINE)
            return {c["name"] for c in inspect(eng).get_columns("jobs")}
        finally:
            eng.dispose()


def _upgrade_locked(conn: Connection, url: str, revision: str) -> tuple[str | None, str | None]:
    state = schema_state(conn)
    before = state.revision
    if state.status == "unknown":
        raise SchemaError(state.problem(url))
    cfg = alembic_config(url)
    cfg.attributes["connection"] = conn
    if state.status == "legacy":  # made by create_all before migrations: it is the baseline, adopt it
        have = {c["name"] for c in inspect(conn).get_columns("jobs")}
        want = _baseline_columns()
        if have != want:
            raise SchemaError(f"the jobs table of {_safe_url(url)} has no alembic_version and does not match the "
                              f"baseline revision {BASELINE} (missing {sorted(want - have)}, extra "
                              f"{sorted(have - want)}); it cannot be upgraded automatically")
        command.stamp(cfg, BASELINE)
        before = f"(pre-migration, adopted as {BASELINE})"
    command.upgrade(cfg, revision)
    return before, MigrationContext.configure(conn).get_current_revision()


def _short_lived_engine(url: str) -> Engine:
    """An engine for one start-up check or upgrade; SQLite waits up to 30 s for another process's
    write lock (the default 5 s is too short on a busy machine with API and workers starting)."""
    connect_args = {"timeout": 30} if url.startswith("sqlite") else {}
    return create_engine(url, poolclass=pool.NullPool, connect_args=connect_args)


def upgrade(url: str, revision: str = "head") -> tuple[str | None, str | None]:
    """Bring the database at `url` to `revision` (default head); returns (revision before, after).
    Safe to run from several processes at once (they wait on the migration lock)."""
    engine = _short_lived_engine(url)
    try:
        with _migration_lock(engine) as conn:
            before, after = _upgrade_locked(conn, url, revision)
    finally:
        engine.dispose()
    if before != after:
        log.warning("job database %s upgraded: %s -> %s", _safe_url(url), before, after)
    return before, after


def ensure_schema(engine: Engine) -> None:
    """What the API and the worker do at start: create an empty database, accept one at head,
    raise SchemaError (naming the command) for anything else. Never changes existing data."""
    url = engine.url.render_as_string(hide_password=False)
    with engine.connect() as conn:
        state = schema_state(conn)
    if state.status == "current":
        return
    # judge anything else under the lock: another process may be creating the schema right now, and
    # SQLite's DDL is not transactional, so outside the lock a half-built one looks "legacy"
    with _migration_lock(engine) as conn:
        state = schema_state(conn)  # another process may have created it while we waited
        if state.status == "empty":
            cfg = alembic_config(url)
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, "head")
            log.warning("job database %s was empty: created the schema (revision %s)", _safe_url(url), state.head)
        elif state.status != "current":
            raise SchemaError(state.problem(url))


def ensure_schema_at(url: str) -> None:
    """ensure_schema on a short-lived engine (start-up checks of the worker and scripts/serve.py)."""
    engine = _short_lived_engine(url)
    try:
        db_file = engine.url.database if engine.dialect.name == "sqlite" else None
        if db_file and db_file != ":memory:":
            Path(db_file).parent.mkdir(parents=True, exist_ok=True)
        ensure_schema(engine)
    finally:
        engine.dispose()


# ------------------------------------------------------------------------------------------------
# CLI: ribpull-db (make migrate)
# ------------------------------------------------------------------------------------------------

def _new_revision(message: str, autogenerate: bool) -> None:
    head = head_revision()
    rev_id = f"{int(head) + 1:04d}" if head.isdigit() else None  # the convention: 0001, 0002, ...
    with tempfile.TemporaryDirectory() as d:
        url = f"sqlite:///{d}/autogenerate.db"
        if autogenerate:  # diff the models against a database at the current head
            upgrade(url)
        command.revision(alembic_config(url), message=message, autogenerate=autogenerate, rev_id=rev_id)


def main(argv: list[str] | None = None) -> int:
    from .settings import Settings, normalize_db_url

    ap = argparse.ArgumentParser(prog="ribpull-db", description="RibPull job database schema (Alembic).")
    ap.add_argument("--url", help="database URL (default: RIBPULL_DATABASE_URL / DATABASE_URL, else the "
                                  "SQLite file in RIBPULL_STORAGE_DIR)")
    sub = ap.add_subparsers(dest="cmd", required=True)
    up = sub.add_parser("upgrade", help="upgrade the database to this code's head")
    up.add_argument("--sql", action="store_true", help="print the SQL (from the database's revision) instead")
    up.add_argument("--revision", default="head", help="target revision (default head)")
    sub.add_parser("current", help="print the database's revision and this code's head")
    sub.add_parser("check", help="exit 0 when the database is at head, else 1")
    rv = sub.add_parser("revision", help="write a new revision file on top of the head")
    rv.add_argument("-m", "--message", required=True)
    rv.add_argument("--autogenerate", action="store_true", help="fill it from the difference to app/db.py")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("alembic").setLevel(logging.INFO)

    settings = Settings()
    url = normalize_db_url(args.url) if args.url else settings.db_url
    if url.startswith("sqlite") and not args.url:
        settings.storage_path.mkdir(parents=True, exist_ok=True)
    try:
        if args.cmd == "revision":
            _new_revision(args.message, args.autogenerate)
            return 0
        if args.cmd == "upgrade" and args.sql:
            engine = create_engine(url, poolclass=pool.NullPool)
            with engine.connect() as conn:
                start = schema_state(conn).revision or ("" if not inspect(conn).has_table("jobs") else BASELINE)
            engine.dispose()
            rng = f"{start}:{args.revision}" if start else args.revision
            command.upgrade(alembic_config(url), rng, sql=True)
            return 0
        if args.cmd == "upgrade":
            before, after = upgrade(url, args.revision)
            print(f"{_safe_url(url)}: {before or '(empty)'} -> {after}" if before != after
                  else f"{_safe_url(url)}: already at {after}")
            return 0
        engine = create_engine(url, poolclass=pool.NullPool)
        with engine.connect() as conn:
            state = schema_state(conn)
        engine.dispose()
        if args.cmd == "current":
            print(f"database {state.revision or '(none)'} ({state.status}), code head {state.head}")
            return 0
        if state.status == "current":
            print(f"{_safe_url(url)}: at head {state.head}")
            return 0
        print(state.problem(url) if state.status != "empty" else
              f"{_safe_url(url)} is empty: run {UPGRADE_COMMAND}", file=sys.stderr)
        return 1
    except SchemaError as exc:
        print(f"ribpull-db: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
