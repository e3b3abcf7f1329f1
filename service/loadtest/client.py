"""The load test's clients. A :class:`Run` readies the service (a worker alive, the reference
rendered at the true pose), then ``--clients`` asyncio tasks each submit an estimate, poll it to
its end and take the next; at the deadline the unfinished jobs are cancelled. A :class:`JobRun`
records what one estimate went through, as this client saw it."""

from __future__ import annotations

import asyncio
import json
import random
import time
import uuid
from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING, Any

from service.client import Client, ProxposeClientError
from service.loadtest.accuracy import rss
from service.loadtest.config import Config, LoadTestError
from service.loadtest.poses import perturbed_pose

if TYPE_CHECKING:
    import httpx

#: Samples per pixel of the reference render.
REFERENCE_SPP = 32
#: Longest wait for the service to be ready (a worker alive), s.
READY_TIMEOUT_S = 60.0
#: Interval of the probe of this client's event-loop lag, s.
LOOP_PROBE_S = 0.05
#: Per-request HTTP timeout, s (a render waits for a worker: longer).
REQUEST_TIMEOUT_S = 30.0
RENDER_TIMEOUT_S = 120.0
#: Retries of a submission after a dropped connection or a 503 (a 429 is retried until the
#: deadline, as its Retry-After says).
SUBMIT_RETRIES = 5
TERMINAL = frozenset({"succeeded", "failed", "cancelled"})


@dataclass
class JobRun:
    """What one estimate went through, as this client saw it (times in seconds)."""

    index: int
    idempotency_key: str
    client: int | None = None  # which client ran it
    first_of_client: bool = False  # that client's first submission (the first wave)
    job_id: str | None = None
    submit_latency_s: float | None = None  # the accepted (202) POST
    submit_attempts: int = 0
    throttled: int = 0  # 429 answers before acceptance
    throttled_latency_s: list[float] = field(default_factory=list)
    submit_retries: int = 0  # dropped connections, 503s, 409s
    submit_error: str | None = None  # never accepted: why
    poll_latency_s: list[float] = field(default_factory=list)
    poll_errors: int = 0
    status: str | None = None  # last status seen
    error_code: str | None = None
    attempts: int | None = None  # worker starts, as the service counts them
    created_at: str | None = None
    started_at: str | None = None
    finished_at: str | None = None
    queue_wait_s: float | None = None
    run_time_s: float | None = None
    end_to_end_s: float | None = None  # submit sent → end seen
    submitted_at_s: float | None = None  # since the run started
    ended_at_s: float | None = None
    converged: bool | None = None
    iterations: int | None = None
    rotation_error_deg: float | None = None
    translation_error: float | None = None
    # the stated accuracy: root-sum-square of the reported 1-σ per axis (None: no covariance)
    sigma_rotation_deg: float | None = None
    sigma_translation: float | None = None

    @property
    def terminal(self) -> bool:
        return self.status in TERMINAL


def _typed_client(config: Config) -> Client:
    """The typed client for the setup calls: never through a proxy (an explicit transport
    turns the environment's proxies off), a render wait of up to RENDER_TIMEOUT_S."""
    import httpx

    return Client(
        config.url,
        api_key=config.api_key,
        timeout_s=RENDER_TIMEOUT_S,
        retries=2,
        max_retry_wait_s=2.0,
        transport=httpx.HTTPTransport(),
    )


def _seconds_between(a: str | None, b: str | None) -> float | None:
    if not a or not b:
        return None
    return (datetime.fromisoformat(b) - datetime.fromisoformat(a)).total_seconds()


def _absorb(job: JobRun, body: dict[str, Any]) -> None:
    """Copy the job resource's status, times and outcome into ``job``."""
    job.status = body.get("status")
    job.attempts = body.get("attempts")
    job.created_at = body.get("created_at")
    job.started_at = body.get("started_at")
    job.finished_at = body.get("finished_at")
    job.queue_wait_s = _seconds_between(job.created_at, job.started_at)
    job.run_time_s = _seconds_between(job.started_at, job.finished_at)
    error = body.get("error") or {}
    job.error_code = error.get("code")
    result = body.get("result") or {}
    job.converged = result.get("converged")
    job.iterations = result.get("iterations")
    errors = result.get("errors") or {}
    job.rotation_error_deg = errors.get("rotation_deg")
    job.translation_error = errors.get("translation")
    covariance = result.get("covariance") or {}
    job.sigma_rotation_deg = rss(covariance.get("sigma_rotation_deg"))
    job.sigma_translation = rss(covariance.get("sigma_translation"))


