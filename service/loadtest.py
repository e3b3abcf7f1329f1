"""``proxpose loadtest``: many concurrent clients submit small estimates to a running service,
poll them to completion, and the figures are reported.

Each client (an asyncio task sharing one httpx connection pool) takes the next estimate of the
run, submits it (``POST /v1/estimates``, multipart, an ``Idempotency-Key`` per estimate), polls
``GET /v1/estimates/{id}`` until the job ends, then takes the next one: ``--clients`` estimates
are in flight at any time. The reference image is rendered once, up front, by the service
(``POST /v1/renders`` at the true pose: this client never loads Mitsuba); every estimate starts
from its own small perturbation of the truth and carries the truth, so the result reports the
pose error.

The clients start all at once (the first wave: every client's first submission arrives
together), or evenly over ``--ramp-s``. Reported: submit latency (accepted submissions, also
split into the first wave and the rest; throttled ones apart), status-poll latency, the same two
as the service measured them (its ``/metrics`` histogram), throughput (finished jobs per minute),
queue wait (``started_at − created_at``), run time, failures by error code, lost jobs (accepted
but not ended by the deadline), and this client's own event-loop lag and CPU use (it shares the
machine with the service, so its load shows in every latency it measures). A 429 is obeyed
(``Retry-After``) and retried with the same Idempotency-Key, as is a dropped connection. The run
is bounded: at most ``MAX_CLIENTS`` clients and ``MAX_JOBS`` jobs, ``--timeout-s`` overall
(jobs still running then are cancelled and counted as lost), and loopback URLs only. The exit
status is 0 only if every estimate was accepted and succeeded.
"""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import json
import math
import os
import platform
import random
import re
import socket
import sys
import time
import uuid
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

if TYPE_CHECKING:
    import httpx

#: Bounds of a run: clients, estimates, overall seconds.
MAX_CLIENTS = 256
MAX_JOBS = 10_000
MAX_TIMEOUT_S = 3600.0
#: Defaults of a full run and of ``--quick`` (the CI smoke test).
FULL = {"clients": 50, "jobs": 200, "size": 96, "timeout_s": 900.0}
QUICK = {"clients": 4, "jobs": 8, "size": 80, "timeout_s": 150.0}
#: Estimate options: small and quick (what was requested is stated in the report).
ESTIMATE_OPTIONS = {"max_iterations": 3, "spp": 4, "perturbation_spp": 1}
#: Samples per pixel of the reference render.
REFERENCE_SPP = 32
#: Initial guesses: rotated this far about a random axis, moved this fraction of the range.
PERTURB_ROT_DEG = 2.0
PERTURB_TRANS_FRAC = 0.01
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
#: The service's own latency histogram (``/metrics``), and the routes read from it.
_HISTOGRAM_BUCKET = re.compile(
    r"^proxpose_http_request_duration_seconds_bucket\{(?P<labels>.*)\} (?P<count>\S+)$"
)
SERVER_ROUTES = {"submit": ("POST", "/v1/estimates"), "poll": ("GET", "/v1/estimates/{job_id}")}
TERMINAL = frozenset({"succeeded", "failed", "cancelled"})
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


class LoadTestError(Exception):
    """The run cannot start (bad URL, service not ready, reference render failed)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``proxpose loadtest`` options."""
    parser.add_argument(
        "--url", default="http://127.0.0.1:8000", help="service root (loopback only)"
    )
    parser.add_argument(
        "--clients", type=int, help=f"concurrent clients (default {FULL['clients']})"
    )
    parser.add_argument("--jobs", type=int, help=f"estimates in all (default {FULL['jobs']})")
    parser.add_argument("--size", type=int, help=f"camera side, px (default {FULL['size']})")
    parser.add_argument(
        "--timeout-s", type=float, help=f"overall bound, s (default {FULL['timeout_s']:g})"
    )
    parser.add_argument("--model", default="demo-sat", help="registered model (default demo-sat)")
    parser.add_argument(
        "--max-iterations",
        type=int,
        default=ESTIMATE_OPTIONS["max_iterations"],
        help=f"iteration cap per estimate (default {ESTIMATE_OPTIONS['max_iterations']})",
    )
    parser.add_argument(
        "--poll-interval-s", type=float, default=0.5, help="status poll interval (default 0.5)"
    )
    parser.add_argument(
        "--ramp-s",
        type=float,
        default=0.0,
        help="start the clients evenly over this many seconds (default 0: all at once)",
    )
    parser.add_argument(
        "--api-key", help="Bearer key (default $PROXPOSE_API_KEY; none for an open service)"
    )
    parser.add_argument("--output", type=Path, help="write the JSON report here")
    parser.add_argument(
        "--max-submit-p99-ms",
        type=float,
        help="also fail when the submit latency's p99 is above this (default: report only)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke test: {QUICK['clients']} clients, {QUICK['jobs']} estimates, "
        f"{QUICK['size']} px, {QUICK['timeout_s']:g} s (explicit options still win)",
    )


