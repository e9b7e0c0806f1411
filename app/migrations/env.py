"""Alembic environment of the job store, run programmatically by app.migrate (no alembic.ini).

app.migrate passes either an open connection (config.attributes["connection"], inside its
migration lock) or a URL (sqlalchemy.url); offline mode (`ribpull-db upgrade --sql`) renders SQL.
SQLite gets batch mode (ALTER TABLE there cannot drop or change columns, so Alembic copies the table).
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import create_engine, pool

from app.db import Base

config = context.config
target_metadata = Base.metadata


def _configure(**kw) -> None:
    context.configure(target_metadata=target_metadata, compare_type=True, **kw)


def run_offline() -> None:
    url = config.get_main_option("sqlalchemy.url")
    _configure(url=url, literal_binds=True, render_as_batch=url.startswith("sqlite"),
               dialect_opts={"paramstyle": "named"})
    with context.begin_transaction():
        context.run_migrations()


def run_online() -> None:
    connection = config.attributes.get("connection")
    if connection is None:
        engine = create_engine(config.get_main_option("sqlalchemy.url"), poolclass=pool.NullPool)
        try:
            with engine.connect() as conn:
                _run(conn)
                conn.commit()
        finally:
            engine.dispose()
    else:
        _run(connection)


def _run(connection) -> None:
    _configure(connection=connection, render_as_batch=connection.dialect.name == "sqlite")
    with context.begin_transaction():
        context.run_migrations()


if context.is_offline_mode():
    run_offline()
else:
    run_online()
