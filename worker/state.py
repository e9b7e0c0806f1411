"""Compatibility alias: the job state machine lives in app/state.py (shared by the API and the worker)."""

from app.state import *
from app.state import (  # noqa: F401
    Claim,
    _local_process_dead,
    claim_job,
    finish,
    read_flags,
    sweep,
    update_running,
    worker_id,
)
