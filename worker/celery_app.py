"""The Celery app: `celery -A worker.celery_app worker --pool=prefork -c 1` (or `--pool=solo`).

Long-job settings: late acks (a job whose worker dies is delivered again), prefetch 1, re-queue when
a pool process is lost, and a Redis visibility timeout above the longest job (RIBPULL_JOB_TIMEOUT_S
+ 30 min by default). The parent process never imports torch (CUDA cannot be re-initialised in a
forked child): pool processes import it in `worker_process_init`, a solo worker in its first task.

Each pool process (or the solo worker) also runs a maintenance thread that refreshes a heartbeat key
in Redis (`ribpull:worker:<host>:<pid>`, read by /readyz) and sweeps jobs whose heartbeat is stale.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time

from celery import Celery, signals

from app.jobs import QUEUE, TASK_RUN_JOB, WORKER_KEY_PREFIX
from app.settings import get_settings

log = logging.getLogger("ribpull.worker")

settings = get_settings()

celery_app = Celery("ribpull", broker=settings.redis_url, include=["worker.tasks"])
celery_app.conf.update(
    task_acks_late=True,
    task_reject_on_worker_lost=True,
    task_acks_on_failure_or_timeout=True,
    worker_prefetch_multiplier=1,
    broker_transport_options={"visibility_timeout": settings.visibility_timeout},
    broker_connection_retry_on_startup=True,
    task_default_queue=QUEUE,
    task_ignore_result=True,
    task_store_errors_even_if_ignored=False,
    worker_send_task_events=False,
    worker_hijack_root_logger=True,
    worker_cancel_long_running_tasks_on_connection_loss=False,
    broker_heartbeat=0,
    worker_proc_alive_timeout=120,  # pool processes import torch at start-up
    # a pool process whose resident memory grew past this after a job is replaced by a fresh one
    # (a 512^3 grid leaves GBs in the allocator otherwise); KiB, from RIBPULL_WORKER_MAX_MEMORY_MB
    worker_max_memory_per_child=settings.max_memory_per_child_kib,
)
app = celery_app  # `celery -A worker.celery_app` looks for `app`

_torch_ready = False
#: True in a prefork pool process (the master replaces it if it exits), False in a solo worker
IN_POOL_CHILD = False


def configure_torch() -> None:
    """Set torch's thread count for this process (RIBPULL_TORCH_THREADS; 0 = cores / concurrency)."""
    global _torch_ready
    if _torch_ready:
        return
    import torch

    n = settings.effective_torch_threads
    os.environ["RIBPULL_TORCH_THREADS"] = str(n)  # run_pipeline reads it too
    torch.set_num_threads(n)
    try:
        torch.set_num_interop_threads(max(1, min(n, 2)))
    except RuntimeError:  # already set / parallel work already started
        pass
    _torch_ready = True
    log.info("torch %s: %d threads", torch.__version__, n)


# ------------------------------------------------------------------------------------------------
# maintenance thread: worker heartbeat key + stale-job sweep
# ------------------------------------------------------------------------------------------------

_stop = threading.Event()
_thread: threading.Thread | None = None


def _maintenance_loop() -> None:
    import redis

    from app.db import make_sessionmaker
    from app.jobs import celery_client, enqueue
    from app.state import sweep, worker_id
    from app.storage import artifact_store

    key = WORKER_KEY_PREFIX + worker_id()
    r = redis.Redis.from_url(settings.redis_url, socket_timeout=5, socket_connect_timeout=5)
    sm = make_sessionmaker(settings)
    client = celery_client(settings)
    beat = 10.0
    next_beat = 0.0
    next_sweep = 0.0  # sweep at start-up, then every sweep_interval_s
    while not _stop.is_set():
        now = time.monotonic()
        if now >= next_beat:
            try:
                r.set(key, json.dumps({"pid": os.getpid(), "at": time.time()}), ex=int(beat * 3))
            except Exception as exc:  # noqa: BLE001
                log.warning("worker heartbeat to Redis failed: %s", exc)
            next_beat = now + beat
        if now >= next_sweep:
            try:
                ended = sweep(sm, settings, lambda job_id: enqueue(client, TASK_RUN_JOB, job_id))
                for job_id in ended["failed"] + ended["canceled"]:  # the dead attempt's files
                    artifact_store(settings).keep_only(job_id, None)
            except Exception as exc:  # noqa: BLE001
                log.warning("stale-job sweep failed: %s", exc)
            next_sweep = now + settings.sweep_interval_s
        _stop.wait(min(1.0, max(0.05, min(next_beat, next_sweep) - time.monotonic())))
    try:
        r.delete(key)
    except Exception as exc:  # noqa: BLE001  (shutting down: the heartbeat key expires on its own)
        log.debug("could not delete heartbeat key %s: %s", key, exc)


def start_maintenance() -> None:
    global _thread
    if _thread is not None and _thread.is_alive():
        return
    _stop.clear()
    _thread = threading.Thread(target=_maintenance_loop, name="ribpull-maintenance", daemon=True)
    _thread.start()


def stop_maintenance() -> None:
    _stop.set()
    if _thread is not None:
        _thread.join(timeout=5)


@signals.worker_init.connect
def _on_worker_init(**_kw) -> None:
    """Refuse to start against a job database whose schema is not this code's (app/migrate.py):
    the message names the command to run. Raised as SystemExit: Celery logs and swallows
    ordinary exceptions from signal handlers."""
    from app.migrate import SchemaError, ensure_schema_at

    try:
        ensure_schema_at(settings.db_url)
    except SchemaError as exc:
        log.critical("%s", exc)
        raise SystemExit(f"ribpull worker not started: {exc}") from None


@signals.worker_process_init.connect
def _on_process_init(**_kw) -> None:
    """A prefork pool process: fresh DB connections, torch threads, warm imports, maintenance."""
    from app import db

    global IN_POOL_CHILD
    IN_POOL_CHILD = True
    for eng in list(db._engines.values()):
        eng.dispose(close=False)
    db._engines.clear()
    try:
        configure_torch()
        import torch._dynamo  # noqa: F401 - the first torch.optim optimizer imports it (~3-4 s a job)

        import ribpull_core.pipeline  # noqa: F401 - warm the import before the first job
    except Exception as exc:  # noqa: BLE001 - the task reports import errors per job
        log.error("warm-up import failed: %s", exc)
    start_maintenance()


@signals.worker_process_shutdown.connect
def _on_process_shutdown(**_kw) -> None:
    stop_maintenance()


@signals.worker_ready.connect
def _on_worker_ready(sender=None, **_kw) -> None:
    """Solo/threads pools run tasks in this process: run the maintenance thread here."""
    pool = getattr(sender, "pool", None)
    if pool is not None and "prefork" in type(pool).__module__:
        return
    start_maintenance()


@signals.worker_shutdown.connect
def _on_worker_shutdown(**_kw) -> None:
    stop_maintenance()
