"""A typed client of the proxpose API, for programs and scripts.

    from service.client import Client

    with Client("http://127.0.0.1:8000", api_key=None) as api:
        job = api.submit_estimate("ref.png", {"model_id": "demo-sat", "camera": ..., ...})
        for event in api.events(job.id):
            print(event.kind, event.progress)
        job = api.wait(job.id)
        print(job.status, job.result.pose if job.result else job.error)
        open("difference.png", "wb").write(api.artifact(job.id, "difference"))

It needs nothing but httpx and the :mod:`schemas` models (no FastAPI, numpy or Mitsuba), so
``pip install proxpose`` is enough to use it. Answers come back as the ``schemas`` models
(:class:`~schemas.jobs.EstimatePublic` has ``.id``, ``.status``, ``.result``); errors as
:class:`ApiError` subclasses carrying the problem details (:class:`~schemas.problem.Problem`).

Tracks (``/v1/tracks``) have the same calls: ``submit_track(frames, request)``, ``get_track``,
``track_events``, ``wait_track``, ``cancel_track``, ``track_artifact`` and ``track_json``.

Retries: a dropped connection, a 503 or a 429 with ``Retry-After`` is retried (up to
``retries`` times, waiting as the service says, at most ``max_retry_wait_s`` a time). A
submission is retried only with an Idempotency-Key, so one is generated when none is given: a
retried submission returns the job the first attempt created instead of a second one.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
from pydantic import BaseModel

from schemas.jobs import (
    EstimateCreate,
    EstimateList,
    EstimatePublic,
    EstimateSummary,
    JobStatus,
    RenderCreate,
)
from schemas.models import ModelList, ModelPublic
from schemas.track import TrackResult
from schemas.track_jobs import TrackCreate, TrackPublic
from service.client.calls import EVENTS_RECONNECTS, POLL_S, Calls, ImageInput, image_part
from service.client.errors import (
    ApiError,
    BadRequest,
    Conflict,
    Forbidden,
    NotFound,
    PayloadTooLarge,
    ProxposeClientError,
    RateLimited,
    ServerError,
    ServiceUnavailable,
    ServiceUnreachable,
    Unauthorized,
    UnsupportedMediaType,
    WaitTimeout,
)
from service.client.events import ESTIMATES, TRACKS, EstimateEvent, JobEvent, TrackEvent

__all__ = [
    "ApiError",
    "BadRequest",
    "Client",
    "Conflict",
    "EstimateEvent",
    "Forbidden",
    "JobEvent",
    "NotFound",
    "PayloadTooLarge",
    "ProxposeClientError",
    "RateLimited",
    "ServerError",
    "ServiceUnavailable",
    "ServiceUnreachable",
    "TrackEvent",
    "Unauthorized",
    "UnsupportedMediaType",
    "WaitTimeout",
]


# ----------------------------------------------------------------------------- the client
RequestInput = EstimateCreate | Mapping[str, Any]
TrackRequestInput = TrackCreate | Mapping[str, Any]
#: One status or several (a list, since ``Client.list`` hides the builtin in the class).
StatusFilter = JobStatus | list[JobStatus] | None


class Client(Calls):
    """Calls of the ``/v1`` API (see the module docstring); use as a context manager, or
    ``close()`` it. ``Client(base_url, api_key=None, timeout_s=30.0, retries=3,
    max_retry_wait_s=30.0, transport=None)``."""

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ models
    def upload_model(self, path: str | Path, name: str | None = None) -> ModelPublic:
        """Register the mesh at ``path`` (its id is the file's content address, so uploading
        it again returns the same model)."""
        path = Path(path)
        files = {"file": (path.name, path.read_bytes(), "application/octet-stream")}
        data = {"name": name} if name is not None else None
        return self._json(  # type: ignore[no-any-return]
            "POST", "/v1/models", ModelPublic, files=files, data=data, idempotent=True
        )

    def models(self) -> list[ModelPublic]:
        return self._json("GET", "/v1/models", ModelList).items  # type: ignore[no-any-return]

    def model(self, model_id: str) -> ModelPublic:
        return self._json("GET", f"/v1/models/{model_id}", ModelPublic)  # type: ignore[no-any-return]

    def delete_model(self, model_id: str) -> None:
        self._request("DELETE", f"/v1/models/{model_id}", idempotent=True)

    # ------------------------------------------------------------------ estimates
    def submit_estimate(
        self, image: ImageInput, request: RequestInput, idempotency_key: str | None = None
    ) -> EstimatePublic:
        """Queue an estimate of ``image`` (a path or the file's bytes) for ``request`` (an
        :class:`~schemas.jobs.EstimateCreate` or the same as a dict, sent as given: the
        service validates it and answers each bad field)."""
        return self._submit(ESTIMATES, [("image", image_part(image))], request, idempotency_key)

    def get(self, job_id: str) -> EstimatePublic:
        return self._get(ESTIMATES, job_id)

    def list(
        self,
        status: StatusFilter = None,
        model_id: str | None = None,
        limit: int = 20,
        cursor: str | None = None,
    ) -> EstimateList:
        """One page of estimates, newest first (``next_cursor`` continues)."""
        params: dict[str, Any] = {"limit": limit}
        if status is not None:
            params["status"] = [status] if isinstance(status, str) else status
        if model_id is not None:
            params["model_id"] = model_id
        if cursor is not None:
            params["cursor"] = cursor
        return self._json("GET", "/v1/estimates", EstimateList, params=params)  # type: ignore[no-any-return]

    def iter_estimates(
        self, status: StatusFilter = None, model_id: str | None = None
    ) -> Iterator[EstimateSummary]:
        """Every estimate (matching the filters), newest first, page after page."""
        cursor = None
        while True:
            page = self.list(status, model_id, limit=100, cursor=cursor)
            yield from page.items
            if page.next_cursor is None:
                return
            cursor = page.next_cursor

    def cancel(self, job_id: str) -> EstimatePublic:
        """Cancel a queued job, or ask a running one to stop (raises :class:`Conflict` when it
        has already ended)."""
        return self._cancel(ESTIMATES, job_id)

    def artifact(self, job_id: str, name: str) -> bytes:
        """A PNG artifact of a succeeded job (``difference``, ``final_render``, ...)."""
        return self._artifact(ESTIMATES, job_id, name)

    def events(self, job_id: str, reconnects: int = EVENTS_RECONNECTS) -> Iterator[EstimateEvent]:
        """The job's events until ``end`` (``status``, ``progress`` after every iteration). A
        dropped stream is reopened (``Last-Event-ID``: no progress event is repeated) up to
        ``reconnects`` times in a row."""
        return self._events(ESTIMATES, job_id, reconnects)

    def wait(
        self, job_id: str, timeout_s: float | None = None, poll_s: float = POLL_S
    ) -> EstimatePublic:
        """The job once it has ended (succeeded, failed or cancelled): follows its event stream,
        and polls when the stream cannot be had. Raises :class:`WaitTimeout` after
        ``timeout_s``."""
        return self._wait(ESTIMATES, job_id, timeout_s, poll_s)

    # ------------------------------------------------------------------ tracks
    def submit_track(
        self,
        frames: Sequence[ImageInput],
        request: TrackRequestInput,
        idempotency_key: str | None = None,
    ) -> TrackPublic:
        """Queue a track of ``frames`` (paths or bytes, in order) for ``request`` (a
        :class:`~schemas.track_jobs.TrackCreate` or the same as a dict: REQUEST.json of
        ``proxpose track`` plus ``model_id``)."""
        parts = [("frames", image_part(frame)) for frame in frames]
        return self._submit(TRACKS, parts, request, idempotency_key)

    def get_track(self, job_id: str) -> TrackPublic:
        """The track: status, the frames so far, the result once it succeeded."""
        return self._get(TRACKS, job_id)

    def cancel_track(self, job_id: str) -> TrackPublic:
        return self._cancel(TRACKS, job_id)

    def track_artifact(self, job_id: str, name: str) -> bytes:
        """An artifact of a succeeded track: ``trajectory``, ``track.csv``, ``overlay_<k>``."""
        return self._artifact(TRACKS, job_id, name)

    def track_json(self, job_id: str) -> TrackResult:
        """The track.json of a succeeded track."""
        return self._json("GET", f"/v1/tracks/{job_id}/track.json", TrackResult)  # type: ignore[no-any-return]

    def track_events(
        self, job_id: str, reconnects: int = EVENTS_RECONNECTS
    ) -> Iterator[TrackEvent]:
        """The track's events until ``end``: ``progress`` after every frame, carrying it."""
        return self._events(TRACKS, job_id, reconnects)

    def wait_track(
        self, job_id: str, timeout_s: float | None = None, poll_s: float = POLL_S
    ) -> TrackPublic:
        return self._wait(TRACKS, job_id, timeout_s, poll_s)

    # ------------------------------------------------------------------ renders, health
    def render(self, request: RenderCreate | Mapping[str, Any]) -> bytes:
        """A PNG of the model at a pose, rendered by a worker while the call waits."""
        if isinstance(request, BaseModel):
            body = json.loads(request.model_dump_json(exclude_unset=True, by_alias=True))
        else:
            body = dict(request)
        timeout = httpx.Timeout(
            self.http.timeout.connect, read=max(120.0, self.http.timeout.read or 0)
        )
        return self._request(
            "POST", "/v1/renders", idempotent=True, json=body, timeout=timeout
        ).content

    def ready(self) -> dict[str, Any]:
        """``/readyz`` (raises :class:`ServiceUnavailable` while the service is not ready)."""
        return self._request("GET", "/readyz", idempotent=True).json()  # type: ignore[no-any-return]
