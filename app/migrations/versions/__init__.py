"""Alembic revisions of the job store, one file each, in a single linear chain (see app/migrate.py)."""
