"""The typed client (``service.client``): against a real API process on a real Redis (no
worker: jobs stay queued, which is what listing, filtering and cancelling need), and its retry
and event-stream logic against scripted answers (httpx.MockTransport)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis
from conftest import REPO, RedisServer, free_port, start_api
from rq import SimpleWorker
from rq.serializers import JSONSerializer
from service_api_helpers import KEYS, base_request, png

from schemas.jobs import EstimateCreate
from service.client import (
    BadRequest,
    Client,
    Conflict,
    NotFound,
    RateLimited,
    ServiceUnreachable,
    UnsupportedMediaType,
    WaitTimeout,
)
from service.store import Queues

DB = 12


@pytest.fixture(scope="module")
def client_env(
    redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, str]:
    """The environment of the API process (and of a worker that serves it)."""
    env = {
        **os.environ,
        "PROXPOSE_REDIS_URL": redis_server.url(DB),
        "PROXPOSE_DATA_DIR": str(tmp_path_factory.mktemp("client")),
    }
    for name in ("PROXPOSE_API_KEYS", "PROXPOSE_ADMIN_API_KEYS"):
        env.pop(name, None)
    return env


@pytest.fixture(scope="module")
def api_url(client_env: dict[str, str]) -> Iterator[str]:
    root = Path(client_env["PROXPOSE_DATA_DIR"])
    r = redis.Redis.from_url(client_env["PROXPOSE_REDIS_URL"])
    r.flushdb()
    port = free_port()
    proc = start_api(client_env, root / "api.log", port)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        r.flushdb()


@pytest.fixture
def api(api_url: str) -> Iterator[Client]:
    with Client(api_url, timeout_s=10.0) as client:
        yield client


def test_submit_get_list_and_cancel(api: Client, tmp_path: Path) -> None:
    image = tmp_path / "ref.png"
    image.write_bytes(png())
    job = api.submit_estimate(image, EstimateCreate.model_validate(base_request()))
    assert job.status == "queued" and len(job.id) == 32
    other = api.submit_estimate(png(), base_request())  # bytes and a dict
    assert api.get(job.id).id == job.id
    listed = [j.id for j in api.list(status="queued", model_id="demo-sat").items]
    assert {job.id, other.id} <= set(listed)
    assert api.cancel(other.id).status == "cancelled"
    assert [j.id for j in api.list(status="cancelled").items] == [other.id]
    assert other.id not in [j.id for j in api.list(status=["queued", "running"]).items]
    assert api.list(model_id="abcdef0123456789").items == []
    assert {j.id for j in api.iter_estimates()} >= {job.id, other.id}
    with pytest.raises(Conflict) as ended:
        api.cancel(other.id)
    assert ended.value.code == "job_ended" and ended.value.problem.status == 409


def test_a_bad_request_raises_with_the_problem_and_each_field(api: Client) -> None:
    bad = base_request(camera={"width": 64, "height": 64, "fx": -5, "fy": 70, "cx": 1, "cy": 1})
    with pytest.raises(BadRequest) as refused:
        api.submit_estimate(png(), bad)
    problem = refused.value.problem
    assert problem.status == 422 and problem.code == "validation_error"
    assert [e.loc for e in problem.errors] == [["body", "request", "camera", "fx"]]
    with pytest.raises(BadRequest) as mismatch:
        api.submit_estimate(png(32, 32), base_request())
    assert mismatch.value.code == "image_size_mismatch"
    with pytest.raises(NotFound) as missing:
        api.get("0" * 32)
    assert missing.value.problem.type == "urn:proxpose:problem:not_found"


def test_a_retried_submission_returns_the_same_job(api: Client) -> None:
    first = api.submit_estimate(png(), base_request(), idempotency_key="client-test-key-1")
    again = api.submit_estimate(png(), base_request(), idempotency_key="client-test-key-1")
    assert again.id == first.id


def test_wait_times_out_on_a_queued_job_and_events_end_for_a_cancelled_one(api: Client) -> None:
    job = api.submit_estimate(png(), base_request())
    with pytest.raises(WaitTimeout) as late:
        api.wait(job.id, timeout_s=0.5, poll_s=0.1)
    assert late.value.job.status == "queued"
    api.cancel(job.id)
    events = list(api.events(job.id))
    assert events[0].kind == "status" and events[-1].kind == "end"
    assert events[-1].job is not None and events[-1].job.status == "cancelled"
    assert api.wait(job.id).status == "cancelled"


def test_the_cli_verbs_use_the_client(api: Client, api_url: str, tmp_path: Path) -> None:
    import json

    (tmp_path / "ref.png").write_bytes(png())
    (tmp_path / "request.json").write_text(json.dumps(base_request()))
    cli = [sys.executable, "-m", "worker.cli"]
    common = ["--url", api_url]
    submitted = subprocess.run(
        [*cli, "submit", *common, "--image", "ref.png", "--request", "request.json", "--json"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert submitted.returncode == 0, submitted.stderr
    job_id = json.loads(submitted.stdout)["id"]
    status = subprocess.run(
        [*cli, "status", *common, job_id], capture_output=True, text=True, timeout=60
    )
    assert status.returncode == 0 and f"{job_id} queued" in status.stdout
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(base_request(model_id="Not An Id")))
    refused = subprocess.run(
        [*cli, "submit", *common, "--image", "ref.png", "--request", "bad.json"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert refused.returncode == 2
    assert "body.request.model_id" in refused.stderr and "validation_error" in refused.stderr
    version = subprocess.run([*cli, "--version"], capture_output=True, text=True, cwd=REPO)
    assert version.stdout.startswith("proxpose ")


# ----------------------------------------------------------------------------- scripted answers
def scripted(answers: list[Any], seen: list[httpx.Request]) -> Client:
    """A client whose requests get ``answers`` in turn (an exception is raised instead)."""

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer  # type: ignore[no-any-return]

    return Client(
        "http://proxpose.test", transport=httpx.MockTransport(handle), max_retry_wait_s=0.01
    )


def problem(status: int, code: str, **headers: str) -> httpx.Response:
    body = {"type": f"urn:proxpose:problem:{code}", "title": "x", "status": status}
    body |= {"detail": "d", "code": code}
    return httpx.Response(status, json=body, headers=headers)


def job_json(status: str = "queued") -> dict[str, Any]:
    return {
        "id": "a" * 32,
        "status": status,
        "model_id": "demo-sat",
        "created_at": "2026-01-01T00:00:00Z",
        "progress": {"iteration": 0, "max_iterations": 30},
    }


def test_a_dropped_submission_is_retried_with_the_same_idempotency_key() -> None:
    seen: list[httpx.Request] = []
    answers = [httpx.ConnectError("refused"), problem(503, "unavailable", **{"Retry-After": "1"})]
    answers.append(httpx.Response(202, json=job_json()))
    with scripted(answers, seen) as client:
        job = client.submit_estimate(png(), base_request())
    assert job.id == "a" * 32 and len(seen) == 3
    keys = {request.headers["Idempotency-Key"] for request in seen}
    assert len(keys) == 1 and len(keys.pop()) >= 16


def test_retries_end_and_errors_are_typed() -> None:
    seen: list[httpx.Request] = []
    answers = [problem(429, "rate_limited", **{"Retry-After": "2"}) for _ in range(4)]
    with scripted(answers, seen) as client, pytest.raises(RateLimited) as limited:
        client.get("a" * 32)
    assert limited.value.retry_after_s == 2 and len(seen) == 4  # 1 + 3 retries
    with scripted([problem(415, "unsupported_media_type")], []) as client:
        with pytest.raises(UnsupportedMediaType):
            client.get("a" * 32)
    with scripted([httpx.ConnectError("refused")] * 4, []) as client:
        with pytest.raises(ServiceUnreachable):
            client.get("a" * 32)


def test_a_dropped_event_stream_resumes_after_the_last_event() -> None:
    seen: list[httpx.Request] = []
    first = (
        'event: status\ndata: {"status": "running"}\n\n'
        ": keep-alive\n\n"
        'id: 1\nevent: progress\ndata: {"iteration": 1, "max_iterations": 30, "cost": 2.5}\n\n'
    )
    end = f"event: end\ndata: {httpx.Response(200, json=job_json('succeeded')).text}\n\n"
    second = 'id: 2\nevent: progress\ndata: {"iteration": 2, "max_iterations": 30}\n\n' + end
    answers = [
        httpx.Response(200, text=first, headers={"content-type": "text/event-stream"}),
        httpx.ReadError("dropped"),
        httpx.Response(200, text=second, headers={"content-type": "text/event-stream"}),
    ]
    with scripted(answers, seen) as client:
        events = list(client.events("a" * 32))
    assert [e.kind for e in events] == ["status", "progress", "progress", "end"]
    assert [e.progress.iteration for e in events if e.progress] == [1, 2]
    assert events[-1].job is not None and events[-1].job.status == "succeeded"
    assert "Last-Event-ID" not in seen[0].headers
    assert seen[1].headers["Last-Event-ID"] == "1" and seen[2].headers["Last-Event-ID"] == "1"


def rq_info(url: str, *options: str) -> list[str]:
    """The lines of `rq info --raw` with the JSON serializer, as the README says to run it."""
    rq = Path(sys.executable).parent / "rq"
    argv = [str(rq), "info", "-u", url, "-S", "json", "--raw", *options]
    shown = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0, shown.stderr
    return shown.stdout.splitlines()


def test_rq_info_sees_our_queues_and_workers(api: Client, redis_server: RedisServer) -> None:
    """Every queue we use (Queues.all(): renders and estimates, tracks on the latter) and a
    worker on them, as `rq info` shows them. A queue is listed once a job was queued on it; the
    API queues a render only while a worker is live, so the render is queued here directly."""
    url = redis_server.url(DB)
    r = redis.Redis.from_url(url)
    queues = Queues(r, KEYS)
    api.submit_estimate(png(), base_request())
    render = {"camera": base_request()["camera"], "pose": base_request()["initial_pose"]}
    queues.enqueue_render("rq-info-render", "demo-sat", json.dumps(render), timeout_s=60)
    worker = SimpleWorker(
        queues.all(), connection=r, name="rq-info-worker", serializer=JSONSerializer
    )
    worker.register_birth()
    try:
        lines = rq_info(url)
    finally:
        worker.register_death()
    counts = {
        line.split()[1]: int(line.split()[2].rstrip(","))
        for line in lines
        if line.startswith("queue ")
    }
    assert {q.name for q in queues.all()} <= counts.keys(), lines
    assert counts[queues.estimates.name] >= 1 and counts[queues.renders.name] >= 1, counts
    (shown,) = [line for line in lines if line.startswith("worker rq-info-worker ")]
    assert all(q.name in shown for q in queues.all()), shown