# ----------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class Config:
    """One run's parameters (after defaults and bounds)."""

    url: str
    clients: int
    jobs: int
    size: int
    timeout_s: float
    model: str
    max_iterations: int
    poll_interval_s: float
    ramp_s: float
    api_key: str | None
    quick: bool

    def public(self) -> dict[str, Any]:
        """The parameters for the report (the key left out)."""
        data = asdict(self)
        data["api_key"] = "set" if self.api_key else None
        return data


def check_loopback(url: str) -> str:
    """``url`` without a trailing slash if it is http(s) on a loopback address, else raises."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise LoadTestError(f"--url must be http://host:port, not '{url}'")
    host = parts.hostname
    try:
        addresses = {ipaddress.ip_address(host)}
    except ValueError:
        try:
            infos = socket.getaddrinfo(host, parts.port or 80, proto=socket.IPPROTO_TCP)
        except OSError as exc:
            raise LoadTestError(f"cannot resolve '{host}': {exc}") from exc
        addresses = {ipaddress.ip_address(info[4][0]) for info in infos}
    if not addresses or not all(a.is_loopback for a in addresses):
        raise LoadTestError(
            f"refusing to load-test '{host}': the load test only targets a service on this "
            "machine (127.0.0.1, ::1 or localhost)"
        )
    return url.rstrip("/")


def make_config(args: argparse.Namespace) -> Config:
    """The run's parameters: explicit options, else the --quick or full defaults; bounded."""
    base = QUICK if args.quick else FULL

    def pick(name: str) -> Any:
        value = getattr(args, name)
        return base[name] if value is None else value

    config = Config(
        url=check_loopback(args.url),
        clients=int(pick("clients")),
        jobs=int(pick("jobs")),
        size=int(pick("size")),
        timeout_s=float(pick("timeout_s")),
        model=args.model,
        max_iterations=args.max_iterations,
        poll_interval_s=args.poll_interval_s,
        ramp_s=args.ramp_s,
        api_key=args.api_key or os.environ.get("PROXPOSE_API_KEY") or None,
        quick=args.quick,
    )
    limits = [
        (1 <= config.clients <= MAX_CLIENTS, f"--clients must be 1..{MAX_CLIENTS}"),
        (1 <= config.jobs <= MAX_JOBS, f"--jobs must be 1..{MAX_JOBS}"),
        (16 <= config.size <= 1024, "--size must be 16..1024 px"),
        (10.0 <= config.timeout_s <= MAX_TIMEOUT_S, f"--timeout-s must be 10..{MAX_TIMEOUT_S:g}"),
        (1 <= config.max_iterations <= 100, "--max-iterations must be 1..100"),
        (0.05 <= config.poll_interval_s <= 10.0, "--poll-interval-s must be 0.05..10"),
        (0.0 <= config.ramp_s <= config.timeout_s / 2, "--ramp-s must be 0..timeout/2"),
    ]
    for ok, message in limits:
        if not ok:
            raise LoadTestError(message)
    return config


# ----------------------------------------------------------------------------- poses
Quaternion = tuple[float, float, float, float]


def _qmul(a: Quaternion, b: Quaternion) -> Quaternion:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _unit(v: list[float]) -> list[float]:
    norm = math.sqrt(sum(x * x for x in v))
    return [x / norm for x in v]


