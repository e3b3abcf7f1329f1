"""End to end: the API (uvicorn) and `proxpose worker` processes on a real Redis, the real engine.

The references are renders of the demo satellite made by the engine in a separate process (the
API process never loads Mitsuba). The estimates start 3° and 3 % of the range off the truth.
Workers are started and stopped by the tests that need a given number of them.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import redis
from conftest import RENDER_SCRIPT, REPO, RedisServer, WorkerPool, free_port, log_tails, start_api
from PIL import Image
from rq import Queue

from schemas.settings import get_settings
from service.store import JobStore, Keys
from worker.engine.posemath import axis_angle_to_matrix, matrix_to_quaternion, quaternion_to_matrix

pytestmark = pytest.mark.slow

#: Redis database of this module.
DB = 2
KEYS = Keys("proxpose")
#: A unit cube, corners (0, 0, 0) and (1, 1, 1), as OBJ.
CUBE_OBJ = (
    "".join(f"v {i & 1} {i >> 1 & 1} {i >> 2 & 1}\n" for i in range(8))
    + "f 1 3 2\nf 2 3 4\nf 5 6 7\nf 6 8 7\nf 1 2 5\nf 2 6 5\n"
    + "f 3 7 4\nf 4 7 8\nf 1 5 3\nf 3 5 7\nf 2 4 6\nf 4 8 6\n"
).encode()
ARTIFACTS = {"overlay_1", "overlay_2", "overlay_final", "difference", "final_render", "convergence"}

# The truth: the demo satellite 14 m away, turned 110° about (1, 0.6, 0.3).
AXIS = np.array([1.0, 0.6, 0.3]) / np.linalg.norm([1.0, 0.6, 0.3])
R_TRUE = axis_angle_to_matrix(AXIS, np.radians(110.0))
T_TRUE = np.array([0.3, -0.2, 14.0])


def camera(side: int) -> dict[str, float]:
    f = 1.1 * side
    return {
        "width": side,
        "height": side,
        "fx": f,
        "fy": f,
        "cx": side / 2 - 0.5,
        "cy": side / 2 - 0.5,
    }


def pose(R: np.ndarray, t: np.ndarray) -> dict[str, list[float]]:
    return {"t": [float(c) for c in t], "quaternion": [float(c) for c in matrix_to_quaternion(R)]}


def initial_pose(
    seed: int = 0, offset_deg: float = 3.0, offset_frac: float = 0.03
) -> dict[str, Any]:
    """The truth moved by ``offset_deg`` about a random axis and ``offset_frac`` of the range."""
    rng = np.random.default_rng(seed)
    unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
    R0 = R_TRUE @ axis_angle_to_matrix(unit(rng.normal(size=3)), np.radians(offset_deg))
    t0 = T_TRUE + unit(rng.normal(size=3)) * offset_frac * np.linalg.norm(T_TRUE)
    return pose(R0, t0)


def estimate_request(side: int, **options: Any) -> dict[str, Any]:
    return {
        "model_id": "demo-sat",
        "camera": camera(side),
        "initial_pose": initial_pose(),
        "ground_truth": pose(R_TRUE, T_TRUE),
        "options": options,
    }


@dataclass
class Stack:
    api: httpx.Client
    r: redis.Redis
    workers: WorkerPool
    data_dir: Path
    logs: Path
    references: dict[str, bytes]


@pytest.fixture(scope="module")
def stack(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    root = tmp_path_factory.mktemp("e2e")
    data_dir, logs = root / "data", root / "logs"
    logs.mkdir()
    r = redis.Redis.from_url(redis_server.url(DB))
    r.flushdb()
    env = {
        **os.environ,
        "PROXPOSE_REDIS_URL": redis_server.url(DB),
        "PROXPOSE_DATA_DIR": str(data_dir),
        "PYTHONUNBUFFERED": "1",
    }
    get_settings.cache_clear()
    renders = {
        "ref192": {"camera": camera(192), "pose": pose(R_TRUE, T_TRUE), "spp": 64},
        "ref128": {"camera": camera(128), "pose": pose(R_TRUE, T_TRUE), "spp": 32},
    }
    spec = json.dumps({"data_dir": str(data_dir), "out": str(root), "renders": renders})
    render = subprocess.Popen([sys.executable, "-c", RENDER_SCRIPT, spec], env=env, cwd=REPO)
    port = free_port()
    api = start_api(env, logs / "api.log", port)
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120.0)
    workers = WorkerPool(env, logs, r, KEYS.estimate_queue)
    try:
        assert render.wait(timeout=300) == 0, "reference renders failed"
        references = {name: (root / f"{name}.png").read_bytes() for name in renders}
        yield Stack(client, r, workers, data_dir, logs, references)
    finally:  # every process goes, even when stopping one of them fails
        try:
            workers.stop_all()
        finally:
            render.kill()
            for proc in (*workers.procs.values(), api, render):
                proc.terminate()
                proc.wait(timeout=30)
            r.flushdb()


# ----------------------------------------------------------------------------- helpers
def submit(stack: Stack, request: dict[str, Any], image: str = "ref128", **headers: str) -> Any:
    files = {"image": ("ref.png", stack.references[image], "image/png")}
    response = stack.api.post(
        "/v1/estimates", files=files, data={"request": json.dumps(request)}, headers=headers
    )
    assert response.status_code == 202, response.text
    return response


def wait_for(
    stack: Stack, job_id: str, until: set[str], timeout_s: float = 120.0
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Poll the job until its status is in ``until``; (last state, every state seen)."""
    seen = []
    deadline = time.monotonic() + timeout_s
    while True:
        job = stack.api.get(f"/v1/estimates/{job_id}").json()
        seen.append(job)
        if job["status"] in until:
            return job, seen
        assert time.monotonic() < deadline, f"job stuck: {job}"
        time.sleep(0.1)


def failure(stack: Stack, *jobs: dict[str, Any]) -> str:
    """The jobs' errors and the end of every worker's log (where tracebacks go)."""
    logs = log_tails(stack.logs)
    errors = [(job.get("status"), job.get("error")) for job in jobs]
    return f"jobs: {errors}\n{logs}"


def rotation_error_deg(quaternion: list[float]) -> float:
    dR = quaternion_to_matrix(np.asarray(quaternion)).T @ R_TRUE
    return float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))


def assert_png(data: bytes) -> Image.Image:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    Image.open(io.BytesIO(data)).verify()
    return Image.open(io.BytesIO(data))


# ----------------------------------------------------------------------------- tests
def test_queued_job_waits_for_a_worker_and_a_cancelled_one_never_runs(stack: Stack) -> None:
    stack.workers.stop_all()
    ready = stack.api.get("/readyz")
    assert ready.status_code == 503 and ready.json()["workers"] == 0
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


def test_render_an_uploaded_model_fetched_from_redis(stack: Stack) -> None:
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
    assert invisible.json()["detail"][0]["loc"] == ["body", "pose"]


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
