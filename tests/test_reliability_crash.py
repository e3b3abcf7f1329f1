"""Crash safety with real processes: the API (uvicorn) and `proxpose worker` subprocesses on a
real Redis, the real engine. Workers are SIGKILLed in the middle of estimates, stopped cold,
and the API is killed and restarted; no job or result may be lost.

The lease is short here (PROXPOSE_JOB_LEASE_S=5) so that a dead worker is noticed in seconds,
and an estimate is started at most twice (PROXPOSE_JOB_MAX_ATTEMPTS=2).
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis
from conftest import RENDER_SCRIPT, REPO, RedisServer, WorkerPool, free_port, log_tails, start_api
from e2e_helpers import R_TRUE, T_TRUE, camera, estimate_request, pose
from PIL import Image

from schemas.settings import get_settings
from service.store import JobStore, Keys

pytestmark = pytest.mark.slow

#: Redis database of this module.
DB = 5
KEYS = Keys("proxpose")
LEASE_S = 5.0
MAX_ATTEMPTS = 2
#: A dead worker's job must be running again within this (the issue's bound), s.
RECOVERY_BOUND_S = 60.0


@dataclass
class Crash:
    env: dict[str, str]
    port: int
    api_proc: subprocess.Popen[bytes]
    api: httpx.Client
    r: redis.Redis
    store: JobStore
    workers: WorkerPool
    logs: Path
    reference: bytes


@pytest.fixture(scope="module")
def crash(redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Crash]:
    root = tmp_path_factory.mktemp("crash")
    data_dir, logs = root / "data", root / "logs"
    logs.mkdir()
    r = redis.Redis.from_url(redis_server.url(DB))
    r.flushdb()
    env = {
        **os.environ,
        "PROXPOSE_REDIS_URL": redis_server.url(DB),
        "PROXPOSE_DATA_DIR": str(data_dir),
        "PROXPOSE_JOB_LEASE_S": str(LEASE_S),
        "PROXPOSE_JOB_MAX_ATTEMPTS": str(MAX_ATTEMPTS),
        "PYTHONUNBUFFERED": "1",
    }
    get_settings.cache_clear()
    renders = {"ref128": {"camera": camera(128), "pose": pose(R_TRUE, T_TRUE), "spp": 32}}
    spec = json.dumps({"data_dir": str(data_dir), "out": str(root), "renders": renders})
    subprocess.run([sys.executable, "-c", RENDER_SCRIPT, spec], env=env, cwd=REPO, check=True)
    port = free_port()
    api_proc = start_api(env, logs / "api.log", port)
    workers = WorkerPool(env, logs, r, KEYS.estimate_queue)
    state = Crash(
        env=env,
        port=port,
        api_proc=api_proc,
        api=httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60.0),
        r=r,
        store=JobStore(r, KEYS, 60),
        workers=workers,
        logs=logs,
        reference=(root / "ref128.png").read_bytes(),
    )
    try:
        yield state
    finally:
        workers.terminate_all()
        state.api_proc.terminate()
        state.api_proc.wait(timeout=30)
        r.flushdb()


# ----------------------------------------------------------------------------- helpers
#: Slow renders (8× the default samples), so that it is still running when it is killed.
LONG = {"spp": 128, "perturbation_spp": 32}
SHORT = {"max_iterations": 3}
#: Far slower (64× the samples): it never ends on its own in a test; it is stopped.
VERY_LONG = {"spp": 1024, "perturbation_spp": 256, "max_iterations": 80}


def submit(crash: Crash, options: dict[str, Any], image: bytes | None = None) -> str:
    files = {"image": ("ref.png", image or crash.reference, "image/png")}
    data = {"request": json.dumps(estimate_request(128, **options))}
    response = crash.api.post("/v1/estimates", files=files, data=data)
    assert response.status_code == 202, response.text
    return str(response.json()["id"])


def job(crash: Crash, job_id: str) -> dict[str, Any]:
    return crash.api.get(f"/v1/estimates/{job_id}").json()  # type: ignore[no-any-return]


def wait_for(crash: Crash, job_id: str, until: set[str], timeout_s: float = 90.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while (state := job(crash, job_id))["status"] not in until:
        assert time.monotonic() < deadline, f"job stuck: {state}\n{log_tails(crash.logs)}"
        time.sleep(0.1)
    return state


def wait_running(
    crash: Crash, job_id: str, attempt: int, timeout_s: float = 60.0, iterations: int = 1
) -> str:
    """Wait until attempt ``attempt`` of the job runs and has done ``iterations``; its worker's
    name."""
    deadline = time.monotonic() + timeout_s
    while True:
        record = crash.store.get(job_id)
        assert record is not None
        done = record.progress["iteration"] if record.progress else 0
        if record.status == "running" and record.attempts == attempt and done >= iterations:
            assert record.worker is not None
            return record.worker
        assert record.status in ("queued", "running"), f"{record}\n{log_tails(crash.logs)}"
        assert time.monotonic() < deadline, f"not running: {record}\n{log_tails(crash.logs)}"
        time.sleep(0.02)


def failure(crash: Crash, *states: dict[str, Any]) -> str:
    return f"jobs: {[(s['status'], s['error']) for s in states]}\n{log_tails(crash.logs)}"


# ----------------------------------------------------------------------------- tests
def test_a_worker_killed_mid_estimate_does_not_lose_the_job(crash: Crash) -> None:
    crash.workers.ensure(2)
    job_id = submit(crash, LONG)
    victim = wait_running(crash, job_id, attempt=1)
    crash.workers.kill(victim)  # SIGKILL: no handler runs, nothing is written
    killed_at = time.monotonic()
    wait_running(crash, job_id, attempt=2, timeout_s=RECOVERY_BOUND_S, iterations=0)
    rerun_after_s = time.monotonic() - killed_at
    final = wait_for(crash, job_id, {"succeeded", "failed", "cancelled"})
    assert final["status"] == "succeeded", failure(crash, final)
    assert final["attempts"] == 2 and final["result"]["converged"]
    assert final["progress"]["iteration"] == final["result"]["iterations"]
    assert LEASE_S - 1.0 < rerun_after_s < LEASE_S + 5.0, rerun_after_s
    record = crash.store.get(job_id)
    assert record is not None and record.worker != victim
    assert [lost["worker"] for lost in record.lost] == [victim]
    assert crash.api.get(f"/v1/estimates/{job_id}/artifacts/difference").status_code == 200


def test_a_job_that_kills_its_workers_fails_after_max_attempts_and_the_queue_goes_on(
    crash: Crash,
) -> None:
    crash.workers.ensure(3)
    poison = submit(crash, LONG)
    victims = []
    for attempt in range(1, MAX_ATTEMPTS + 1):
        victims.append(wait_running(crash, poison, attempt, timeout_s=RECOVERY_BOUND_S))
        crash.workers.kill(victims[-1])
        if attempt == 1:
            other = submit(crash, SHORT)  # queued behind the requeued poison job
    final = wait_for(crash, poison, {"succeeded", "failed", "cancelled"}, RECOVERY_BOUND_S)
    assert final["status"] == "failed", failure(crash, final)
    assert final["error"]["code"] == "worker_lost"
    assert f"{MAX_ATTEMPTS} attempts" in final["error"]["message"]
    assert final["attempts"] == MAX_ATTEMPTS and final["result"] is None
    assert "Traceback" not in json.dumps(final) and "lost" not in final
    record = crash.store.get(poison)
    assert record is not None and [lost["worker"] for lost in record.lost] == victims
    survivor = wait_for(crash, other, {"succeeded", "failed", "cancelled"})
    assert survivor["status"] == "succeeded" and survivor["attempts"] == 1, failure(crash, survivor)
    metrics = crash.api.get("/metrics").text
    assert 'proxpose_job_failures_total{code="worker_lost",kind="estimate"}' in metrics


def test_a_worker_stopped_cold_gives_its_job_back_at_once(crash: Crash) -> None:
    crash.workers.ensure(2)
    job_id = submit(crash, VERY_LONG)
    name = wait_running(crash, job_id, attempt=1)
    proc = crash.workers.procs.pop(name)
    proc.send_signal(signal.SIGTERM)  # warm: would let the job finish
    time.sleep(1.2)  # RQ ignores a second signal within 1 s
    proc.send_signal(signal.SIGTERM)  # cold: the job is interrupted
    stopped_at = time.monotonic()
    wait_running(crash, job_id, attempt=2, timeout_s=RECOVERY_BOUND_S, iterations=0)
    assert time.monotonic() - stopped_at < LEASE_S, "requeued by the lease, not given back"
    proc.wait(timeout=30)
    assert crash.api.delete(f"/v1/estimates/{job_id}").status_code == 202  # no need to finish
    final = wait_for(crash, job_id, {"succeeded", "failed", "cancelled"})
    assert final["status"] == "cancelled" and final["attempts"] == 2, failure(crash, final)


def test_the_api_restarts_without_losing_jobs_or_results(crash: Crash) -> None:
    crash.workers.ensure(1)
    done = submit(crash, SHORT)
    before = wait_for(crash, done, {"succeeded", "failed", "cancelled"})
    assert before["status"] == "succeeded", failure(crash, before)
    artifact = crash.api.get(f"/v1/estimates/{done}/artifacts/overlay_final").content
    waiting = [submit(crash, SHORT) for _ in range(2)]
    crash.api_proc.kill()  # SIGKILL the API mid-flight
    crash.api_proc.wait()
    crash.api_proc = start_api(crash.env, crash.logs / "api.log", crash.port)
    after = job(crash, done)
    assert after["result"] == before["result"] and after["status"] == "succeeded"
    assert crash.api.get(f"/v1/estimates/{done}/artifacts/overlay_final").content == artifact
    for job_id in waiting:
        final = wait_for(crash, job_id, {"succeeded", "failed", "cancelled"})
        assert final["status"] == "succeeded", failure(crash, final)
    listed = {j["id"] for j in crash.api.get("/v1/estimates?limit=100").json()["items"]}
    assert {done, *waiting} <= listed


def test_unusable_estimates_fail_with_a_code_not_a_crash(crash: Crash) -> None:
    crash.workers.ensure(1)
    black = io.BytesIO()
    Image.new("RGB", (128, 128)).save(black, format="PNG")
    featureless = submit(crash, SHORT, image=black.getvalue())
    request = estimate_request(128, **SHORT)
    request["initial_pose"]["t"] = [60.0, 0.0, 14.0]  # the target far outside the view
    files = {"image": ("ref.png", crash.reference, "image/png")}
    response = crash.api.post("/v1/estimates", files=files, data={"request": json.dumps(request)})
    invisible = response.json()["id"]
    for job_id, code in ((featureless, "too_few_features"), (invisible, "empty_render")):
        final = wait_for(crash, job_id, {"succeeded", "failed", "cancelled"})
        assert final["status"] == "failed" and final["error"]["code"] == code, failure(crash, final)
        assert final["attempts"] == 1  # a clean failure is not retried
        assert "Traceback" not in final["error"]["message"]
    assert len(crash.workers.procs) == 1 and all(
        p.poll() is None for p in crash.workers.procs.values()
    )


def test_an_internal_error_or_a_timeout_keeps_its_traceback_in_the_record_only(
    crash: Crash,
) -> None:
    crash.workers.ensure(1)
    blocker = submit(crash, VERY_LONG)  # keeps the one worker busy while two are altered
    broken, slow = submit(crash, SHORT), submit(crash, VERY_LONG)
    crash.r.hset(KEYS.job(broken), "request", '{"camera": 1}')  # a bug's stored record
    crash.r.hset(KEYS.job(slow), "timeout_s", "1")  # as if submitted with a 1 s timeout
    assert crash.api.delete(f"/v1/estimates/{blocker}").status_code in (200, 202)
    for job_id, code in ((broken, "internal_error"), (slow, "timeout")):
        final = wait_for(crash, job_id, {"succeeded", "failed", "cancelled"})
        assert final["status"] == "failed" and final["error"]["code"] == code, failure(crash, final)
        answer = crash.api.get(f"/v1/estimates/{job_id}").text
        assert "Traceback (most recent" not in answer and '"traceback"' not in answer
        stored = crash.r.hget(KEYS.job(job_id), "traceback")
        assert stored is not None and b"Traceback (most recent call last)" in stored
    assert b"ValidationError" in crash.r.hget(KEYS.job(broken), "traceback")  # type: ignore[operator]
    assert "1 s" in job(crash, slow)["error"]["message"]
    logs = (crash.logs / f"{next(iter(crash.workers.procs))}.log").read_text()
    lines = [json.loads(line) for line in logs.splitlines() if line.startswith("{")]
    assert any(e.get("job_id") == broken and e["level"] == "ERROR" and "exc" in e for e in lines)
