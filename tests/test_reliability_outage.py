"""Workers ride out a Redis outage: a Redis with the append-only file on (as a team deploys it)
is SIGKILLed while two standalone `proxpose worker` processes run and wait for jobs, and
restarted from its AOF a few seconds later; then once more while both wait for jobs. Every
accepted job succeeds, exactly once; the same worker processes are still alive afterwards and
run a job submitted after the restart; and each worker logged the outage, not one traceback
per retry."""

from __future__ import annotations

import json
import os
import re
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
from e2e_helpers import R_TRUE, T_TRUE, camera, estimate_request, pose
from test_reliability_redis import FSYNC_S, start_redis, wait_for

from schemas.settings import get_settings
from service.store import Keys

pytestmark = pytest.mark.slow

KEYS = Keys("proxpose")
#: How long Redis stays down, s.
OUTAGE_S = 3.0


def _env(tmp_path: Path, port: int) -> dict[str, str]:
    return {
        **os.environ,
        "PROXPOSE_REDIS_URL": f"redis://127.0.0.1:{port}/0",
        "PROXPOSE_DATA_DIR": str(tmp_path / "data"),
        "PROXPOSE_LOG_FORMAT": "json",
        "PYTHONUNBUFFERED": "1",
    }


def _render_reference(tmp_path: Path, env: dict[str, str]) -> bytes:
    spec = {
        "data_dir": str(tmp_path / "data"),
        "out": str(tmp_path),
        "renders": {"ref": {"camera": camera(128), "pose": pose(R_TRUE, T_TRUE), "spp": 32}},
    }
    subprocess.run(
        [sys.executable, "-c", RENDER_SCRIPT, json.dumps(spec)], env=env, check=True, cwd=REPO
    )
    return (tmp_path / "ref.png").read_bytes()


def _outage(redis_proc: subprocess.Popen[bytes], port: int, data: Path, logs: Path) -> Any:
    """SIGKILL Redis, keep it down for OUTAGE_S, restart it from its AOF."""
    redis_proc.send_signal(signal.SIGKILL)
    redis_proc.wait()
    time.sleep(OUTAGE_S)
    return start_redis(port, data, logs / "redis.log")


def _check_logs(logs: Path, names: list[str], job_ids: list[str]) -> None:
    """Nothing finished twice, and the outage is logged once per part, without tracebacks."""
    worker_logs = "".join((logs / f"{name}.log").read_text() for name in names)
    for job_id in job_ids:
        succeeded = re.findall(rf"job {job_id}: attempt \d+ ended: succeeded", worker_logs)
        assert len(succeeded) == 1, (job_id, succeeded)
    for name in names:
        lines = (logs / f"{name}.log").read_text().splitlines()
        outage = [line for line in lines if "Redis is unreachable" in line]
        assert outage, f"{name} did not log the outage"
        # once per part (worker, lease, progress, ...), not per retry
        assert len(outage) <= 8, outage
        assert not any("unhandled exception, quitting" in line for line in lines)
        retries = [line for line in lines if "could not connect to Redis" in line]
        assert len(retries) <= 2, retries  # RQ's own retry line: once per outage


def test_workers_survive_a_redis_outage_and_every_job_succeeds_once(tmp_path: Path) -> None:
    data, logs = tmp_path / "redis", tmp_path / "logs"
    data.mkdir()
    logs.mkdir()
    port = free_port()
    env = _env(tmp_path, port)
    get_settings.cache_clear()
    reference = _render_reference(tmp_path, env)
    redis_proc = start_redis(port, data, logs / "redis.log")
    r = redis.Redis(port=port)
    api_port = free_port()
    api_proc = start_api(env, logs / "api.log", api_port)
    api = httpx.Client(base_url=f"http://127.0.0.1:{api_port}", timeout=60.0)
    workers = WorkerPool(env, logs, r, KEYS.estimate_queue)

    def submit() -> str:
        files = {"image": ("ref.png", reference, "image/png")}
        request = json.dumps(estimate_request(128, max_iterations=6))
        response = api.post("/v1/estimates", files=files, data={"request": request})
        assert response.status_code == 202, response.text
        return str(response.json()["id"])

    def alive() -> bool:
        return all(proc.poll() is None for proc in workers.procs.values())

    try:
        workers.ensure(2)
        pids = {name: proc.pid for name, proc in workers.procs.items()}
        accepted = [submit() for _ in range(4)]
        deadline = time.monotonic() + 120
        while api.get(f"/v1/estimates/{accepted[0]}").json()["status"] != "running":
            assert time.monotonic() < deadline, log_tails(logs)
            time.sleep(0.1)
        time.sleep(max(FSYNC_S + 0.5, 1.5))  # on disk, and the first job well into its run

        redis_proc.send_signal(signal.SIGKILL)
        redis_proc.wait()
        down = api.get(f"/v1/estimates/{accepted[0]}")
        assert down.status_code == 503 and int(down.headers["Retry-After"]) > 0
        assert down.headers["content-type"].startswith("application/problem+json")
        time.sleep(OUTAGE_S)
        assert alive(), log_tails(logs)
        redis_proc = start_redis(port, data, logs / "redis.log")

        accepted.append(submit())  # the API recovers by itself
        finals = [
            wait_for(api, job_id, {"succeeded", "failed", "cancelled"}, logs) for job_id in accepted
        ]
        assert [f["status"] for f in finals] == ["succeeded"] * len(accepted), (
            [(f["status"], f["error"]) for f in finals],
            log_tails(logs),
        )
        # the same processes, alive and registered again
        assert {name: proc.pid for name, proc in workers.procs.items()} == pids and alive()
        deadline = time.monotonic() + 30
        while not set(pids) <= workers.registered():
            assert time.monotonic() < deadline, log_tails(logs)
            time.sleep(0.2)
        # a second outage while both workers wait for jobs (RQ's loop between jobs)
        redis_proc = _outage(redis_proc, port, data, logs)
        after = submit()
        assert wait_for(api, after, {"succeeded", "failed"}, logs)["status"] == "succeeded"
        assert {name: proc.pid for name, proc in workers.procs.items()} == pids
        assert alive(), log_tails(logs)
    finally:
        workers.terminate_all()
        api_proc.terminate()
        api_proc.wait(timeout=30)
        redis_proc.terminate()
        redis_proc.wait(timeout=30)
    _check_logs(logs, list(pids), [*accepted, after])
