"""Server-Sent Events of one job: its state now, then its changes as the worker publishes them.

Events: ``status`` ({"status", ...}) on every change of state, ``progress`` (after every
iteration of an estimate, every frame of a track: see :class:`EventShape`), and ``end`` (the
full job resource) once the job is terminal, after which the stream closes. Subscribing
before reading the record means no event is lost in between; duplicates are dropped by event
id (the iteration, the frames done), and a client that reconnects with ``Last-Event-ID`` gets
only the progress after it. Idle streams get a keep-alive comment, and the record is re-read
then, so a lost message or a dead worker cannot leave a stream hanging.
"""

from __future__ import annotations

import json
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Any

import redis.asyncio
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from schemas.settings import Settings
from service.resources import estimate_public
from service.store import JobRecord, JobStore, Reaper


@dataclass(frozen=True)
class EventShape:
    """What a kind of job's stream is made of: ``public`` is the job resource (JSON) that the
    ``end`` event carries, ``backlog`` the progress events (data, id) a client connecting
    after event id ``after`` gets from the record, and ``position`` a published progress
    event's id (the iteration of an estimate, the frames done of a track)."""

    public: Callable[[JobRecord], str]
    backlog: Callable[[JobRecord, int], list[tuple[dict[str, Any], int]]]
    position: Callable[[dict[str, Any]], int]


def _estimate_backlog(record: JobRecord, after: int) -> list[tuple[dict[str, Any], int]]:
    last = record.progress_model()
    return [(last.model_dump(mode="json"), last.iteration)] if last.iteration > after else []


#: The stream of an estimate: one progress event per iteration.
ESTIMATE_EVENTS = EventShape(
    public=lambda record: estimate_public(record).model_dump_json(by_alias=True),
    backlog=_estimate_backlog,
    position=lambda data: int(data["iteration"]),
)


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
    shape: EventShape = ESTIMATE_EVENTS,
) -> AsyncIterator[str]:
    """The event stream of job ``job_id`` (which must exist), until it ends; progress events
    up to id ``after_iteration`` (a reconnecting client's Last-Event-ID) are not sent
    again."""

    def current() -> JobRecord | None:
        record = store.get(job_id)
        return Reaper(store, max_attempts).reconcile(record) if record is not None else None

    def end(record: JobRecord) -> str:
        return sse("end", shape.public(record))

    pubsub = aredis.pubsub(ignore_subscribe_messages=True)
    await pubsub.subscribe(store.keys.job_events(job_id))
    try:
        record = await run_in_threadpool(current)
        if record is None:
            return
        yield sse("status", {"status": record.status})
        seen = after_iteration
        for data, event_id in shape.backlog(record, after_iteration):
            seen = max(seen, event_id)
            yield sse("progress", data, event_id)
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
                if shape.position(data) > seen:
                    seen = shape.position(data)
                    yield sse("progress", data, seen)
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


def event_stream(
    store: JobStore,
    aredis: redis.asyncio.Redis,
    job_id: str,
    settings: Settings,
    last_event_id: str | None,
    shape: EventShape = ESTIMATE_EVENTS,
) -> StreamingResponse:
    """The response of a job's ``/events`` (the job must exist): resumes after
    ``last_event_id`` (a reconnecting client's Last-Event-ID header)."""
    after = int(last_event_id) if last_event_id and last_event_id.isdigit() else 0
    events = job_events(
        store, aredis, job_id, settings.sse_keepalive_s, settings.job_max_attempts, after, shape
    )
    return StreamingResponse(
        events,
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
