"""A job's event stream as the client reads it: text/event-stream parsing and typed events,
for each kind of job (an estimate, a track) the resource it has and what its progress says."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

from pydantic import BaseModel

from schemas.jobs import EstimatePublic, JobStatus, JobSummary, Progress
from schemas.track_jobs import TrackProgressEvent, TrackPublic

P = TypeVar("P", bound=BaseModel)
J = TypeVar("J", bound=JobSummary)


@dataclass(frozen=True)
class JobKind(Generic[P, J]):
    """A kind of job as the API serves it: under ``path`` (``/v1/estimates``), shown as a
    ``public`` resource, its ``progress`` events carrying a ``progress`` model."""

    path: str
    public: type[J]
    progress: type[P]


ESTIMATES = JobKind("/v1/estimates", EstimatePublic, Progress)
TRACKS = JobKind("/v1/tracks", TrackPublic, TrackProgressEvent)


@dataclass(frozen=True)
class JobEvent(Generic[P, J]):
    """One event of a job's stream: ``status`` (``status`` set), ``progress`` (``progress``
    set: after every iteration of an estimate, after every frame of a track) or ``end``
    (``job`` set: the final resource)."""

    kind: str
    status: JobStatus | None = None
    progress: P | None = None
    job: J | None = None
    id: str | None = None


EstimateEvent = JobEvent[Progress, EstimatePublic]
TrackEvent = JobEvent[TrackProgressEvent, TrackPublic]


def parse_event(
    job_kind: JobKind[P, J], kind: str, data: str, event_id: str | None
) -> JobEvent[P, J]:
    if kind == "progress":
        return JobEvent(kind, progress=job_kind.progress.model_validate_json(data), id=event_id)
    if kind == "end":
        job = job_kind.public.model_validate_json(data)
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
