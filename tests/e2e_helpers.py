"""What the end-to-end modules share: the demo satellite's true pose and requests around it,
the ``stack`` fixture (the API and `proxpose worker` processes on a real Redis, the references
rendered in a separate process), and helpers to submit, wait for and check jobs.

Used by test_service_e2e, test_ui_browser, test_reliability_crash, test_reliability_redis and
test_estimate.
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

from schemas.settings import get_settings
from service.store import Keys
from worker.engine.posemath import axis_angle_to_matrix, matrix_to_quaternion, quaternion_to_matrix

#: Redis database of the end-to-end modules (test_service_e2e, test_ui_browser).
DB = 2
KEYS = Keys("proxpose")
#: A unit cube, corners (0, 0, 0) and (1, 1, 1), as OBJ.
CUBE_OBJ = (
    "".join(f"v {i & 1} {i >> 1 & 1} {i >> 2 & 1}\n" for i in range(8))
    + "f 1 3 2\nf 2 3 4\nf 5 6 7\nf 6 8 7\nf 1 2 5\nf 2 6 5\n"
    + "f 3 7 4\nf 4 7 8\nf 1 5 3\nf 3 5 7\nf 2 4 6\nf 4 8 6\n"
).encode()
#: Redis memory a finished 512² estimate may take (issue 17): its bytes are in the blob store.
JOB_REDIS_BUDGET_BYTES = 20_000
#: What grows with a job is its result's iteration history (~0.7 kB per iteration as JSON, kept
#: zlib-compressed: ~0.2 kB); the rest of the hash (request, timestamps, artifact references,
#: the result's fixed part) is ~5 kB. A job's memory is held to BASE + PER_ITERATION × iterations
#: (at most the budget), which a plain result would overshoot from the first iterations on.
JOB_REDIS_BASE_BYTES = 5_500
JOB_REDIS_PER_ITERATION_BYTES = 350
#: Largest hash field but the compressed result (the artifact references are ~1.1 kB).
JOB_FIELD_MAX_BYTES = 2_048
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


@pytest.fixture(scope="module", name="stack")
def e2e_stack(
    redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Stack]:
    """The API, its Redis database and a worker pool, with the references rendered (a module
    imports it as e2e_stack; its tests ask for ``stack``)."""
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


def job_redis_bytes(r: redis.Redis, job_id: str) -> dict[str, int]:
    """``MEMORY USAGE … SAMPLES 0`` of every key naming the job (its hash; RQ's job hash and
    the lease while it runs), bytes."""
    return {
        k.decode(): int(r.memory_usage(k, samples=0) or 0) for k in r.scan_iter(match=f"*{job_id}*")
    }


def assert_job_redis_budget(r: redis.Redis, job: dict[str, Any]) -> int:
    """A finished job keeps only metadata in Redis: no plain result, no big field, its result
    compressed, and its memory within the budget scaled by its iterations; the bytes used."""
    fields = r.hgetall(KEYS.job(job["id"]))
    assert b"result" not in fields and b"result_z" in fields, sorted(fields)
    big = {f: len(v) for f, v in fields.items() if len(v) > JOB_FIELD_MAX_BYTES}
    assert set(big) <= {b"result_z"}, big
    assert len(fields[b"result_z"]) < 0.5 * len(json.dumps(job["result"]))
    per_key = job_redis_bytes(r, job["id"])
    used = sum(per_key.values())
    iterations = int(job["result"]["iterations"])
    bound = min(
        JOB_REDIS_BUDGET_BYTES, JOB_REDIS_BASE_BYTES + JOB_REDIS_PER_ITERATION_BYTES * iterations
    )
    assert used <= bound, (per_key, iterations, {f: len(v) for f, v in fields.items()})
    return used
