"""Accepted estimates, on a real Redis without workers (nothing here renders): submission
(202 with the job), the request as a file part, the method preset, idempotency, listing and
paging, cancelling a queued job, and jobs lost by a dead worker or by RQ put back in the queue.
The end-to-end tests with workers are in test_service_e2e.py."""

from __future__ import annotations

import json

import redis
from fastapi.testclient import TestClient
from rq import Queue
from service_api_helpers import (
    KEYS,
    api_client,  # noqa: F401 (the client fixture)
    assert_field_error,
    base_request,
    png,
    redis_db,  # noqa: F401 (the r fixture)
    response_model_bytes,
    submit,
)

from schemas.estimate import EstimateResult
from service.resources import estimate_public
from service.routes import estimates
from service.store import JobStore, Leases, Reaper


def test_submit_answers_202_with_location_and_the_job(client: TestClient, r: redis.Redis) -> None:
    response = submit(client)
    assert response.status_code == 202, response.text
    job = response.json()
    assert response.headers["location"] == f"/v1/estimates/{job['id']}"
    assert len(job["id"]) == 32
    assert job["status"] == "queued"
    assert job["model_id"] == "demo-sat"
    assert job["progress"] == {"iteration": 0, "max_iterations": 30, "cost": None, "stage": None}
    assert job["result"] is None and job["error"] is None and job["artifacts"] == {}
    assert Queue(KEYS.estimate_queue, connection=r).job_ids == [f"{job['id']}-1"]
    assert client.get(response.headers["location"]).json() == job


def test_request_may_come_as_a_file_part(client: TestClient) -> None:
    files = {
        "image": ("ref.png", png(), "image/png"),
        "request": ("request.json", json.dumps(base_request()).encode(), "application/json"),
    }
    response = client.post("/v1/estimates", files=files)
    assert response.status_code == 202, response.text


def test_method_preset_is_kept_for_the_worker(client: TestClient, r: redis.Redis) -> None:
    job = submit(client, base_request(options={"method": "paper"})).json()
    assert job["progress"]["max_iterations"] == 10  # the paper preset's cap
    stored = JobStore(r, KEYS, 60).get(job["id"])
    assert stored is not None and json.loads(stored.request)["options"] == {"method": "paper"}


def test_idempotency_key_returns_the_same_job(client: TestClient, r: redis.Redis) -> None:
    key = {"Idempotency-Key": "c0ffee-1"}
    first = submit(client, headers=key)
    again = submit(client, headers=key)
    assert first.status_code == again.status_code == 202
    assert again.json()["id"] == first.json()["id"]
    assert again.headers["idempotent-replayed"] == "true"
    assert again.headers["location"] == first.headers["location"]
    assert Queue(KEYS.estimate_queue, connection=r).count == 1
    other = submit(client, base_request(options={"max_iterations": 3}), headers=key)
    assert_field_error(other, 422, ("header", "Idempotency-Key"))
    fresh = submit(client, headers={"Idempotency-Key": "c0ffee-2"})
    assert fresh.json()["id"] != first.json()["id"]
    assert Queue(KEYS.estimate_queue, connection=r).count == 2


def test_a_key_whose_first_request_is_not_stored_yet_answers_409(
    client: TestClient, r: redis.Redis
) -> None:
    """The key is claimed before the job is written: a retry that finds the claim but not its
    job (the first request still between the two) is told to retry, and creates nothing."""
    key = {"Idempotency-Key": "in-flight"}
    job_id = submit(client, headers=key).json()["id"]
    r.delete(KEYS.job(job_id))  # as if the first request had only claimed the key so far
    again = submit(client, headers=key)
    assert again.status_code == 409, again.text
    assert again.json()["code"] == "idempotency_in_progress"
    assert Queue(KEYS.estimate_queue, connection=r).count == 1
    assert json.loads(r.get(KEYS.idempotency("anonymous", "in-flight")))["job_id"] == job_id  # type: ignore[arg-type]


def test_listing_is_newest_first_and_paged(client: TestClient) -> None:
    ids = [submit(client).json()["id"] for _ in range(5)]
    assert [j["id"] for j in client.get("/v1/estimates").json()["items"]] == ids[::-1]
    seen, cursor, pages = [], None, 0
    while True:
        params = {"limit": 2} | ({"cursor": cursor} if cursor else {})
        page = client.get("/v1/estimates", params=params).json()
        seen += [j["id"] for j in page["items"]]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ids[::-1] and pages == 3
    assert "result" not in page["items"][0]  # listings stay small


def test_cancel_queued_job(client: TestClient, r: redis.Redis) -> None:
    job = submit(client).json()
    response = client.delete(f"/v1/estimates/{job['id']}")
    assert response.status_code == 200, response.text
    cancelled = response.json()
    assert cancelled["status"] == "cancelled" and cancelled["finished_at"] is not None
    assert Queue(KEYS.estimate_queue, connection=r).count == 0
    assert r.ttl(KEYS.job(job["id"])) > 0  # kept for the retention, then gone
    assert client.delete(f"/v1/estimates/{job['id']}").status_code == 409
    events = client.get(f"/v1/estimates/{job['id']}/events")
    assert events.headers["content-type"].startswith("text/event-stream")
    assert "event: status" in events.text and "event: end" in events.text