def perturbed_pose(truth: dict[str, Any], seed: int) -> dict[str, list[float]]:
    """``truth`` rotated by ``PERTURB_ROT_DEG`` about a random axis (camera frame) and moved by
    ``PERTURB_TRANS_FRAC`` of its range in a random direction (deterministic in ``seed``)."""
    rng = random.Random(seed)
    axis = _unit([rng.gauss(0.0, 1.0) for _ in range(3)])
    half = math.radians(PERTURB_ROT_DEG) / 2.0
    delta = (math.cos(half), *(math.sin(half) * a for a in axis))
    q = _qmul(delta, tuple(truth["quaternion"]))  # type: ignore[arg-type]
    norm = math.sqrt(sum(x * x for x in q))
    t = [float(x) for x in truth["t"]]
    shift = PERTURB_TRANS_FRAC * math.sqrt(sum(x * x for x in t))
    step = _unit([rng.gauss(0.0, 1.0) for _ in range(3)])
    return {
        "t": [round(x + shift * d, 6) for x, d in zip(t, step, strict=True)],
        "quaternion": [round(x / norm, 9) for x in q],
    }


# ----------------------------------------------------------------------------- per job
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

    @property
    def terminal(self) -> bool:
        return self.status in TERMINAL


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
        """Wait for a worker, frame the model, render the reference at the true pose."""
        import httpx

        cfg = self.config
        ready_by = time.monotonic() + min(READY_TIMEOUT_S, self.remaining())
        while True:
            try:
                ready = await self.client.get("/readyz")
                body = ready.json()
                if ready.status_code == 200 and body.get("workers", 0) > 0:
                    self.workers = int(body["workers"])
                    break
                why = body.get("reason") or f"HTTP {ready.status_code}"
            except (httpx.HTTPError, ValueError) as exc:
                why = f"{type(exc).__name__}: {exc}"
            if time.monotonic() >= ready_by:
                raise LoadTestError(f"the service at {cfg.url} is not ready: {why}")
            await self.sleep(0.5)
        # the model's default framing (a pages helper: an EstimateCreate document)
        while True:
            framed = await self.client.get(
                f"/models/{cfg.model}/request.json", params={"width": cfg.size, "height": cfg.size}
            )
            if framed.status_code == 200:
                break
            if framed.status_code != 404 or self.remaining() <= 0:
                raise LoadTestError(
                    f"cannot frame model '{cfg.model}': HTTP {framed.status_code} "
                    f"{framed.text[:200]}"
                )
            await self.sleep(0.5)  # the first worker registers demo-sat as it starts
        request = framed.json()
        truth = request["initial_pose"]
        render = {
            "model_id": cfg.model,
            "camera": request["camera"],
            "pose": truth,
            "lighting": request["lighting"],
            "spp": REFERENCE_SPP,
        }
        rendered = await self.client.post("/v1/renders", json=render, timeout=RENDER_TIMEOUT_S)
        if rendered.status_code != 200:
            raise LoadTestError(
                f"the reference render failed: HTTP {rendered.status_code} {rendered.text[:300]}"
            )
        self.reference = rendered.content
        self.base_request = {
            "model_id": cfg.model,
            "camera": request["camera"],
            "lighting": request["lighting"],
            "ground_truth": truth,
            "options": {**ESTIMATE_OPTIONS, "max_iterations": cfg.max_iterations},
        }
        self.setup_s = time.monotonic() - self.t0

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
            "initial_pose": perturbed_pose(truth, job.index),
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


# ----------------------------------------------------------------------------- figures
def percentile(values: list[float], p: float) -> float:
    """The ``p``-th percentile (0–100) with linear interpolation (numpy's default)."""
    ordered = sorted(values)
    rank = (len(ordered) - 1) * p / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def stats(values: list[float], scale: float = 1.0) -> dict[str, float | int | None]:
    """n, mean, p50, p95, p99 and max of ``values`` (times ``scale``); None when empty."""
    if not values:
        return {"n": 0, "mean": None, "p50": None, "p95": None, "p99": None, "max": None}
    out: dict[str, float | int | None] = {"n": len(values)}
    out["mean"] = round(scale * sum(values) / len(values), 3)
    for p in (50, 95, 99):
        out[f"p{p}"] = round(scale * percentile(values, p), 3)
    out["max"] = round(scale * max(values), 3)
    return out


Buckets = dict[tuple[str, str], dict[float, float]]


def parse_histograms(text: str | None) -> Buckets:
    """Cumulative bucket counts of the service's HTTP latency histogram by (method, route)."""
    found: Buckets = {}
    for line in (text or "").splitlines():
        match = _HISTOGRAM_BUCKET.match(line)
        if match is None:
            continue
        labels = dict(re.findall(r'(\w+)="([^"]*)"', match["labels"]))
        le = math.inf if labels.get("le") == "+Inf" else float(labels.get("le", "nan"))
        key = (labels.get("method", ""), labels.get("route", ""))
        found.setdefault(key, {})[le] = float(match["count"])
    return found


