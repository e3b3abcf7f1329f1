"""Estimate submissions stored on the event loop (service/inline.py): which submissions go there,
and what happens when Redis hangs (a real redis-server stopped with SIGSTOP): the submission on
the loop answers 503 within the inline client's timeout, the loop answers other requests
again at once, and the next submissions go through the thread pool until the pause ends; the
readiness probe answers 503 in bounded time too. A narrow unit test with a fake clock pins the
pause rules beside the real ones."""

from __future__ import annotations

import asyncio
import io
import logging
import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import redis
from conftest import settings_on_redis, start_redis_server
from fastapi.testclient import TestClient
from PIL import Image
from service_api_helpers import base_request, submit

from schemas.settings import get_settings
from service import inline, ratelimit
from service.inline import INLINE_MAX_IMAGE_BYTES, InlineSubmissions
from service.main import REDIS_COMMAND_TIMEOUT_S, create_app
from service.routes import health
from service.store.blobs import CountingBlobStore, FileBlobStore

DB = 13
POOL_THREAD = "AnyIO worker thread"  # the name of the thread pool's threads


def queued_in(caplog: pytest.LogCaptureFixture) -> list[str]:
    """The thread names of the "estimate … queued" log records so far."""
    return [
        rec.threadName or ""
        for rec in caplog.records
        if rec.name == "service.routes.estimates" and "queued" in rec.getMessage()
    ]


def noise_png(side: int) -> bytes:
    pixels = np.random.default_rng(0).integers(0, 256, (side, side, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def big_request(side: int) -> dict[str, Any]:
    c = (side - 1) / 2
    camera = {"width": side, "height": side, "fx": side, "fy": side, "cx": c, "cy": c}
    return base_request(camera=camera)


def test_small_submissions_run_on_the_loop_large_ones_in_the_pool(
    redis_server: Any,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    big = noise_png(1024)
    assert len(big) > INLINE_MAX_IMAGE_BYTES
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch):
        with caplog.at_level(logging.INFO, "service.routes.estimates"):
            with TestClient(create_app()) as client:
                assert submit(client).status_code == 202
                assert submit(client, big_request(1024), big).status_code == 202
    small, large = queued_in(caplog)
    assert small != POOL_THREAD and large == POOL_THREAD, (small, large)


def test_inline_submissions_can_be_turned_off(
    redis_server: Any,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    env = {"PROXPOSE_INLINE_SUBMISSIONS": "false"}
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch, env):
        with caplog.at_level(logging.INFO, "service.routes.estimates"):
            with TestClient(create_app()) as client:
                assert submit(client).status_code == 202
    assert queued_in(caplog) == [POOL_THREAD]


@pytest.fixture
def private_redis(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], str]]:
    """A redis-server of this test's own (it is stopped and continued)."""
    server = start_redis_server(tmp_path)
    try:
        yield server.proc, server.url(0)
    finally:
        os.kill(server.proc.pid, signal.SIGCONT)
        server.proc.kill()
        server.proc.wait()