def test_running_job_of_a_dead_worker_is_requeued_then_failed(
    client: TestClient, r: redis.Redis
) -> None:
    """A lapsed lease (the worker died) sends the job back to the queue, at the front, until
    it has been started job_max_attempts (3) times; then it fails with worker_lost."""
    job_id = submit(client).json()["id"]
    other_id = submit(client).json()["id"]
    leases = Leases(JobStore(r, KEYS, 60), lease_s=30.0)
    queue = Queue(KEYS.estimate_queue, connection=r)
    for attempt in (1, 2, 3):
        rq_id = f"{job_id}-{attempt}"
        assert queue.job_ids[0] == rq_id  # a requeued job goes first
        queue.remove(rq_id)
        assert leases.start(job_id, f"w{attempt}", rq_id) is not None
        assert leases.start(job_id, "again", rq_id) is None  # started once only
        assert client.get(f"/v1/estimates/{job_id}").json()["status"] == "running"
        r.delete(KEYS.job_lease(job_id))  # the lease lapses: the worker is gone
        job = client.get(f"/v1/estimates/{job_id}").json()
        assert job["attempts"] == attempt
        assert job["status"] == ("queued" if attempt < 3 else "failed")
    assert job["error"]["code"] == "worker_lost" and "3 attempts" in job["error"]["message"]
    stored = JobStore(r, KEYS, 60).get(job_id)
    assert stored is not None and [e["worker"] for e in stored.lost] == ["w1", "w2", "w3"]
    assert "lost" not in job and "traceback" not in job
    assert queue.job_ids == [f"{other_id}-1"]  # the other job is untouched
    assert not r.sismember(KEYS.jobs_running, job_id)


def test_a_queued_job_that_rq_lost_is_enqueued_again(client: TestClient, r: redis.Redis) -> None:
    """A worker killed between popping a job from the queue and starting it: the orphan sweep
    enqueues it again once it was missing at two sweeps in a row."""
    job_id = submit(client).json()["id"]
    queue = Queue(KEYS.estimate_queue, connection=r)
    assert r.lpop(queue.key) == f"{job_id}-1".encode()  # what BLPOP does; then the worker dies
    reaper = Reaper(JobStore(r, KEYS, 60), max_attempts=3)

    def sweep() -> list[str]:
        r.delete(KEYS.orphan_sweep_lock)  # the next period
        return reaper.sweep_orphans()

    assert reaper.sweep_orphans() == [] and sweep() == [job_id]
    assert queue.job_ids == [f"{job_id}-2"]
    job = client.get(f"/v1/estimates/{job_id}").json()
    assert job["status"] == "queued" and job["attempts"] == 0
    assert sweep() == [] and sweep() == []  # present in the queue: nothing to do
    assert Leases(JobStore(r, KEYS, 60), 30.0).start(job_id, "w", f"{job_id}-1") is None  # stale
    assert Leases(JobStore(r, KEYS, 60), 30.0).start(job_id, "w", f"{job_id}-2") is not None
    assert not r.sismember(KEYS.jobs_queued, job_id)


def test_a_submission_answers_the_bytes_fastapi_would_serialise(
    client: TestClient, r: redis.Redis
) -> None:
    """The 202 is serialised by the route (``submissions.accepted``), not by FastAPI's pass over
    the route's response_model: its body is the bytes that pass gives, for a new job and for
    the replay of a finished one (a result with awkward floats and an aliased field, artifacts)."""
    store = JobStore(r, KEYS, 60, blobs=client.app.state.blobs)  # type: ignore[attr-defined]

    def fastapi_bytes(job_id: str) -> bytes:
        record = store.get(job_id)
        assert record is not None
        return response_model_bytes(
            estimates.router, estimates.create_estimate, estimate_public(record)
        )

    key = {"Idempotency-Key": "bytes-1"}
    first = submit(client, base_request(options={"max_iterations": 7}), headers=key)
    assert first.status_code == 202 and first.headers["content-type"] == "application/json"
    job_id = first.json()["id"]
    assert first.content == fastapi_bytes(job_id)
    pose = {"R": [[0.1 + 0.2, -1.0, 0.0], [1.0, 1e-17, 0.0], [0.0, 0.0, 1.0]],
            "q": [1e16, -0.0, 2.5e-7], "quaternion": [1, 0, 0, 0], "t": [0, 0, 1 / 3]}  # fmt: skip
    step = {"iteration": 1, "stage": "refine", "pose": pose, "cost": 1.0, "step_norm": 0.1,
            "lambda": 1e-3, "accepted": True, "features": 10, "renders": 13,
            "seconds": 0.5}  # fmt: skip
    result = EstimateResult.model_validate(
        {"pose": pose, "initial_pose": pose, "converged": True, "reason": "cost_converged",
         "iterations": 1, "renders": 13, "seconds": 0.5, "method": "default", "history": [step],
         "features": 10, "rms_residual_px": 0.2, "alignment_score": 0.95, "variant": "scalar_rgb"}
    )  # fmt: skip
    assert store.finish(
        job_id, "succeeded", result_json=result.model_dump_json(), artifacts={"overlay": b"png"}
    )
    again = submit(client, base_request(options={"max_iterations": 7}), headers=key)
    assert again.status_code == 202 and again.headers["idempotent-replayed"] == "true"
    assert again.json()["status"] == "succeeded" and again.json()["artifacts"]
    assert again.content == fastapi_bytes(job_id)
    assert list(again.headers)[:3] == ["content-length", "content-type", "location"]