def histogram_stats(before: dict[float, float], after: dict[float, float]) -> dict[str, Any]:
    """n, p50/p95/p99 (ms, interpolated within buckets) and the share under 50 ms of the
    requests counted between two scrapes of a cumulative histogram."""
    edges = sorted(after)
    counts = [after[e] - before.get(e, 0.0) for e in edges]
    total = counts[-1] if counts else 0.0
    out: dict[str, Any] = {"n": int(total)}
    for p in (50, 95, 99):
        value = None
        if total > 0:
            target, lower, below = total * p / 100.0, 0.0, 0.0
            for edge, count in zip(edges, counts, strict=True):
                if count >= target:
                    if math.isinf(edge):
                        value = lower  # above the last finite bucket: a lower bound
                    else:
                        share = (target - below) / (count - below) if count > below else 1.0
                        value = lower + (edge - lower) * share
                    break
                lower, below = edge, count
        out[f"p{p}"] = round(1000.0 * value, 1) if value is not None else None
    under = dict(zip(edges, counts, strict=True)).get(0.05)
    out["under_50ms_pct"] = round(100.0 * under / total, 1) if total and under is not None else None
    return out


def server_latency(run: Run) -> dict[str, Any] | None:
    """Submit and poll latency as the service measured them (``/metrics``), or None."""
    before, after = parse_histograms(run.metrics_before), parse_histograms(run.metrics_after)
    if not after:
        return None
    figures: dict[str, Any] = {
        "source": "the service's /metrics histogram between the start and the end of the "
        "clients (percentiles interpolated within its buckets; the rate limiter's 429s are "
        "counted under route 'unmatched', so not here)"
    }
    for name, key in SERVER_ROUTES.items():
        figures[name] = histogram_stats(before.get(key, {}), after.get(key, {}))
    return figures


def build_report(run: Run, wall_s: float, cancelled: int) -> dict[str, Any]:
    """The JSON report: parameters, figures, failures, lost jobs and every job."""
    jobs = run.jobs
    accepted = [j for j in jobs if j.job_id]
    ended = [j for j in accepted if j.terminal]
    lost = [j for j in accepted if not j.terminal]
    first = [j for j in accepted if j.first_of_client]
    later = [j for j in accepted if not j.first_of_client]
    failures: dict[str, int] = {}
    for j in jobs:
        if j.job_id is None:
            code = "not_submitted:" + (j.submit_error or "deadline").split(":")[0]
        elif j.status in ("failed", "cancelled"):
            code = f"{j.status}:{j.error_code or 'none'}"
        else:
            continue
        failures[code] = failures.get(code, 0) + 1
    ends = [j.ended_at_s for j in ended if j.ended_at_s is not None]
    span_s = max(ends) if ends else 0.0
    ms = 1000.0
    return {
        "tool": "proxpose loadtest",
        "started": datetime.fromtimestamp(time.time() - wall_s).isoformat(timespec="seconds"),
        "config": run.config.public(),
        "requested": {
            "camera": run.base_request.get("camera"),
            "options": run.base_request.get("options"),
            "reference_spp": REFERENCE_SPP,
            "initial_guess": f"truth rotated {PERTURB_ROT_DEG:g}° about a random axis, moved "
            f"{100 * PERTURB_TRANS_FRAC:g} % of the range",
        },
        "service": {"workers_at_start": run.workers},
        "machine": {
            "host": platform.node(),
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
        },
        "duration_s": round(wall_s, 3),
        "setup_s": round(run.setup_s, 3),
        "jobs": {
            "requested": len(jobs),
            "submitted": len(accepted),
            "not_submitted": len(jobs) - len(accepted),
            "succeeded": sum(j.status == "succeeded" for j in accepted),
            "failed": sum(j.status == "failed" for j in accepted),
            "cancelled": sum(j.status == "cancelled" for j in accepted),
            "lost": len(lost),
            "lost_ids": [j.job_id for j in lost],
            "cancelled_at_deadline": cancelled,
            "requeued": sum((j.attempts or 0) > 1 for j in accepted),
        },
        "failures_by_code": failures,
        "throughput_jobs_per_min": round(60.0 * len(ended) / span_s, 2) if span_s else None,
        "throughput_span_s": round(span_s, 3),
        "latency_ms": {
            "submit": stats([j.submit_latency_s for j in accepted if j.submit_latency_s], ms),
            # the first wave: every client's first submission (all at once unless --ramp-s);
            # then one per finished job
            "submit_first_wave": stats(
                [j.submit_latency_s for j in first if j.submit_latency_s is not None], ms
            ),
            "submit_after_first_wave": stats(
                [j.submit_latency_s for j in later if j.submit_latency_s is not None], ms
            ),
            "submit_throttled_429": stats([x for j in jobs for x in j.throttled_latency_s], ms),
            "poll": stats([x for j in jobs for x in j.poll_latency_s], ms),
        },
        "server_latency_ms": server_latency(run),
        "throttled_429": sum(j.throttled for j in jobs),
        "submit_retries": sum(j.submit_retries for j in jobs),
        "poll_errors": sum(j.poll_errors for j in jobs),
        "client": {
            "loop_lag_ms": stats(run.loop_lag_s, ms),
            "cpu_fraction": round(run.client_cpu, 3),
        },
        "queue_wait_s": stats([j.queue_wait_s for j in ended if j.queue_wait_s is not None]),
        "run_time_s": stats([j.run_time_s for j in ended if j.run_time_s is not None]),
        "end_to_end_s": stats([j.end_to_end_s for j in ended if j.end_to_end_s is not None]),
        "pose_error": {
            "rotation_deg": stats(
                [j.rotation_error_deg for j in ended if j.rotation_error_deg is not None]
            ),
            "translation": stats(
                [j.translation_error for j in ended if j.translation_error is not None]
            ),
            "converged": sum(bool(j.converged) for j in ended),
        },
        "per_job": [_job_row(j) for j in jobs],
    }


