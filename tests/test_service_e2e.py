"""End to end: the API (uvicorn) and `proxpose worker` processes on a real Redis, the real engine.

The references are renders of the demo satellite made by the engine in a separate process (the
API process never loads Mitsuba). The estimates start 3° and 3 % of the range off the truth.
Workers are started and stopped by the tests that need a given number of them.
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np
import pytest
from e2e_helpers import (
    ARTIFACTS,
    CUBE_OBJ,
    KEYS,
    R_TRUE,
    T_TRUE,
    Stack,
    assert_job_redis_budget,
    assert_png,
    camera,
    e2e_stack,  # noqa: F401 (the stack fixture)
    estimate_request,
    failure,
    pose,
    rotation_error_deg,
    submit,
    wait_for,
)
from rq import Queue
from rq.serializers import JSONSerializer

from service.store import JobStore, Queues

pytestmark = pytest.mark.slow


def test_queued_job_waits_for_a_worker_and_a_cancelled_one_never_runs(stack: Stack) -> None:
    stack.workers.stop_all()
    ready = stack.api.get("/readyz")  # ready without workers: jobs queue
    assert ready.status_code == 200 and ready.json()["workers"] == 0
    waiting = submit(stack, estimate_request(128, max_iterations=3)).json()
    dropped = submit(stack, estimate_request(128, max_iterations=3)).json()
    cancel = stack.api.delete(f"/v1/estimates/{dropped['id']}")
    assert cancel.status_code == 200 and cancel.json()["status"] == "cancelled"
    time.sleep(1.0)
    assert stack.api.get(f"/v1/estimates/{waiting['id']}").json()["status"] == "queued"
    assert Queue(KEYS.estimate_queue, connection=stack.r).job_ids == [f"{waiting['id']}-1"]

    stack.workers.ensure(1)
    job, _ = wait_for(stack, waiting["id"], {"succeeded", "failed", "cancelled"})
    assert job["status"] == "succeeded", failure(stack, job)
    assert stack.api.get("/readyz").status_code == 200
    never = stack.api.get(f"/v1/estimates/{dropped['id']}").json()
    assert never["status"] == "cancelled" and never["started_at"] is None


def test_estimate_converges_to_the_truth_with_progress_and_artifacts(stack: Stack) -> None:
    stack.workers.ensure(1)
    response = submit(stack, estimate_request(192), image="ref192")
    location = response.headers["location"]
    job, seen = wait_for(stack, response.json()["id"], {"succeeded", "failed", "cancelled"})
    assert job["status"] == "succeeded", failure(stack, job)
    assert any(s["status"] == "running" and s["progress"]["iteration"] >= 1 for s in seen)
    assert job["progress"]["iteration"] == job["result"]["iterations"]
    result = job["result"]
    assert result["errors"]["rotation_deg"] < 0.5
    assert result["errors"]["translation_pct_of_range"] < 1.0
    # check the returned pose itself, not only the engine's own error figures
    assert rotation_error_deg(result["pose"]["quaternion"]) < 0.5
    t_err = np.linalg.norm(np.asarray(result["pose"]["t"]) - T_TRUE) / np.linalg.norm(T_TRUE)
    assert t_err < 0.01
    assert set(job["artifacts"]) == ARTIFACTS
    for name, url in job["artifacts"].items():
        assert url == f"{location}/artifacts/{name}"
        png = stack.api.get(url)
        assert png.status_code == 200 and png.headers["content-type"] == "image/png"
        assert_png(png.content)
    assert assert_png(stack.api.get(job["artifacts"]["difference"]).content).size == (192, 192)
    assert job["created_at"] <= job["started_at"] <= job["finished_at"]
    # the bytes are in the blob store: what the job leaves in Redis is its hash (the request,
    # the result with its history, compressed), within issue 17's budget
    assert_job_redis_budget(stack.r, job)


def test_events_stream_progress_then_the_final_state(stack: Stack) -> None:
    stack.workers.ensure(1)
    job_id = submit(stack, estimate_request(128, max_iterations=4)).json()["id"]
    events: list[tuple[str, Any]] = []
    with stack.api.stream("GET", f"/v1/estimates/{job_id}/events", timeout=120.0) as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        name = None
        for line in stream.iter_lines():
            if line.startswith("event: "):
                name = line.removeprefix("event: ")
            elif line.startswith("data: ") and name is not None:
                events.append((name, json.loads(line.removeprefix("data: "))))
    names = [n for n, _ in events]
    assert "progress" in names, failure(stack, events[-1][1]) if events else names
    assert names[-1] == "end", names  # and the server closed the stream after it
    iterations = [d["iteration"] for n, d in events if n == "progress"]
    assert iterations == sorted(set(iterations)) and iterations[-1] <= 4
    final = events[-1][1]
    assert final["id"] == job_id and final["status"] == "succeeded", failure(stack, final)
    assert final["result"]["iterations"] == iterations[-1]


def test_two_jobs_run_in_parallel_on_two_workers(stack: Stack) -> None:
    stack.workers.ensure(2)
    ids = [submit(stack, estimate_request(128, max_iterations=6)).json()["id"] for _ in range(2)]
    jobs = [wait_for(stack, i, {"succeeded", "failed", "cancelled"})[0] for i in ids]
    assert [j["status"] for j in jobs] == ["succeeded", "succeeded"], failure(stack, *jobs)
    store = JobStore(stack.r, KEYS, 60)
    records = [store.get(i) for i in ids]
    assert records[0] and records[1] and records[0].worker != records[1].worker
    a, b = jobs
    assert a["started_at"] < b["finished_at"] and b["started_at"] < a["finished_at"]  # overlap


def test_cancel_a_running_job(stack: Stack) -> None:
    stack.workers.ensure(1)
    long_job = estimate_request(192, max_iterations=100, spp=1024, perturbation_spp=256)
    job_id = submit(stack, long_job, image="ref192").json()["id"]
    job, _ = wait_for(stack, job_id, {"running", "succeeded", "failed"}, timeout_s=60.0)
    assert job["status"] == "running", failure(stack, job)
    response = stack.api.delete(f"/v1/estimates/{job_id}")
    assert response.status_code == 202, response.text
    assert response.json()["cancel_requested"] is True
    job, _ = wait_for(stack, job_id, {"succeeded", "failed", "cancelled"}, timeout_s=30.0)
    assert job["status"] == "cancelled", job
    assert job["result"] is None and job["error"] is None
    assert job["progress"]["iteration"] < 100


def test_failed_job_keeps_the_engine_error_code(stack: Stack) -> None:
    stack.workers.ensure(1)
    request = estimate_request(128)
    request["initial_pose"]["t"] = [60.0, 0.0, 14.0]  # the target far outside the view
    job_id = submit(stack, request).json()["id"]
    job, _ = wait_for(stack, job_id, {"succeeded", "failed", "cancelled"})
    assert job["status"] == "failed"
    assert job["error"]["code"] == "empty_render", job["error"]
    assert job["error"]["message"] and "Traceback" not in job["error"]["message"]
    assert job["result"] is None and job["artifacts"] == {}


def test_render_an_uploaded_model_fetched_from_the_blob_store(stack: Stack) -> None:
    stack.workers.ensure(1)
    upload = stack.api.post("/v1/models", files={"file": ("cube.obj", CUBE_OBJ)})
    assert upload.status_code in (200, 201), upload.text
    model = upload.json()
    cam = camera(64)
    body = {
        "model_id": model["id"],
        "camera": cam,
        "pose": {"t": [-0.5, -0.5, 4.0], "q": [0.2, 0.3, 0.1]},
    }
    response = stack.api.post("/v1/renders", json=body)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    image = assert_png(response.content)
    assert image.size == (64, 64) and image.convert("L").getextrema()[1] > 0
    assert (stack.data_dir / "cache" / "models" / f"{model['sha256']}.obj").is_file()
    body["pose"]["t"] = [50.0, 0.0, 4.0]
    invisible = stack.api.post("/v1/renders", json=body)
    assert invisible.status_code == 422
    assert invisible.json()["errors"][0]["loc"] == ["body", "pose"]


def test_a_killed_worker_leaves_readyz_when_a_new_one_starts(stack: Stack) -> None:
    stack.workers.ensure(1)
    running = len(stack.workers.procs)
    dead = stack.workers.kill()
    assert dead in stack.workers.registered()  # its heartbeat key has not expired yet
    stack.workers.ensure(running)  # a new worker unregisters the dead ones of its host
    assert dead not in stack.workers.registered()
    assert stack.api.get("/readyz").json()["workers"] == running


def test_metrics_count_jobs_of_all_workers(stack: Stack) -> None:
    stack.workers.ensure(1)
    body = {"model_id": "demo-sat", "camera": camera(64), "pose": pose(R_TRUE, T_TRUE), "spp": 1}
    assert stack.api.post("/v1/renders", json=body).status_code == 200
    text = stack.api.get("/metrics").text
    lines = dict(line.rsplit(" ", 1) for line in text.splitlines() if not line.startswith("#"))
    assert float(lines['proxpose_jobs_total{kind="render",status="succeeded"}']) >= 1
    assert float(lines['proxpose_job_duration_seconds_count{kind="render"}']) >= 1
    assert float(lines["proxpose_workers"]) >= 1
    assert 'proxpose_queue_depth{queue="estimates"}' in lines


def test_jobs_queued_under_the_names_before_the_restructuring_still_run(stack: Stack) -> None:
    """An API from before worker/ was split into packages enqueued "worker.jobs.run_render_job"
    and "worker.jobs.run_estimate_job"; such jobs, still queued after an upgrade, must run."""
    stack.workers.stop_all()
    queues = Queues(stack.r, KEYS)
    render = {"camera": camera(64), "pose": pose(R_TRUE, T_TRUE), "spp": 1}
    queues.renders.enqueue(
        "worker.jobs.run_render_job", "old-render", "demo-sat", json.dumps(render),
        job_id="old-render", result_ttl=0,
    )  # fmt: skip
    job = submit(stack, estimate_request(128, max_iterations=3)).json()
    rq_id = f"{job['id']}-1"
    assert queues.remove(queues.estimates, rq_id)  # as the old API would have enqueued it:
    old = queues.estimates.create_job(
        "worker.jobs.run_estimate_job", args=(job["id"],), job_id=rq_id, result_ttl=0
    )
    queues.estimates.enqueue_job(old)
    assert Queue(KEYS.estimate_queue, connection=stack.r, serializer=JSONSerializer).job_ids == [
        rq_id
    ]
    stack.workers.ensure(1)
    done = stack.r.blpop([KEYS.render_done("old-render")], timeout=120)
    assert done is not None and json.loads(done[1]) == {"status": "succeeded"}, failure(stack)
    finished, _ = wait_for(stack, job["id"], {"succeeded", "failed", "cancelled"})
    assert finished["status"] == "succeeded", failure(stack, finished)
