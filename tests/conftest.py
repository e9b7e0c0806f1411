"""Service test fixtures only (the real-process stack lives in tests/servicekit.py)."""

from __future__ import annotations

import json
import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import servicekit


@pytest.fixture(scope="session")
def service(tmp_path_factory):
    """Redis + Celery worker + API (real processes on loopback), shared by the service tests."""
    # RIBPULL_TEST_ENV='{"RIBPULL_DATABASE_URL": "postgresql+psycopg2://..."}' runs the stack differently
    extra = json.loads(os.environ.get("RIBPULL_TEST_ENV") or "{}")
    stack = servicekit.Stack(tmp_path_factory.mktemp("service"), extra)
    yield from stack.serve()


@pytest.fixture(scope="session")
def sample_ply(tmp_path_factory):
    """The synthetic ribcage point cloud (20k points) written by ribpull_core.phantom."""
    return servicekit.make_sample(tmp_path_factory.mktemp("sample"))


@pytest.fixture(scope="session")
def postgres():
    """A throw-away PostgreSQL cluster (tests/pgcluster.py); installs Debian's `postgresql` as root
    when missing, else skips loudly (a warning in the summary, not only an 's')."""
    import warnings

    import pgcluster

    bindir, why = pgcluster.ensure_postgres()
    if bindir is None:
        warnings.warn(f"PostgreSQL tests SKIPPED: {why}", stacklevel=1)
        pytest.skip(f"PostgreSQL unavailable: {why}")
    cluster = pgcluster.PgCluster(bindir).start()
    yield cluster
    cluster.stop()