def _job_row(job: JobRun) -> dict[str, Any]:
    row = asdict(job)
    for name in ("poll_latency_s", "throttled_latency_s"):
        row[name.replace("_s", "_ms")] = [round(1000.0 * x, 2) for x in row.pop(name)]
    for name, value in row.items():
        if isinstance(value, float):
            row[name] = round(value, 4)
    return row


def summary(report: dict[str, Any]) -> str:
    """A readable table of the report's headline figures."""
    cfg, req, jobs = report["config"], report["requested"], report["jobs"]
    cam, opts = req["camera"] or {}, req["options"] or {}
    lines = [
        f"proxpose loadtest → {cfg['url']} ({report['service']['workers_at_start']} worker(s), "
        f"{report['machine']['cpus']} CPUs)",
        f"requested: {cfg['clients']} clients × {cfg['jobs']} estimates of {cfg['model']}, "
        f"{cam.get('width')}×{cam.get('height')} px, "
        + ", ".join(f"{k} {v}" for k, v in opts.items() if k != "seed")
        + f"; {req['initial_guess']}; polls every {cfg['poll_interval_s']:g} s"
        + (f"; clients started over {cfg['ramp_s']:g} s" if cfg["ramp_s"] else ""),
        "",
        f"{'':24}{'n':>6}{'mean':>9}{'p50':>9}{'p95':>9}{'p99':>9}{'max':>9}",
    ]
    rows = [
        ("submit latency (ms)", report["latency_ms"]["submit"]),
        ("  first wave (ms)", report["latency_ms"]["submit_first_wave"]),
        ("  after it (ms)", report["latency_ms"]["submit_after_first_wave"]),
        ("  throttled 429 (ms)", report["latency_ms"]["submit_throttled_429"]),
        ("status poll (ms)", report["latency_ms"]["poll"]),
        ("client loop lag (ms)", report["client"]["loop_lag_ms"]),
        ("queue wait (s)", report["queue_wait_s"]),
        ("run time (s)", report["run_time_s"]),
        ("end to end (s)", report["end_to_end_s"]),
        ("rotation error (°)", report["pose_error"]["rotation_deg"]),
        ("translation error", report["pose_error"]["translation"]),
    ]
    for name, s in rows:
        cells = "".join(
            f"{s[k]:>9.4g}" if s[k] is not None else f"{'—':>9}"
            for k in ("mean", "p50", "p95", "p99", "max")
        )
        lines.append(f"{name:<24}{s['n']:>6}{cells}")
    server = report["server_latency_ms"]
    if server is not None:
        for name in SERVER_ROUTES:
            s = server[name]
            cells = "".join(
                f"{s[k]:>9.4g}" if s[k] is not None else f"{'—':>9}" for k in ("p50", "p95", "p99")
            )
            lines.append(
                f"{'server ' + name + ' (ms)':<24}{s['n']:>6}{'':>9}{cells}{'':>9}"
                f"  ({s['under_50ms_pct']} % < 50 ms)"
            )
    throughput = report["throughput_jobs_per_min"]
    lines += [
        "",
        f"jobs: {jobs['requested']} requested, {jobs['submitted']} submitted, "
        f"{jobs['succeeded']} succeeded, {jobs['failed']} failed, {jobs['cancelled']} cancelled, "
        f"{jobs['not_submitted']} not submitted, {jobs['lost']} LOST"
        + (f" ({jobs['requeued']} re-queued after a lost worker)" if jobs["requeued"] else ""),
        f"throughput: {throughput if throughput is not None else '—'} jobs/min over "
        f"{report['throughput_span_s']:.1f} s; {report['throttled_429']} submissions throttled "
        f"(429), {report['submit_retries']} retried, {report['poll_errors']} poll errors",
        "failures: "
        + (", ".join(f"{k} ×{v}" for k, v in report["failures_by_code"].items()) or "none"),
        f"converged: {report['pose_error']['converged']} of {jobs['succeeded']} succeeded; "
        f"wall time {report['duration_s']:.1f} s (setup {report['setup_s']:.1f} s); this "
        f"client used {100 * report['client']['cpu_fraction']:.0f} % of a CPU",
    ]
    return "\n".join(lines)


