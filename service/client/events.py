"""A job's event stream as the client reads it: text/event-stream parsing and typed events."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass

from schemas.jobs import EstimatePublic, JobStatus, Progress


@dataclass(frozen=True)
class JobEvent:
    """One event of a job's stream: ``status`` (``status`` set), ``progress`` (``progress``
    set, after every iteration) or ``end`` (``job`` set: the final resource)."""

    kind: str
    status: JobStatus | None = None
    progress: Progress | None = None
    job: EstimatePublic | None = None
    id: str | None = None


def parse_event(kind: str, data: str, event_id: str | None) -> JobEvent:
    if kind == "progress":
        return JobEvent(kind, progress=Progress.model_validate_json(data), id=event_id)
    if kind == "end":
        job = EstimatePublic.model_validate_json(data)
        return JobEvent(kind, status=job.status, job=job, id=event_id)
    payload = json.loads(data)
    return JobEvent(kind, status=payload.get("status"), id=event_id)


def read_sse(lines: Iterator[str]) -> Iterator[tuple[str, str, str | None]]:
    """(event, data, id) of a text/event-stream (comments and keep-alives skipped)."""
    kind, event_id = "message", None
    data: list[str] = []
    for line in lines:
        if line == "":
            if data:
                yield kind, "\n".join(data), event_id
            kind, event_id = "message", None
            data = []
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if name == "event":
            kind = value
        elif name == "data":
            data.append(value)
        elif name == "id":
            event_id = value
