"""Job state machine on a real SQLite store: claim (idempotent task), lost claims, attempts, sweep."""

from __future__ import annotations

import uuid
from datetime import timedelta

import pytest

from app.db import Job, get_job, make_sessionmaker, utcnow
from app.settings import Settings
from worker import state

pytestmark = pytest.mark.service


@pytest.fixture()
def env(tmp_path):
    s = Settings(storage_dir=tmp_path, max_attempts=2, heartbeat_s=1, stale_after_s=5)
    return s, make_sessionmaker(s)


def _job(sm, **kw) -> str:
    jid = uuid.uuid4().hex
    with sm() as s:
        s.add(Job(id=jid, owner="", status=kw.pop("status", "queued"), params={}, **kw))
        s.commit()
    return jid


def _get(sm, jid) -> Job:
    with sm() as s:
        return get_job(s, jid)


def test_claim_is_exclusive_and_redelivery_takes_over_a_stale_job(env):
    settings, sm = env
    jid = _job(sm)
    c1 = state.claim_job(sm, settings, jid)
    assert c1.outcome == "claimed" and _get(sm, jid).attempts == 1
    assert state.claim_job(sm, settings, jid).outcome == "busy"  # a second delivery while it runs
    with sm() as s:  # the worker died: its heartbeat goes stale
        j = get_job(s, jid)
        j.heartbeat_at = utcnow() - timedelta(seconds=60)
        s.commit()
    c2 = state.claim_job(sm, settings, jid)
    assert c2.outcome == "claimed" and c2.token != c1.token and _get(sm, jid).attempts == 2
    assert not state.update_running(sm, jid, c1.token, stage="fit")  # the old attempt has lost it
    assert state.finish(sm, jid, c2.token, "succeeded", artifacts=["mesh.ply"])
    assert state.claim_job(sm, settings, jid).outcome == "finished"
    assert _get(sm, jid).status == "succeeded"


def test_attempts_are_capped(env):
    settings, sm = env
    jid = _job(sm, status="running", attempts=2, claim_token="x" * 32,
               heartbeat_at=utcnow() - timedelta(seconds=60))
    assert state.claim_job(sm, settings, jid).outcome == "failed"
    j = _get(sm, jid)
    assert j.status == "failed" and j.error_code == "worker_lost" and j.finished_at


def test_cancel_requested_before_start(env):
    settings, sm = env
    jid = _job(sm, cancel_requested=True)
    assert state.claim_job(sm, settings, jid).outcome == "canceled"
    assert _get(sm, jid).status == "canceled"


def test_sweep_requeues_fails_and_cancels_stale_jobs(env):
    settings, sm = env
    old = utcnow() - timedelta(seconds=60)
    a = _job(sm, status="running", attempts=1, claim_token="a" * 32, heartbeat_at=old)
    b = _job(sm, status="running", attempts=2, claim_token="b" * 32, heartbeat_at=old)
    c = _job(sm, status="running", attempts=1, claim_token="c" * 32, heartbeat_at=old, cancel_requested=True)
    d = _job(sm, status="running", attempts=1, claim_token="d" * 32, heartbeat_at=utcnow())
    requeued = []
    out = state.sweep(sm, settings, requeued.append)
    assert out == {"requeued": [a], "failed": [b], "canceled": [c]} and requeued == [a]
    assert _get(sm, a).status == "queued" and _get(sm, a).claim_token is None
    assert _get(sm, b).error_code == "worker_lost"
    assert _get(sm, c).status == "canceled"
    assert _get(sm, d).status == "running"
    assert state.sweep(sm, settings, requeued.append) == {"requeued": [], "failed": [], "canceled": []}
    assert state.claim_job(sm, settings, a).outcome == "claimed"


def test_claim_of_unknown_job(env):
    settings, sm = env
    assert state.claim_job(sm, settings, uuid.uuid4().hex).outcome == "unknown"


def test_fresh_job_of_a_dead_local_process_is_taken_over(env):
    settings, sm = env
    jid = _job(sm, status="running", attempts=1, claim_token="e" * 32, heartbeat_at=utcnow(),
               worker=f"{state.HOSTNAME}:999999999")
    assert state.claim_job(sm, settings, jid).outcome == "claimed"
    jid2 = _job(sm, status="running", attempts=1, claim_token="f" * 32, heartbeat_at=utcnow(),
                worker="some-other-host:1")
    assert state.claim_job(sm, settings, jid2).outcome == "busy"
