"""Prometheus metrics: HTTP requests and blob operations of this process, and the queue, job,
Redis memory and blob store figures of the whole deployment read from Redis at scrape time (so
every worker's jobs are counted; the blob census is the last sweep's)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator

import redis
from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.inline import PAUSE_S
from service.store import JobStats, Keys, Queues
from service.store.blobs import CountingBlobStore
from service.store.budget import redis_memory

#: Where the collector finds Redis and the key names (None before the app has started).
StoreSource = Callable[[], tuple[redis.Redis, Keys] | None]
#: Where it finds this process's blob store (None before the app has started).
BlobSource = Callable[[], CountingBlobStore | None]
#: Buckets of the HTTP latency histogram, s (30 and 40 ms: the 50 ms target of a burst's
#: submissions told apart from 26 ms).
HTTP_LATENCY_BUCKETS_S = (
    0.005, 0.01, 0.025, 0.03, 0.04, 0.05, 0.075, 0.1, 0.15, 0.2, 0.25, 0.5,
    1.0, 2.5, 5.0, 10.0, 30.0, 60.0,
)  # fmt: skip


class Metrics:
    """The app's registry and its HTTP instruments."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        # Several API processes (PROMETHEUS_MULTIPROC_DIR set, see `proxpose serve`): each
        # writes its HTTP figures to files there and a scrape adds up all of them.
        multiprocess = bool(os.environ.get("PROMETHEUS_MULTIPROC_DIR"))
        own = None if multiprocess else self.registry
        self.requests = Counter(
            "proxpose_http_requests",
            "HTTP requests answered, by method, route template and status.",
            ["method", "route", "status"],
            registry=own,
        )
        self.latency = Histogram(
            "proxpose_http_request_duration_seconds",
            "Time to answer an HTTP request (event streams: until they end), s.",
            ["method", "route"],
            buckets=HTTP_LATENCY_BUCKETS_S,
            registry=own,
        )
        self.inline_paused = Counter(
            "proxpose_inline_submissions_paused",
            "Times submissions left the event loop for the thread pool (a Redis error or a slow "
            f"call on the loop; service/inline.py), for {PAUSE_S:g} s each.",
            registry=own,
        )
        if multiprocess:
            from prometheus_client.multiprocess import MultiProcessCollector

            MultiProcessCollector(self.registry)

    def watch_store(self, source: StoreSource, blobs: BlobSource | None = None) -> None:
        """Also expose the queue, worker, job, memory and blob figures kept in Redis, and the
        blob operations of this process."""
        self.registry.register(StoreCollector(source))
        if blobs is not None:
            self.registry.register(BlobOpsCollector(blobs))


class MetricsMiddleware:
    """Counts each request under its route template (``/v1/estimates/{job_id}``), not its raw
    path, so that ids do not explode the label space."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 500
        t0 = time.perf_counter()

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            method = scope["method"]
            self.metrics.requests.labels(method, route, str(status)).inc()
            self.metrics.latency.labels(method, route).observe(time.perf_counter() - t0)


class StoreCollector(Collector):
    """Reads queue depths, live workers and job statistics from Redis on every scrape."""

    def __init__(self, source: StoreSource) -> None:
        self.source = source

    def collect(self) -> Iterator[Metric]:
        up = GaugeMetricFamily("proxpose_redis_up", "1 if Redis answered this scrape.")
        store = self.source()
        if store is None:
            up.add_metric([], 0)
            yield up
            return
        r, keys = store
        try:
            queues = Queues(r, keys)
            depths, workers = queues.depths(), queues.live_workers()
            snap = JobStats(r, keys).snapshot()
            memory = redis_memory(r)
            census = r.hgetall(keys.blob_census)
        except redis.RedisError:
            up.add_metric([], 0)
            yield up
            return
        up.add_metric([], 1)
        yield up
        depth = GaugeMetricFamily(
            "proxpose_queue_depth", "Jobs waiting, by queue.", labels=["queue"]
        )
        for name, n in depths.items():
            depth.add_metric([name], n)
        yield depth
        yield GaugeMetricFamily("proxpose_workers", "Live workers.", value=workers)
        yield from _memory_and_census(memory, census)  # type: ignore[arg-type]
        jobs = CounterMetricFamily(
            "proxpose_jobs", "Jobs finished, by kind and final status.", labels=["kind", "status"]
        )
        for (kind, status), n in sorted(snap.jobs.items()):
            jobs.add_metric([kind, status], n)
        yield jobs
        failures = CounterMetricFamily(
            "proxpose_job_failures", "Failed jobs, by kind and error code.", labels=["kind", "code"]
        )
        for (kind, code), n in sorted(snap.failures.items()):
            failures.add_metric([kind, code], n)
        yield failures
        duration = HistogramMetricFamily(
            "proxpose_job_duration_seconds", "Run time of finished jobs, s.", labels=["kind"]
        )
        for kind, buckets in sorted(snap.buckets.items()):
            duration.add_metric([kind], buckets, sum_value=snap.duration_sum_s.get(kind, 0.0))
        yield duration


def _memory_and_census(memory: tuple[int, int], census: dict[bytes, bytes]) -> Iterator[Metric]:
    used, limit = memory
    yield GaugeMetricFamily("proxpose_redis_used_memory_bytes", "Redis used_memory.", value=used)
    yield GaugeMetricFamily(
        "proxpose_redis_maxmemory_bytes", "Redis maxmemory (0: no limit).", value=limit
    )
    if not census:
        return  # no sweep yet
    figures = {k.decode(): float(v) for k, v in census.items()}
    yield GaugeMetricFamily(
        "proxpose_blob_store_objects",
        "Blobs in the blob store at the last sweep.",
        value=figures.get("objects", 0.0),
    )
    yield GaugeMetricFamily(
        "proxpose_blob_store_bytes",
        "Bytes in the blob store at the last sweep.",
        value=figures.get("bytes", 0.0),
    )
    yield CounterMetricFamily(
        "proxpose_blob_swept", "Blobs deleted by the sweeps.", value=figures.get("swept", 0.0)
    )
    yield GaugeMetricFamily(
        "proxpose_blob_sweep_timestamp_seconds",
        "When the last sweep ended (Unix time).",
        value=figures.get("at", 0.0),
    )


class BlobOpsCollector(Collector):
    """This process's blob store operations (by op and outcome) and bytes moved."""

    def __init__(self, source: BlobSource) -> None:
        self.source = source

    def collect(self) -> Iterator[Metric]:
        blobs = self.source()
        if blobs is None:
            return
        ops, written, read = blobs.ops.snapshot()
        family = CounterMetricFamily(
            "proxpose_blob_operations",
            "Blob store operations of this process, by op and outcome (ok, missing, error).",
            labels=["op", "outcome"],
        )
        for (op, outcome), n in sorted(ops.items()):
            family.add_metric([op, outcome], n)
        yield family
        moved = CounterMetricFamily(
            "proxpose_blob_transferred_bytes",
            "Bytes this process wrote to and read from the blob store.",
            labels=["direction"],
        )
        moved.add_metric(["write"], written)
        moved.add_metric(["read"], read)
        yield moved
