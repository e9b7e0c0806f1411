"""Alembic migration environment of the job store (env.py + versions/); run through app.migrate."""