def verdict(report: dict[str, Any], max_submit_p99_ms: float | None) -> list[str]:
    """Why the run failed (empty: it passed)."""
    jobs = report["jobs"]
    problems = []
    if jobs["lost"]:
        problems.append(f"{jobs['lost']} job(s) lost (accepted, never ended)")
    if jobs["succeeded"] != jobs["requested"]:
        problems.append(f"{jobs['requested'] - jobs['succeeded']} estimate(s) did not succeed")
    p99 = report["latency_ms"]["submit"]["p99"]
    if max_submit_p99_ms is not None and p99 is not None and p99 > max_submit_p99_ms:
        problems.append(f"submit p99 {p99:.1f} ms > {max_submit_p99_ms:g} ms")
    return problems


# ----------------------------------------------------------------------------- entry point
async def _main(config: Config) -> tuple[Run, float, int]:
    import httpx

    headers = {"Authorization": f"Bearer {config.api_key}"} if config.api_key else {}
    limits = httpx.Limits(
        max_connections=config.clients + 4, max_keepalive_connections=config.clients + 4
    )
    async with httpx.AsyncClient(
        base_url=config.url,
        headers=headers,
        limits=limits,
        timeout=REQUEST_TIMEOUT_S,
        trust_env=False,  # never through a proxy: the target is this machine
    ) as client:
        run = Run(config, client)
        start = time.monotonic()
        await run.prepare()
        run.metrics_before = await run.scrape_metrics()
        await run.clients()
        run.metrics_after = await run.scrape_metrics()
        cancelled = await run.cancel_unfinished()
        return run, time.monotonic() - start, cancelled


def run(args: argparse.Namespace) -> int:
    """``proxpose loadtest``: 0 when every estimate succeeded and none was lost."""
    try:
        config = make_config(args)
    except LoadTestError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(
        f"proxpose loadtest: {config.clients} clients, {config.jobs} estimates of "
        f"{config.model} at {config.size} px against {config.url} (at most "
        f"{config.timeout_s:g} s)",
        flush=True,
    )
    import httpx

    try:
        loadtest, wall_s, cancelled = asyncio.run(_main(config))
    except (LoadTestError, httpx.HTTPError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    report = build_report(loadtest, wall_s, cancelled)
    problems = verdict(report, args.max_submit_p99_ms)
    report["passed"], report["problems"] = not problems, problems
    print(summary(report), flush=True)
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(report, indent=2) + "\n")
        print(f"report: {args.output}")
    for problem in problems:
        print(f"FAILED: {problem}", file=sys.stderr)
    return EXIT_OK if not problems else EXIT_FAILED
