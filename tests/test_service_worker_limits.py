"""Worker-side bounds on a stack of its own (real Redis, Celery prefork worker, API):

- a pool process whose memory grew past RIBPULL_WORKER_MAX_MEMORY_MB after a job is replaced
  (Celery's max-memory-per-child), so an idle worker does not keep GBs after a big grid;
- a cancel is enforced within RIBPULL_CANCEL_GRACE_S even in a stage that never checks for it: the
  job is recorded canceled, the pool process ends, the master starts a fresh one and the next job runs.

The stage that ignores cancellation is `pipeline` below (RIBPULL_PIPELINE points at it): it stands in
for a long library call (an SDF volume, metrics) inside the real worker; every other job runs the
real ribpull_core pipeline.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.service

UNCANCELLABLE_SEED = 4242
GRACE_S = 1.0  # the default: a cancel is honoured within 2 s at every stage


def pipeline(input_path, outdir, options, progress=None, should_cancel=None):
    """RIBPULL_PIPELINE of this stack: the real pipeline, except seed 4242 sleeps in a stage that
    never calls should_cancel (what a long C-level call looks like to the worker)."""
    from ribpull_core.pipeline import PipelineProgress, run_pipeline

    if options.seed == UNCANCELLABLE_SEED:
        if progress:
            progress(PipelineProgress(stage="sdf", fraction=0.85, message="a stage that ignores cancel"))
        time.sleep(300)
        raise RuntimeError("the uncancellable stage was not stopped")
    return run_pipeline(input_path, outdir, options, progress, should_cancel)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    import servicekit

    here = str(Path(__file__).resolve().parent)
    s = servicekit.Stack(tmp_path_factory.mktemp("limits"), {
        "RIBPULL_WORKER_MAX_MEMORY_MB": "64",  # every child that ran a job is over this: always recycled
        "RIBPULL_CANCEL_GRACE_S": str(GRACE_S),
        "RIBPULL_PIPELINE": "test_service_worker_limits:pipeline",
    })
    s.env["PYTHONPATH"] = here + ":" + s.env["PYTHONPATH"]
    yield from s.serve()


def _xyz(points) -> bytes:
    return "\n".join(" ".join(repr(float(v)) for v in p) for p in points).encode()


CLOUD = _xyz(np.random.default_rng(3).normal(size=(600, 3)) * 40.0)
FAST = {"preset": "smoke", "iterations": 10, "skeleton": False, "preview": False}


def _worker_pid_of(stack, job_id: str) -> int:
    text = "\n".join(p.read_text(errors="replace") for p in sorted(stack.logs.glob("worker-*.log")))
    m = re.findall(rf"job {job_id}: attempt \d+ started \([^)]*:(\d+)\)", text)
    assert m, text[-2000:]
    return int(m[-1])


def _run(stack, params) -> dict:
    from servicekit import submit, wait_job

    c = stack.client()
    r = submit(c, content=CLOUD, filename="c.xyz", params=params)
    assert r.status_code == 202, r.text
    return wait_job(c, r.json()["id"], "succeeded", timeout=300, stack=stack)


def test_child_recycled_after_a_job_that_grew_its_memory(stack):
    from servicekit import pool_children, proc_status

    a = _run(stack, FAST)
    pid_a = _worker_pid_of(stack, a["id"])
    b = _run(stack, FAST)
    pid_b = _worker_pid_of(stack, b["id"])
    assert pid_a != pid_b, "the pool process was not replaced after passing max-memory-per-child"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        kids = pool_children(stack.worker)
        if kids and pid_b not in kids:
            break
        time.sleep(0.5)
    kids = pool_children(stack.worker)
    assert pid_b not in kids and kids, kids
    print("\nfresh pool process after recycling:", {k: proc_status(k) for k in kids})


def test_cancel_enforced_within_grace_in_a_stage_that_ignores_it(stack):
    from servicekit import submit, wait_job

    c = stack.client()
    r = submit(c, content=CLOUD, filename="c.xyz", params={**FAST, "seed": UNCANCELLABLE_SEED})
    assert r.status_code == 202, r.text
    jid = r.json()["id"]
    wait_job(c, jid, "running", timeout=120, stack=stack, predicate=lambda j: j["progress"]["stage"] == "sdf")
    t = time.monotonic()
    assert c.delete(f"/v1/jobs/{jid}").status_code == 202
    job = wait_job(c, jid, "canceled", timeout=30, stack=stack)
    took = time.monotonic() - t
    assert took < 2.0, f"cancel took {took:.1f} s"
    assert job["status"] == "canceled"
    # the redelivered message must not run it again, and the worker takes the next job
    nxt = _run(stack, FAST)
    assert nxt["status"] == "succeeded"
    assert c.get(f"/v1/jobs/{jid}").json()["status"] == "canceled"
    print(f"\ncancel honoured after {took:.2f} s")
