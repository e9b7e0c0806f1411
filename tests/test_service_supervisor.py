"""`make run` (scripts/serve.py) supervises: a worker or API that dies is restarted with back-off and
logged; only SIGTERM/Ctrl-C stops the stack. Real processes: serve.py starts Redis, the worker, the API."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import httpx
import pytest
from servicekit import ROOT

from app import launcher

pytestmark = pytest.mark.service


def _wait(pred, timeout: float, what: str, proc=None, out=None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"serve.py exited ({proc.returncode}) while waiting for {what}:\n{out.read_text()}")
        v = pred()
        if v:
            return v
        time.sleep(0.3)
    raise AssertionError(f"timed out waiting for {what}:\n{out.read_text() if out else ''}")


def _ready(url: str) -> bool:
    try:
        return httpx.get(url + "/readyz", timeout=3).status_code == 200
    except httpx.HTTPError:
        return False


def _pid(out, name: str, after: int = 0) -> int | None:
    text = out.read_text()[after:]
    m = re.findall(rf"{name}\s+(?:restarted: )?pid (\d+)", text)
    return int(m[-1]) if m else None


def test_dead_worker_and_api_are_restarted(tmp_path):
    port = launcher.free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("RIBPULL_") and k not in ("REDIS_URL", "PORT")}
    env.update({"PORT": str(port), "RIBPULL_STORAGE_DIR": str(tmp_path / "storage"), "RIBPULL_DEVICE": "cpu",
                "RIBPULL_TORCH_THREADS": "1", "PYTHONUNBUFFERED": "1", "RIBPULL_NO_ACCESS_LOG": "1"})
    out = tmp_path / "serve.log"
    with open(out, "wb") as fh:
        proc = subprocess.Popen([sys.executable, "scripts/serve.py"], cwd=ROOT, env=env, stdout=fh,
                                stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        _wait(lambda: _ready(url), 180, "readyz", proc, out)
        for name in ("worker", "api"):
            mark = len(out.read_text())
            old = _pid(out, name)
            assert old, out.read_text()
            os.killpg(old, signal.SIGKILL)  # the child and its pool processes, like the OOM killer
            _wait(lambda n=name, o=old: f"{n} (pid {o}) exited" in out.read_text(), 30, f"{name} exit logged", proc, out)
            new = _wait(lambda n=name, m=mark: _pid(out, n, m), 60, f"{name} restarted", proc, out)
            assert new != old
            _wait(lambda: _ready(url), 180, f"readyz after the {name} restart", proc, out)
        assert proc.poll() is None, "serve.py stopped although only a child died"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=40) == 0, out.read_text()
        assert not launcher.port_open("127.0.0.1", port)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
