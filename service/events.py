"""Server-Sent Events of one job: its state now, then its changes as the worker publishes them.

Events: ``status`` ({"status", ...}) on every change of state, ``progress`` (the job's progress
object) after every iteration, and ``end`` (the full job resource) once the job is terminal,
after which the stream closes. Subscribing before reading the record means no event is lost in
between; duplicates are dropped by iteration number (the event id), and a client that
reconnects with ``Last-Event-ID`` gets only the iterations after it. Idle streams get a
keep-alive comment, and the record is re-read then, so a lost message or a dead worker cannot
leave a stream hanging.
"""

from __future__ import annotations

import json
import time
from collections.abc import AsyncIterator
from typing import Any

import redis.asyncio
from starlette.concurrency import run_in_threadpool

from service.resources import estimate_public
from service.store import JobRecord, JobStore, Reaper


def sse(event: str, data: dict[str, Any] | str, event_id: int | None = None) -> str:
    """One event in the text/event-stream format."""
    payload = data if isinstance(data, str) else json.dumps(data)
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {event}\ndata: {payload}\n\n"


async def job_events(
    store: JobStore,
    aredis: redis.asyncio.Redis,
    job_id: str,
    keepalive_s: float,
    max_attempts: int,
    after_iteration: int = 0,
) -> AsyncIterator[str]:
    """The event stream of job ``job_id`` (which must exist), until it ends; progress events
    of iterations up to ``after_iteration`` (a reconnecting client's Last-Event-ID) are not
    sent again."""

    def current() -> JobRecord | None:
        record = store.get(job_id)
        return Reaper(store, max_attempts).reconcile(record) if record is not None else None

    def end(record: JobRecord) -> str:
        return sse("end", estimate_public(record).model_dump_json(by_alias=True))

    pubsub = aredis.pubsub(ignore_subscribe_messages=True)
    await pubsub.subscribe(store.keys.job_events(job_id))
    try:
        record = await run_in_threadpool(current)
        if record is None:
            return
        yield sse("status", {"status": record.status})
        last = record.progress_model()
        if last.iteration > after_iteration:
            yield sse("progress", last.model_dump(mode="json"), last.iteration)
        if record.terminal:
            yield end(record)
            return
        idle_until = time.monotonic() + keepalive_s
        while True:
            wait_s = max(0.01, idle_until - time.monotonic())
            message = await pubsub.get_message(timeout=wait_s)
            if message is None and time.monotonic() < idle_until:
                continue  # a subscribe confirmation (returned as None), not a timeout
            idle_until = time.monotonic() + keepalive_s
            if message is None:
                record = await run_in_threadpool(current)
                if record is None or record.terminal:
                    if record is not None:
                        yield end(record)
                    return
                yield ": keep-alive\n\n"
                continue
            payload = json.loads(message["data"])
            event, data = payload["event"], payload["data"]
            if event == "progress":
                if data["iteration"] > max(last.iteration, after_iteration):
                    last = last.model_validate(data)
                    yield sse("progress", data, last.iteration)
            elif event == "status":
                record = await run_in_threadpool(current)
                if record is None or record.terminal:
                    if record is not None:
                        yield end(record)
                    return
                yield sse("status", data)
    finally:
        await pubsub.unsubscribe()
        await pubsub.aclose()