@pytest.mark.parametrize("rate_limit", [True, False], ids=["rate-limited", "no-rate-limit"])
def test_a_hung_redis_holds_the_loop_once_then_submissions_go_to_the_pool(
    rate_limit: bool,
    private_redis: tuple[subprocess.Popen[bytes], str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """With the rate limit on, its Redis call is the first to meet the hung Redis; without
    it, the submission's own."""
    proc, url = private_redis
    monkeypatch.setenv("PROXPOSE_REDIS_URL", url)
    monkeypatch.setenv("PROXPOSE_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("PROXPOSE_SUBMISSIONS_PER_MINUTE", "600" if rate_limit else "0")
    get_settings.cache_clear()

    def timed_submit(client: TestClient) -> tuple[Any, float]:
        start = time.monotonic()
        response = submit(client)
        return response, time.monotonic() - start

    try:
        with caplog.at_level(logging.INFO):
            with TestClient(create_app()) as client:
                assert submit(client).status_code == 202  # on the loop
                os.kill(proc.pid, signal.SIGSTOP)
                hung, took = timed_submit(client)
                assert hung.status_code == 503 and hung.headers["retry-after"], hung.text
                # one socket timeout (a timeout is not retried), plus the request's own time
                assert took < inline.SOCKET_TIMEOUT_S + 1.5, took
                assert client.get("/static/favicon.svg").status_code == 200  # the loop is free
                if rate_limit:  # paused: the limit's async call, bounded
                    hung, took = timed_submit(client)
                    assert hung.status_code == 503, hung.text
                    assert ratelimit.ADMIT_TIMEOUT_S <= took < ratelimit.ADMIT_TIMEOUT_S + 1.5
                os.kill(proc.pid, signal.SIGCONT)
                # still paused: the next submission goes through the pool, and succeeds
                assert submit(client).status_code == 202
                metrics = client.get("/metrics").text
                assert "proxpose_inline_submissions_paused_total 1.0" in metrics
                subs = client.app.state.inline  # type: ignore[attr-defined]
                subs.clock = lambda: time.monotonic() + inline.PAUSE_S  # the pause is over
                assert submit(client).status_code == 202  # on the loop again
    finally:
        get_settings.cache_clear()
    threads = queued_in(caplog)
    assert len(threads) == 3 and threads[0] != POOL_THREAD, threads
    assert threads[1] == POOL_THREAD and threads[2] != POOL_THREAD, threads
    paused = [m for m in caplog.messages if "submissions go through the thread pool" in m]
    assert len(paused) == 1 and "TimeoutError" in paused[0], paused


def test_readiness_and_polls_answer_503_soon_when_redis_hangs(
    private_redis: tuple[subprocess.Popen[bytes], str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A readiness probe against a hung Redis: 503 within READY_WAIT_S; a status poll (the
    sync client, in a thread) within one REDIS_COMMAND_TIMEOUT_S, a timeout not retried (it
    took 4 × 65 s); ready again once Redis answers."""
    proc, url = private_redis
    monkeypatch.setenv("PROXPOSE_REDIS_URL", url)
    monkeypatch.setenv("PROXPOSE_DATA_DIR", str(tmp_path))
    get_settings.cache_clear()
    try:
        with TestClient(create_app()) as client:
            assert client.get("/readyz").status_code == 200
            os.kill(proc.pid, signal.SIGSTOP)
            start = time.monotonic()
            hung = client.get("/readyz")
            took = time.monotonic() - start
            assert hung.status_code == 503 and hung.headers["retry-after"], hung.text
            assert hung.json()["redis"] is False and "Redis unreachable" in hung.json()["reason"]
            assert took < health.READY_WAIT_S + 1.5, took
            start = time.monotonic()
            poll = client.get("/v1/estimates/" + "0" * 32)
            took = time.monotonic() - start
            assert poll.status_code == 503 and poll.headers["retry-after"], poll.text
            assert took < REDIS_COMMAND_TIMEOUT_S + 1.5, took
            os.kill(proc.pid, signal.SIGCONT)
            deadline = time.monotonic() + 10.0
            while client.get("/readyz").status_code != 200:
                assert time.monotonic() < deadline
                time.sleep(0.1)
    finally:
        get_settings.cache_clear()


# ----------------------------------------------------------------------------- unit, fake clock
class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class FakeS3:
    url = "s3://bucket/prefix"
    description = "S3"


def files(tmp_path: Path) -> CountingBlobStore:
    return CountingBlobStore(FileBlobStore(tmp_path))


def test_usable_only_for_small_images_on_the_file_store_and_with_a_client(
    tmp_path: Path,
) -> None:
    r = redis.Redis()  # never connected here
    assert InlineSubmissions(r, files(tmp_path)).usable(1000)
    assert not InlineSubmissions(r, files(tmp_path)).usable(INLINE_MAX_IMAGE_BYTES + 1)
    assert not InlineSubmissions(r, CountingBlobStore(FakeS3())).usable(1000)  # type: ignore[arg-type]
    assert not InlineSubmissions(None, files(tmp_path)).usable(1000)


def test_a_failure_or_a_slow_submission_pauses_inline_runs(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    clock = Clock()
    subs = InlineSubmissions(redis.Redis(), files(tmp_path), clock=clock)
    loop_thread: list[str] = []

    def on_loop(_r: redis.Redis) -> str:
        loop_thread.append(threading.current_thread().name)
        return "inline"

    def failing(_r: redis.Redis) -> str:
        raise redis.ConnectionError("gone")

    def slow(_r: redis.Redis) -> str:
        clock.now += inline.SLOW_S * 2
        return "inline"

    async def run(work: Any) -> str:
        return await subs.run(1000, work, lambda: "pooled")

    with caplog.at_level(logging.WARNING, "service.inline"):
        assert asyncio.run(run(on_loop)) == "inline"
        with pytest.raises(redis.ConnectionError):
            asyncio.run(run(failing))
        assert asyncio.run(run(on_loop)) == "pooled"
        clock.now += inline.PAUSE_S
        assert asyncio.run(run(on_loop)) == "inline"
        assert asyncio.run(run(slow)) == "inline"  # answered, but the next ones are pooled
        assert asyncio.run(run(on_loop)) == "pooled"
    assert len(caplog.messages) == 2, caplog.messages
    assert "ConnectionError" in caplog.messages[0] and "ms on the loop" in caplog.messages[1]
    assert loop_thread == [threading.current_thread().name] * 2
