"""`ribpull submit / status / download` (ribpull_core/client.py) against the real running service:
the commands a newcomer or a CI job runs, as subprocesses, with their exit codes and output."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from servicekit import KEY_A, KEY_B, ROOT

pytestmark = pytest.mark.service

# 300 iterations keep the training itself ~2.5 s long, several 0.3 s polls wide: with 20 it lasted
# ~0.2 s and a poll could miss every iteration report (CI stop 33 saw only "running fit (2%)").
PARAMS = json.dumps({"preset": "smoke", "iterations": 300, "preview": False})


def ribpull(*args: str, timeout: float = 400) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ribpull_core.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout, check=False)


def test_submit_wait_download(service, sample_ply, tmp_path):
    out = tmp_path / "out"
    p = ribpull("submit", str(sample_ply), "--url", service.url, "--key", KEY_A, "--params", PARAMS,
                "--wait", "--poll", "0.3", "-o", str(out))
    assert p.returncode == 0, p.stderr[-2000:]
    job_id = p.stdout.strip().splitlines()[0]
    assert len(job_id) == 32
    assert "running fit" in p.stderr and "loss" in p.stderr, p.stderr[-1000:]  # progress: stage, iteration, loss
    job = service.client().get(f"/v1/jobs/{job_id}").json()
    names = {a["name"] for a in job["artifacts"]}
    assert names and names == {f.name for f in out.iterdir()}, (names, list(out.iterdir()))
    for a in job["artifacts"]:
        assert (out / a["name"]).stat().st_size == a["bytes"]

    s = ribpull("status", job_id, "--url", service.url, "--key", KEY_A)
    assert s.returncode == 0 and "succeeded" in s.stdout, s.stderr
    d = ribpull("download", job_id, "--url", service.url, "--key", KEY_A, "-o", str(tmp_path / "d"),
                "--name", "mesh.glb")
    assert d.returncode == 0 and (tmp_path / "d" / "mesh.glb").stat().st_size > 0, d.stderr
    # another key sees no such job: non-zero with the problem's detail
    other = ribpull("status", job_id, "--url", service.url, "--key", KEY_B)
    assert other.returncode == 2 and "no job with id" in other.stderr, other.stderr


def test_refused_submit_exits_nonzero_with_the_detail(service, tmp_path):
    f = tmp_path / "metres.xyz"
    pts = np.random.default_rng(0).normal(size=(400, 3)) * 0.04
    f.write_text("\n".join(" ".join(str(v) for v in p) for p in pts))
    p = ribpull("submit", str(f), "--url", service.url, "--key", KEY_A, "--params", PARAMS, "--wait",
                "-o", str(tmp_path / "o"))
    assert p.returncode == 2, (p.returncode, p.stderr)
    assert "implausible_extent" in p.stderr and '"units": "m"' in p.stderr, p.stderr
    assert not (tmp_path / "o").exists()


def test_download_before_success_writes_nothing(service, tmp_path):
    d = ribpull("download", "0" * 32, "--url", service.url, "--key", KEY_A, "-o", str(tmp_path / "x"))
    assert d.returncode == 2 and "no job with id" in d.stderr, d.stderr
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())
    bad = ribpull("status", "0" * 32, "--url", "http://127.0.0.1:9", "--key", KEY_A, "--http-timeout", "2")
    assert bad.returncode == 3 and "unreachable" in bad.stderr, bad.stderr
