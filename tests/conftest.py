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
    try:
        stack.start()
    except Exception:
        print(stack.tail())
        stack.stop()
        raise
    yield stack
    stack.stop()


@pytest.fixture(scope="session")
def sample_ply(tmp_path_factory):
    """The synthetic ribcage point cloud (20k points) written by ribpull_core.phantom."""
    return servicekit.make_sample(tmp_path_factory.mktemp("sample"))
