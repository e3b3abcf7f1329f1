"""End to end on the S3-compatible backend: the API (uvicorn) and `proxpose worker` processes
sharing Redis and a bucket of a real S3-compatible server process (moto's), the real engine.
A real estimate leaves its bytes in the bucket and a few kB in Redis; a worker that cannot
reach the store gives the job back like a lost worker and fails it with ``store_unavailable``
on its last attempt."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator

import httpx
import pytest
import redis
from blob_helpers import S3Server
from blob_helpers import s3_server as s3_server  # noqa: F401 (fixture)
from conftest import RENDER_SCRIPT, REPO, RedisServer, WorkerPool, free_port, start_api
from e2e_helpers import (
    ARTIFACTS,
    KEYS,
    R_TRUE,
    T_TRUE,
    Stack,
    assert_job_redis_budget,
    assert_png,
    camera,
    estimate_request,
    failure,
    pose,
    submit,
    wait_for,
)

from schemas.settings import get_settings

pytestmark = pytest.mark.slow

#: Redis database of this module.
DB = 13


@pytest.fixture(scope="module", name="stack")
def s3_stack(
    redis_server: RedisServer,
    s3_server: S3Server,  # noqa: F811
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[Stack]:
    """The API and a worker pool on Redis database DB and a fresh bucket, one reference."""
    root = tmp_path_factory.mktemp("blobs-e2e")
    logs = root / "logs"
    logs.mkdir()
    r = redis.Redis.from_url(redis_server.url(DB))
    r.flushdb()
    bucket = s3_server.new_bucket()
    env = {
        **os.environ,
        **s3_server.env(bucket),
        "PROXPOSE_REDIS_URL": redis_server.url(DB),
        "PROXPOSE_DATA_DIR": str(root / "api"),  # the API's and the workers' disks differ:
        "PYTHONUNBUFFERED": "1",  # they share only Redis and the bucket
    }
    get_settings.cache_clear()
    renders = {"ref128": {"camera": camera(128), "pose": pose(R_TRUE, T_TRUE), "spp": 32}}
    spec = json.dumps({"data_dir": str(root / "refs"), "out": str(root), "renders": renders})
    render = subprocess.Popen([sys.executable, "-c", RENDER_SCRIPT, spec], env=env, cwd=REPO)
    api = start_api(env, logs / "api.log", free_port())
    port = api.args[-3]  # type: ignore[index]
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120.0)
    workers = WorkerPool(
        {**env, "PROXPOSE_DATA_DIR": str(root / "worker")}, logs, r, KEYS.estimate_queue
    )
    try:
        assert render.wait(timeout=300) == 0, "reference render failed"
        references = {"ref128": (root / "ref128.png").read_bytes()}
        yield Stack(client, r, workers, root / "worker", logs, references)
    finally:
        try:
            workers.stop_all()
        finally:
            for proc in (*workers.procs.values(), api, render):
                proc.terminate()
                proc.wait(timeout=30)
            r.flushdb()


def test_a_real_estimate_keeps_its_bytes_in_the_bucket(stack: Stack, s3_server: S3Server) -> None:  # noqa: F811
    stack.workers.ensure(1)
    job_id = submit(stack, estimate_request(128, max_iterations=6)).json()["id"]
    job, _ = wait_for(stack, job_id, {"succeeded", "failed", "cancelled"})
    assert job["status"] == "succeeded", failure(stack, job)
    assert set(job["artifacts"]) == ARTIFACTS
    for url in job["artifacts"].values():
        got = stack.api.get(url)
        assert got.status_code == 200 and got.headers["content-type"] == "image/png"
        assert_png(got.content)
        again = stack.api.get(url, headers={"If-None-Match": got.headers["etag"]})
        assert again.status_code == 304
    assert_job_redis_budget(stack.r, job)
    biggest = max(int(stack.r.memory_usage(k) or 0) for k in stack.r.scan_iter())
    assert biggest < 64 * 1024, biggest  # no PNG, image or model file sits in Redis
    metrics = stack.api.get("/metrics").text
    assert "proxpose_redis_used_memory_bytes" in metrics


def test_a_worker_that_cannot_reach_the_store_fails_the_job_clearly(stack: Stack) -> None:
    stack.workers.stop_all()
    broken = {**stack.workers.env, "PROXPOSE_BLOB_STORE": "s3://no-such-bucket/x"}
    broken["PROXPOSE_JOB_MAX_ATTEMPTS"] = "2"
    pool = WorkerPool(broken, stack.logs, stack.r, KEYS.estimate_queue)
    try:
        pool.ensure(1)
        job_id = submit(stack, estimate_request(128, max_iterations=3)).json()["id"]
        job, seen = wait_for(stack, job_id, {"succeeded", "failed", "cancelled"}, timeout_s=90)
        assert job["status"] == "failed", failure(stack, job)
        assert job["error"]["code"] == "store_unavailable", job["error"]
        assert "blob store" in job["error"]["message"] and "2 attempts" in job["error"]["message"]
        assert job["attempts"] == 2  # given back once, like a lost worker, then failed
    finally:
        pool.terminate_all()
