"""Durability: a Redis with the append-only file on (as `proxpose serve` embeds it and the compose
file runs it) is killed and restarted under a running API; queued jobs, finished results, their
artifacts and registered models are all still there, and the queued jobs then run.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis
from conftest import RENDER_SCRIPT, REPO, WorkerPool, free_port, log_tails, start_api
from e2e_helpers import CUBE_OBJ, R_TRUE, T_TRUE, camera, estimate_request, pose

from schemas.settings import get_settings
from service.embedded_redis import find_redis_server, redis_command
from service.store import Keys

pytestmark = pytest.mark.slow

KEYS = Keys("proxpose")
#: appendfsync everysec: a write is on disk within this, s.
FSYNC_S = 1.0


def start_redis(port: int, data: Path, log: Path) -> subprocess.Popen[bytes]:
    """The embedded Redis's command line (AOF on, fsync every second) on ``port``."""
    binary = find_redis_server()
    assert binary is not None
    with open(log, "ab") as out:
        proc = subprocess.Popen(redis_command(binary, port, data), stdout=out, stderr=out)
    client = redis.Redis(port=port)
    deadline = time.monotonic() + 20.0
    while True:
        try:
            if client.ping():
                return proc
        except redis.RedisError:  # also "LOADING" while it replays the AOF
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)


def wait_for(api: httpx.Client, job_id: str, until: set[str], logs: Path) -> dict[str, Any]:
    deadline = time.monotonic() + 90.0
    while True:
        try:
            state = api.get(f"/v1/estimates/{job_id}").json()
            if state["status"] in until:
                return state  # type: ignore[no-any-return]
        except (httpx.TransportError, KeyError):
            pass
        assert time.monotonic() < deadline, f"job stuck\n{log_tails(logs)}"
        time.sleep(0.1)


def test_redis_killed_and_restarted_keeps_queued_jobs_results_and_models(tmp_path: Path) -> None:
    data, logs = tmp_path / "redis", tmp_path / "logs"
    data.mkdir()
    logs.mkdir()
    port = free_port()
    env = {
        **os.environ,
        "PROXPOSE_REDIS_URL": f"redis://127.0.0.1:{port}/0",
        "PROXPOSE_DATA_DIR": str(tmp_path / "data"),
        "PYTHONUNBUFFERED": "1",
    }
    get_settings.cache_clear()
    spec = {
        "data_dir": str(tmp_path / "data"),
        "out": str(tmp_path),
        "renders": {"ref": {"camera": camera(128), "pose": pose(R_TRUE, T_TRUE), "spp": 32}},
    }
    subprocess.run(
        [sys.executable, "-c", RENDER_SCRIPT, json.dumps(spec)], env=env, check=True, cwd=REPO
    )
    reference = (tmp_path / "ref.png").read_bytes()
    redis_proc = start_redis(port, data, logs / "redis.log")
    r = redis.Redis(port=port)
    api_port = free_port()
    api_proc = start_api(env, logs / "api.log", api_port)
    api = httpx.Client(base_url=f"http://127.0.0.1:{api_port}", timeout=60.0)
    workers = WorkerPool(env, logs, r, KEYS.estimate_queue)

    def submit() -> str:
        files = {"image": ("ref.png", reference, "image/png")}
        request = json.dumps(estimate_request(128, max_iterations=3))
        response = api.post("/v1/estimates", files=files, data={"request": request})
        assert response.status_code == 202, response.text
        return str(response.json()["id"])

    try:
        workers.ensure(1)
        done = submit()
        finished = wait_for(api, done, {"succeeded", "failed", "cancelled"}, logs)
        assert finished["status"] == "succeeded", log_tails(logs)
        artifact = api.get(f"/v1/estimates/{done}/artifacts/difference").content
        model = api.post("/v1/models", files={"file": ("cube.obj", CUBE_OBJ)}).json()
        workers.stop_all()
        waiting = [submit() for _ in range(3)]
        cancelled = submit()
        assert api.delete(f"/v1/estimates/{cancelled}").status_code == 200

        time.sleep(FSYNC_S + 0.5)
        redis_proc.send_signal(signal.SIGKILL)  # a crash: no shutdown save, only the AOF
        redis_proc.wait()
        assert api.get("/v1/estimates").status_code == 503  # Redis down: 503, not 500
        redis_proc = start_redis(port, data, logs / "redis.log")

        # the same API process reconnects; everything is there
        again = api.get(f"/v1/estimates/{done}").json()
        assert again["status"] == "succeeded" and again["result"] == finished["result"]
        assert api.get(f"/v1/estimates/{done}/artifacts/difference").content == artifact
        assert api.get(f"/v1/models/{model['id']}").json() == model
        assert api.get(f"/v1/estimates/{cancelled}").json()["status"] == "cancelled"
        assert [api.get(f"/v1/estimates/{j}").json()["status"] for j in waiting] == ["queued"] * 3
        queued = api.get("/readyz").json()["queue_depth"]["estimates"]
        assert queued == 3

        workers.ensure(1)  # the queued jobs run after the restart
        for job_id in waiting:
            final = wait_for(api, job_id, {"succeeded", "failed", "cancelled"}, logs)
            assert final["status"] == "succeeded", log_tails(logs)
    finally:
        workers.terminate_all()
        api_proc.terminate()
        api_proc.wait(timeout=30)
        redis_proc.terminate()
        redis_proc.wait(timeout=30)
