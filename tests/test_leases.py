"""Lease fencing (service/store/leases.py) on a real Redis: once a worker's lease lapsed and a
reaper gave the job to another attempt, the old attempt can neither renew, report progress,
drop the new attempt's lease nor finish the job; the newer attempt's progress and result stand.
A stale RQ enqueueing cannot start the job twice."""

from __future__ import annotations

import json
import secrets
from collections.abc import Iterator
from pathlib import Path

import pytest
import redis
from conftest import RedisServer

from schemas.jobs import Progress
from service.store import JobStore, Keys, Leases, Reaper
from service.store.blobs import FileBlobStore

#: Redis database of this module.
DB = 11
KEYS = Keys("leasetest")


@pytest.fixture
def store(redis_server: RedisServer, tmp_path: Path) -> Iterator[JobStore]:
    r = redis.Redis.from_url(redis_server.url(DB))
    r.flushdb()
    yield JobStore(r, KEYS, retention_s=3600, blobs=FileBlobStore(tmp_path))
    r.flushdb()
    r.close()


def _job(store: JobStore) -> str:
    job_id = secrets.token_hex(16)
    store.create(job_id, "demo-sat", "{}", 10, b"png", "", owner="alice", timeout_s=60)
    return job_id


def _lapse(store: JobStore, job_id: str) -> None:
    """The worker of the running attempt stops renewing: its lease is gone."""
    store.r.delete(KEYS.job_lease(job_id))


def _progress(iteration: int) -> Progress:
    return Progress(iteration=iteration, max_iterations=10, cost=1.0 / iteration, stage="refine")


def test_a_superseded_attempt_cannot_overwrite_the_newer_attempts_work(store: JobStore) -> None:
    leases, reaper = Leases(store, lease_s=30.0), Reaper(store, max_attempts=3)
    job_id = _job(store)
    first = leases.start(job_id, "worker-a", f"{job_id}-1")
    assert first is not None and first.attempts == 1
    assert leases.set_progress(job_id, 1, _progress(3))
    _lapse(store, job_id)
    assert reaper.recover(job_id) == "requeued"
    second = leases.start(job_id, "worker-b", f"{job_id}-2")
    assert second is not None and second.attempts == 2 and second.progress is None
    assert leases.set_progress(job_id, 2, _progress(1))

    # worker-a comes back (it was only slow): every write of attempt 1 is fenced off
    assert not leases.renew(job_id, 1)
    assert not leases.set_progress(job_id, 1, _progress(7))
    assert leases.check(job_id, 1) == (False, False)
    assert not leases.drop(job_id, 1)
    assert not store.finish(job_id, "succeeded", attempt=1, result_json='{"by": "a"}')
    record = store.get(job_id)
    assert record is not None and record.status == "running" and record.worker == "worker-b"
    assert record.progress == _progress(1).model_dump(mode="json")
    assert record.result is None
    assert store.r.get(KEYS.job_lease(job_id)) == b"2"  # attempt 2's lease is untouched

    # attempt 2 is the one that finishes, and what it wrote stands
    assert leases.renew(job_id, 2) and leases.check(job_id, 2) == (True, False)
    assert store.finish(job_id, "succeeded", attempt=2, result_json='{"by": "b"}')
    record = store.get(job_id)
    assert record is not None and record.status == "succeeded"
    assert json.loads(record.result or "") == {"by": "b"}
    assert [lost["worker"] for lost in record.lost] == ["worker-a"]
    assert not store.finish(job_id, "failed", attempt=1)  # nor after the end


def test_a_stale_enqueueing_does_not_start_the_job_again(store: JobStore) -> None:
    leases, reaper = Leases(store, lease_s=30.0), Reaper(store, max_attempts=3)
    job_id = _job(store)
    assert leases.start(job_id, "worker-a", f"{job_id}-1") is not None
    _lapse(store, job_id)
    assert reaper.recover(job_id) == "requeued"
    assert leases.start(job_id, "worker-c", f"{job_id}-1") is None  # the old RQ job, late
    assert leases.start(job_id, "worker-b", f"{job_id}-2") is not None
    assert leases.start(job_id, "worker-d", f"{job_id}-2") is None  # and not twice


def test_reconcile_recovers_a_job_whose_lease_lapsed(store: JobStore) -> None:
    leases, reaper = Leases(store, lease_s=30.0), Reaper(store, max_attempts=1)
    job_id = _job(store)
    record = leases.start(job_id, "worker-a", f"{job_id}-1")
    assert record is not None and reaper.reconcile(record) == record  # the lease holds
    _lapse(store, job_id)
    after = reaper.reconcile(record)
    assert after.status == "failed" and after.error is not None
    assert after.error["code"] == "worker_lost"  # one attempt allowed, and it was lost


def test_a_track_whose_worker_died_is_requeued_as_a_track_then_failed(store: JobStore) -> None:
    """The reaper requeues by the job's kind: a track goes back as the track job, and after
    job_max_attempts lost workers it fails; its frames stay for the attempts between (the blob
    sweeper removes them once it has ended)."""
    from rq import Queue
    from rq.serializers import JSONSerializer

    from service.store.queues import TRACK_JOB

    job_id = secrets.token_hex(16)
    frames = [("a.png", b"png-a"), ("b.png", b"png-b")]
    store.create_track(job_id, "demo-sat", "{}", frames, "", owner="alice", timeout_s=60)
    queue = Queue(KEYS.estimate_queue, connection=store.r, serializer=JSONSerializer)
    leases = Leases(store, lease_s=30)
    for attempt in (1, 2):
        rq_id = queue.job_ids[0]
        assert queue.fetch_job(rq_id).func_name == TRACK_JOB  # type: ignore[union-attr]
        queue.remove(rq_id)
        record = leases.start(job_id, "w", rq_id)
        assert record is not None and record.kind == "track" and record.attempts == attempt
        _lapse(store, job_id)
        outcome = Reaper(store, max_attempts=2).recover(job_id)
        assert outcome == ("requeued" if attempt == 1 else "failed"), outcome
        if attempt == 1:
            assert store.get_input(store.get(job_id), 1) == b"png-b"  # type: ignore[arg-type]
    record = store.get(job_id)
    assert record is not None and record.status == "failed" and record.error is not None
    assert record.error["code"] == "worker_lost"
