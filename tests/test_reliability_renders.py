"""``POST /v1/renders`` waits for its worker without holding a thread: a real API process
(uvicorn) with more renders in flight than its thread pool has threads (anyio's 40) still answers
the sync routes at once, and every render ends in a clear 504 when no worker takes it."""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

import httpx
import pytest
import redis
from conftest import RedisServer, free_port, start_api
from rq import Queue, Worker
from service_api_helpers import base_request

from service.store import Keys

pytestmark = pytest.mark.slow

KEYS = Keys("proxpose")
#: Renders in flight at once: more than the thread pool (40 threads).
RENDERS = 50
#: How long each render waits for a worker, s.
RENDER_TIMEOUT_S = 6.0
#: Slowest answer allowed to a status poll while the renders wait, s.
POLL_MAX_S = 1.0


async def _renders_and_polls(url: str) -> tuple[list[httpx.Response], list[float], list[int]]:
    body = {
        "model_id": "demo-sat",
        "camera": base_request()["camera"],
        "pose": base_request()["initial_pose"],
    }
    limits = httpx.Limits(max_connections=RENDERS + 8)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=60.0) as client:
        renders = [
            asyncio.create_task(client.post("/v1/renders", json=body)) for _ in range(RENDERS)
        ]
        await asyncio.sleep(1.5)  # every render is in its wait
        poll_s, statuses = [], []
        for path in ("/v1/estimates/nope", "/v1/models", "/v1/estimates") * 4:
            start = time.perf_counter()
            response = await client.get(path)
            poll_s.append(time.perf_counter() - start)
            statuses.append(response.status_code)
        in_flight = sum(not task.done() for task in renders)
        assert in_flight == RENDERS, f"only {in_flight} renders still waiting during the polls"
        return await asyncio.gather(*renders), poll_s, statuses


def test_renders_in_flight_do_not_stall_other_routes(
    tmp_path: Path, redis_server: RedisServer
) -> None:
    url_redis = redis_server.url(7)
    r = redis.Redis.from_url(url_redis)
    r.flushdb()
    env = {
        **os.environ,
        "PROXPOSE_REDIS_URL": url_redis,
        "PROXPOSE_DATA_DIR": str(tmp_path / "data"),
        "PROXPOSE_RENDER_TIMEOUT_S": str(RENDER_TIMEOUT_S),
        "PROXPOSE_SUBMISSIONS_PER_MINUTE": "0",
    }
    for name in ("PROXPOSE_API_KEYS", "PROXPOSE_ADMIN_API_KEYS"):
        env.pop(name, None)
    # a worker registered and alive that never takes a job: every render waits its full time
    idle = Worker([Queue(KEYS.estimate_queue, connection=r)], connection=r, name="idle")
    idle.register_birth()
    port = free_port()
    api = start_api(env, tmp_path / "api.log", port)
    try:
        started = time.monotonic()
        renders, poll_s, statuses = asyncio.run(_renders_and_polls(f"http://127.0.0.1:{port}"))
        elapsed = time.monotonic() - started
    finally:
        idle.register_death()
        api.terminate()
        api.wait(timeout=30)
        r.flushdb()
    assert statuses == [404, 200, 200] * 4
    assert max(poll_s) < POLL_MAX_S, f"polls took up to {max(poll_s):.2f} s behind the renders"
    assert [response.status_code for response in renders] == [504] * RENDERS, renders[0].text
    problem = renders[0].json()
    assert problem["code"] == "timeout" and f"{RENDER_TIMEOUT_S:g} s" in problem["detail"]
    assert renders[0].headers["content-type"].startswith("application/problem+json")
    # all waited together: about one timeout, not RENDERS / 40 of them one after the other
    assert elapsed < 2 * RENDER_TIMEOUT_S + 3.0, f"{RENDERS} renders took {elapsed:.1f} s"
    assert r.llen(f"rq:queue:{KEYS.render_queue}") == 0  # each withdrew its job
    print(f"{RENDERS} renders in flight: polls max {1000 * max(poll_s):.1f} ms")