def _retry_after_s(response: httpx.Response, default: float = 1.0) -> float:
    try:
        return max(0.05, float(response.headers.get("retry-after", default)))
    except ValueError:
        return default


class Run:
    """One load test against a ready service."""

    def __init__(self, config: Config, client: httpx.AsyncClient) -> None:
        self.config = config
        self.client = client
        self.t0 = time.monotonic()
        self.deadline = self.t0 + config.timeout_s
        self.jobs = [JobRun(i, f"loadtest-{uuid.uuid4().hex}") for i in range(config.jobs)]
        self._next = 0
        self.reference = b""
        self.base_request: dict[str, Any] = {}
        self.workers = 0
        self.setup_s = 0.0
        self.t_start = self.t0  # when the clients started (set by clients())
        self.loop_lag_s: list[float] = []
        self.metrics_before: str | None = None
        self.metrics_after: str | None = None
        self.client_cpu = 0.0  # CPU seconds of this process per second while the clients ran

    def remaining(self) -> float:
        return self.deadline - time.monotonic()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, min(seconds, self.remaining())))

    # ------------------------------------------------------------------ setup
    async def prepare(self) -> None:
        """Wait for a worker, frame the model, render the reference at the true pose. The
        readiness probe and the render go through the typed client (:mod:`service.client`, sync:
        in a thread); the measured submissions and polls stay on the shared async pool."""
        cfg = self.config
        with _typed_client(cfg) as api:
            self.workers = await self._wait_ready(api)
            request = await self._framing()
            truth = request["initial_pose"]
            render = {
                "model_id": cfg.model,
                "camera": request["camera"],
                "pose": truth,
                "lighting": request["lighting"],
                "spp": REFERENCE_SPP,
            }
            try:
                self.reference = await asyncio.to_thread(api.render, render)
            except ProxposeClientError as exc:
                raise LoadTestError(f"the reference render failed: {exc}") from exc
        self.base_request = {
            "model_id": cfg.model,
            "camera": request["camera"],
            "lighting": request["lighting"],
            "ground_truth": truth,
            "options": cfg.options,
        }
        self.setup_s = time.monotonic() - self.t0

    async def _wait_ready(self, api: Client) -> int:
        """The live workers, once ``/readyz`` answers with at least one (else raises)."""
        ready_by = time.monotonic() + min(READY_TIMEOUT_S, self.remaining())
        while True:
            try:
                body = await asyncio.to_thread(api.ready)
                if body.get("workers", 0) > 0:
                    return int(body["workers"])
                why = "no worker is registered yet"
            except ProxposeClientError as exc:
                why = str(exc)
            if time.monotonic() >= ready_by:
                raise LoadTestError(f"the service at {self.config.url} is not ready: {why}")
            await self.sleep(0.5)

    async def _framing(self) -> dict[str, Any]:
        """The model's default framing (a pages helper: an EstimateCreate document)."""
        cfg = self.config
        while True:
            framed = await self.client.get(
                f"/models/{cfg.model}/request.json", params={"width": cfg.size, "height": cfg.size}
            )
            if framed.status_code == 200:
                return framed.json()  # type: ignore[no-any-return]
            if framed.status_code != 404 or self.remaining() <= 0:
                raise LoadTestError(
                    f"cannot frame model '{cfg.model}': HTTP {framed.status_code} "
                    f"{framed.text[:200]}"
                )
            await self.sleep(0.5)  # the first worker registers demo-sat as it starts

    async def scrape_metrics(self) -> str | None:
        """The service's ``/metrics`` text, or None when it has none."""
        import httpx

        try:
            response = await self.client.get("/metrics", timeout=10.0)
        except httpx.HTTPError:
            return None
        return response.text if response.status_code == 200 else None

    def request_for(self, job: JobRun) -> dict[str, Any]:
        """The estimate request of ``job``: the common request, its own initial guess."""
        truth = self.base_request["ground_truth"]
        return {
            **self.base_request,
            "initial_pose": perturbed_pose(truth, job.index, self.config.start_deg),
            "options": {**self.base_request["options"], "seed": job.index},
        }

    # ------------------------------------------------------------------ clients
    async def clients(self) -> None:
        """``config.clients`` concurrent clients until every job ran or the deadline."""
        self.t_start = time.monotonic()
        cpu_start = time.process_time()
        monitor = asyncio.create_task(self._watch_loop())
        clients = self.config.clients
        tasks = [
            asyncio.create_task(self._client(i, self.config.ramp_s * i / clients))
            for i in range(clients)
        ]
        done, pending = await asyncio.wait(tasks, timeout=max(0.0, self.remaining()) + 5.0)
        for task in (*pending, monitor):
            task.cancel()
        await asyncio.gather(*pending, monitor, return_exceptions=True)
        busy_s = time.monotonic() - self.t_start
        self.client_cpu = (time.process_time() - cpu_start) / busy_s if busy_s > 0 else 0.0
        for task in done:
            if task.exception() is not None:
                raise task.exception()  # type: ignore[misc]

    async def _watch_loop(self) -> None:
        """Record how late this client's event loop wakes up (its own load inflates every
        latency it measures)."""
        while True:
            start = time.perf_counter()
            await asyncio.sleep(LOOP_PROBE_S)
            self.loop_lag_s.append(max(0.0, time.perf_counter() - start - LOOP_PROBE_S))

    def _take(self) -> JobRun | None:
        if self._next >= len(self.jobs) or self.remaining() <= 0:
            return None
        job = self.jobs[self._next]
        self._next += 1
        return job

    async def _client(self, client: int, delay_s: float) -> None:
        await self.sleep(delay_s)
        first = True
        while (job := self._take()) is not None:
            job.client, job.first_of_client, first = client, first, False
            if await self._submit(job):
                await self._poll(job)

    async def _submit(self, job: JobRun) -> bool:
        import httpx

        form = {"request": json.dumps(self.request_for(job))}
        headers = {"Idempotency-Key": job.idempotency_key}
        sent_at = time.monotonic()
        job.submitted_at_s = sent_at - self.t_start
        while True:
            if self.remaining() <= 0:
                job.submit_error = "deadline"
                return False
            files = {"image": ("reference.png", self.reference, "image/png")}
            job.submit_attempts += 1
            start = time.perf_counter()
            try:
                response = await self.client.post(
                    "/v1/estimates", files=files, data=form, headers=headers
                )
            except httpx.TransportError as exc:
                job.submit_retries += 1
                if job.submit_retries > SUBMIT_RETRIES:
                    job.submit_error = f"transport: {type(exc).__name__}"
                    return False
                await self.sleep(0.2 * job.submit_retries)
                continue
            latency = time.perf_counter() - start
            if response.status_code == 202:
                job.submit_latency_s = latency
                _absorb(job, response.json())
                job.job_id = response.json()["id"]
                return True
            if response.status_code == 429:
                job.throttled += 1
                job.throttled_latency_s.append(latency)
                await self.sleep(_retry_after_s(response))
                continue
            if response.status_code in (409, 503) and job.submit_retries < SUBMIT_RETRIES:
                job.submit_retries += 1
                await self.sleep(_retry_after_s(response, 0.5))
                continue
            job.submit_error = f"http_{response.status_code}: {response.text[:200]}"
            return False

    async def _poll(self, job: JobRun) -> None:
        import httpx

        sent_at = self.t_start + (job.submitted_at_s or 0.0)
        rng = random.Random(job.index)
        while not job.terminal and self.remaining() > 0:
            await self.sleep(self.config.poll_interval_s * rng.uniform(0.8, 1.2))
            start = time.perf_counter()
            try:
                response = await self.client.get(f"/v1/estimates/{job.job_id}")
            except httpx.TransportError:
                job.poll_errors += 1
                continue
            job.poll_latency_s.append(time.perf_counter() - start)
            if response.status_code != 200:
                job.poll_errors += 1
                continue
            _absorb(job, response.json())
        if job.terminal:
            now = time.monotonic()
            job.end_to_end_s = now - sent_at
            job.ended_at_s = now - self.t_start

    async def cancel_unfinished(self) -> int:
        """Best effort: DELETE the jobs still queued or running (they count as lost)."""
        import httpx

        cancelled = 0
        for job in self.jobs:
            if job.job_id and not job.terminal:
                try:
                    response = await self.client.delete(f"/v1/estimates/{job.job_id}", timeout=5.0)
                    cancelled += response.status_code in (200, 202)
                except httpx.HTTPError:
                    pass
        return cancelled
