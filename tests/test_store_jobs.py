"""JobStore on a real Redis: under concurrency, the per-key cap on active jobs holds when many
submissions race, and none of them has to retry; a finished job's result is stored compressed
and reads back whole, and a record of an older deployment (plain ``result``) still reads."""

from __future__ import annotations

import json
import secrets
import threading
import zlib
from collections.abc import Iterator
from pathlib import Path

import pytest
import redis
from conftest import RedisServer

from service.store import JobStore, Keys
from service.store.blobs import FileBlobStore
from service.store.jobs import TRACEBACK_MAX_CHARS, ActiveJobsLimitError, IdempotencyKeyTaken

DB = 9
THREADS = 24


@pytest.fixture(name="store")
def job_store(redis_server: RedisServer, tmp_path: Path) -> Iterator[JobStore]:
    r = redis.Redis.from_url(redis_server.url(DB))
    r.flushdb()
    yield JobStore(r, Keys("storetest"), retention_s=3600, blobs=FileBlobStore(tmp_path))
    r.flushdb()
    r.close()


def _race(store: JobStore, cap: int) -> tuple[list[str], int]:
    """THREADS submissions released at once; the ids accepted and the number refused."""
    accepted: list[str] = []
    refused = [0]
    lock = threading.Lock()
    start = threading.Barrier(THREADS)

    def submit() -> None:
        job_id = secrets.token_hex(16)
        start.wait()
        try:
            store.create(
                job_id, "demo-sat", "{}", 3, b"png", "fp", owner="alice", timeout_s=60,
                max_active=cap,
            )  # fmt: skip
        except ActiveJobsLimitError:
            with lock:
                refused[0] += 1
            return
        with lock:
            accepted.append(job_id)

    threads = [threading.Thread(target=submit) for _ in range(THREADS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return accepted, refused[0]


def test_racing_submissions_never_overshoot_the_cap(store: JobStore) -> None:
    accepted, refused = _race(store, cap=5)
    assert len(accepted) == 5 and refused == THREADS - 5
    r = store.r
    assert r.scard(store.keys.owner_active("alice")) == 5
    assert r.zcard(store.keys.jobs_index) == 5  # refused ones left nothing behind
    seqs = sorted(int(r.hget(store.keys.job(j), "seq")) for j in accepted)  # type: ignore[arg-type]
    assert len(set(seqs)) == 5


def test_uncapped_racing_submissions_all_land_with_distinct_sequence_numbers(
    store: JobStore,
) -> None:
    accepted, refused = _race(store, cap=0)
    assert refused == 0 and len(accepted) == THREADS
    for job_id in accepted:
        record = store.get(job_id)
        assert record is not None and record.status == "queued"
    seqs = {store.get(j).seq for j in accepted}  # type: ignore[union-attr]
    assert len(seqs) == THREADS
    queued = store.queues.estimates.get_job_ids()
    assert len(queued) == THREADS  # every job is on the RQ queue


def test_a_failed_write_gives_the_reserved_place_back(
    store: JobStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise redis.ConnectionError("lost the connection")

    monkeypatch.setattr(store.queues, "enqueue_estimate", broken)
    with pytest.raises(redis.ConnectionError):
        store.create("a" * 32, "demo-sat", "{}", 3, b"png", "fp", owner="alice", timeout_s=60,
                     max_active=1)  # fmt: skip
    assert store.r.scard(store.keys.owner_active("alice")) == 0
    monkeypatch.undo()
    store.create("b" * 32, "demo-sat", "{}", 3, b"png", "fp", owner="alice", timeout_s=60,
                 max_active=1)  # fmt: skip
    assert store.get("a" * 32) is None and store.get("b" * 32) is not None


def test_an_idempotency_key_is_claimed_with_the_reservation(store: JobStore) -> None:
    """The first create with a key claims it (for the retention); another create with it then
    raises IdempotencyKeyTaken with that claim and reserves and writes nothing; at the cap the
    claim stays (the caller gives it back), and a released key can be claimed again."""
    r, keys = store.r, store.keys
    store.create("a" * 32, "demo-sat", "{}", 3, b"png", "fp-a", owner="alice", timeout_s=60,
                 max_active=2, idempotency_key="k1")  # fmt: skip
    claim = {"job_id": "a" * 32, "fingerprint": "fp-a"}
    assert json.loads(r.get(keys.idempotency("alice", "k1"))) == claim  # type: ignore[arg-type]
    assert 3590 < r.ttl(keys.idempotency("alice", "k1")) <= 3600  # type: ignore[operator]
    with pytest.raises(IdempotencyKeyTaken) as taken:
        store.create("b" * 32, "demo-sat", "{}", 3, b"png", "fp-b", owner="alice", timeout_s=60,
                     max_active=2, idempotency_key="k1")  # fmt: skip
    assert taken.value.claim == claim
    assert r.scard(keys.owner_active("alice")) == 1 and r.get(keys.jobs_seq) == b"1"
    assert store.get("b" * 32) is None and store.queues.estimates.count == 1
    # another owner's key of the same name is another key
    store.create("c" * 32, "demo-sat", "{}", 3, b"png", "fp", owner="bob", timeout_s=60,
                 idempotency_key="k1")  # fmt: skip
    store.create("d" * 32, "demo-sat", "{}", 3, b"png", "fp", owner="alice", timeout_s=60,
                 max_active=2)  # fmt: skip
    with pytest.raises(ActiveJobsLimitError):
        store.create("e" * 32, "demo-sat", "{}", 3, b"png", "fp-e", owner="alice", timeout_s=60,
                     max_active=2, idempotency_key="k2")  # fmt: skip
    assert json.loads(r.get(keys.idempotency("alice", "k2")))["job_id"] == "e" * 32  # type: ignore[arg-type]
    store.release_idempotency("alice", "k2")
    store.create("f" * 32, "demo-sat", "{}", 3, b"png", "fp-f", owner="alice", timeout_s=60,
                 idempotency_key="k2")  # fmt: skip
    assert json.loads(r.get(keys.idempotency("alice", "k2")))["job_id"] == "f" * 32  # type: ignore[arg-type]


def test_a_created_job_reads_back_as_the_record_create_returned(store: JobStore) -> None:
    record = store.create("c" * 32, "demo-sat", '{"x": 1}', 7, b"png", "fp", owner="bob",
                          timeout_s=90)  # fmt: skip
    assert store.get("c" * 32) == record


def _finish_with(store: JobStore, job_id: str, result_json: str) -> None:
    store.create(job_id, "demo-sat", "{}", 30, b"png", "fp", owner="bob", timeout_s=90)
    assert store.finish(job_id, "succeeded", result_json=result_json)


def test_a_result_is_stored_compressed_and_reads_back_whole(store: JobStore) -> None:
    history = [{"iteration": i, "pose": {"t": [0.1 * i, -0.2, 14.0 + i / 7]}, "cost": i / 3}
               for i in range(30)]  # fmt: skip
    result_json = json.dumps({"iterations": 30, "history": history})
    _finish_with(store, "d" * 32, result_json)
    stored = store.r.hgetall(store.keys.job("d" * 32))
    assert b"result" not in stored
    assert zlib.decompress(stored[b"result_z"]).decode() == result_json
    assert len(stored[b"result_z"]) < len(result_json) / 2
    record = store.get("d" * 32)
    assert record is not None and record.result == result_json


def test_a_plain_result_of_an_older_deployment_still_reads(store: JobStore) -> None:
    _finish_with(store, "e" * 32, "{}")
    key = store.keys.job("e" * 32)
    store.r.hdel(key, "result_z")
    store.r.hset(key, "result", '{"iterations": 4}')  # how jobs were stored before
    record = store.get("e" * 32)
    assert record is not None and record.result == '{"iterations": 4}'
    page, _cursor = store.list_page(10, None)
    assert [job.result for job in page if job.id == "e" * 32] == ['{"iterations": 4}']


def test_a_failed_job_keeps_only_the_end_of_a_long_traceback(store: JobStore) -> None:
    store.create("f" * 32, "demo-sat", "{}", 30, b"png", "fp", owner="bob", timeout_s=90)
    tb = "Traceback (most recent call last):\n" + "  frame\n" * 5000 + "ValueError: boom\n"
    assert store.finish("f" * 32, "failed", traceback=tb)
    kept = store.r.hget(store.keys.job("f" * 32), "traceback")
    assert kept is not None and len(kept) == TRACEBACK_MAX_CHARS
    assert kept.endswith(b"ValueError: boom\n")
