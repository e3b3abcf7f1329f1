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

Retries: a dropped connection, a 503 or a 429 with ``Retry-After`` is retried (up to
``retries`` times, waiting as the service says, at most ``max_retry_wait_s`` a time). A
submission is retried only with an Idempotency-Key, so one is generated when none is given: a
retried submission returns the job the first attempt created instead of a second one.
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import httpx
from pydantic import BaseModel

from schemas.jobs import (
    TERMINAL_STATUSES,
    EstimateCreate,
    EstimateList,
    EstimatePublic,
    EstimateSummary,
    JobStatus,
    RenderCreate,
)
from schemas.models import ModelList, ModelPublic
from schemas.version import __version__
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
    error_from,
)
from service.client.events import JobEvent, parse_event, read_sse

__all__ = [
    "ApiError",
    "BadRequest",
    "Client",
    "Conflict",
    "Forbidden",
    "JobEvent",
    "NotFound",
    "PayloadTooLarge",
    "ProxposeClientError",
    "RateLimited",
    "ServerError",
    "ServiceUnavailable",
    "ServiceUnreachable",
    "Unauthorized",
    "UnsupportedMediaType",
    "WaitTimeout",
]

#: Default timeout of one HTTP request, s.
DEFAULT_TIMEOUT_S = 30.0
#: Default retries of a request after a dropped connection, a 503 or a 429.
DEFAULT_RETRIES = 3
#: Longest wait before one retry, s (a Retry-After above it is cut to it).
MAX_RETRY_WAIT_S = 30.0
#: First pause after a dropped connection, s (doubled at each further retry).
BACKOFF_S = 0.5
#: Interval of polling when the event stream is not available, s.
POLL_S = 1.0
#: Read timeout of an event stream, s: the service sends a keep-alive every 15 s by default.
EVENTS_READ_TIMEOUT_S = 60.0
#: Times an event stream is reopened after it dropped, before ``wait`` falls back to polling.
EVENTS_RECONNECTS = 5
_IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}
_IMAGE_TYPES |= {".tif": "image/tiff", ".tiff": "image/tiff"}


# ----------------------------------------------------------------------------- the client
ImageInput = bytes | str | Path
RequestInput = EstimateCreate | Mapping[str, Any]
#: One status or several (a list, since ``Client.list`` hides the builtin in the class).
StatusFilter = JobStatus | list[JobStatus] | None


class Client:
    """Calls of the ``/v1`` API (see the module docstring); use as a context manager, or
    ``close()`` it."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        api_key: str | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        max_retry_wait_s: float = MAX_RETRY_WAIT_S,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        headers = {"User-Agent": f"proxpose-client/{__version__}"}
        if api_key:
            headers["Authorization"] = f"Bearer {api_key}"
        self.retries = retries
        self.max_retry_wait_s = max_retry_wait_s
        self.http = httpx.Client(
            base_url=base_url.rstrip("/"), headers=headers, timeout=timeout_s, transport=transport
        )

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ transport
    def _request(
        self, method: str, path: str, *, idempotent: bool, **kwargs: Any
    ) -> httpx.Response:
        """One call, retried after a dropped connection (when ``idempotent``) and after a 503
        or 429 (as Retry-After says); error answers raise :class:`ApiError`."""
        attempt = 0
        while True:
            try:
                response = self.http.request(method, path, **kwargs)
            except httpx.TransportError as exc:
                if not idempotent or attempt >= self.retries:
                    raise ServiceUnreachable(f"{method} {path}: {exc!r}") from exc
                self._pause(BACKOFF_S * 2**attempt)
                attempt += 1
                continue
            if response.is_success:
                return response
            error = error_from(response)
            retryable = response.status_code in (429, 503) and error.retry_after_s is not None
            if not retryable or attempt >= self.retries:
                raise error
            self._pause(error.retry_after_s or BACKOFF_S)
            attempt += 1

    def _pause(self, seconds: float) -> None:
        time.sleep(min(self.max_retry_wait_s, seconds))

    def _json(self, method: str, path: str, model: type[Any], **kwargs: Any) -> Any:
        idempotent = kwargs.pop("idempotent", method in ("GET", "DELETE"))
        response = self._request(method, path, idempotent=idempotent, **kwargs)
        return model.model_validate(response.json())

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
        if isinstance(request, BaseModel):
            text = request.model_dump_json(exclude_unset=True, by_alias=True)
        else:
            text = json.dumps(dict(request))
        files = {
            "image": _image_part(image),
            "request": ("request.json", text.encode(), "application/json"),
        }
        key = idempotency_key or uuid.uuid4().hex
        return self._json(  # type: ignore[no-any-return]
            "POST",
            "/v1/estimates",
            EstimatePublic,
            files=files,
            headers={"Idempotency-Key": key},
            idempotent=True,
        )

    def get(self, job_id: str) -> EstimatePublic:
        return self._json("GET", f"/v1/estimates/{job_id}", EstimatePublic)  # type: ignore[no-any-return]

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
        return self._json("DELETE", f"/v1/estimates/{job_id}", EstimatePublic)  # type: ignore[no-any-return]

    def artifact(self, job_id: str, name: str) -> bytes:
        """A PNG artifact of a succeeded job (``difference``, ``final_render``, ...)."""
        return self._request(
            "GET", f"/v1/estimates/{job_id}/artifacts/{name}", idempotent=True
        ).content

    def events(self, job_id: str, reconnects: int = EVENTS_RECONNECTS) -> Iterator[JobEvent]:
        """The job's events until ``end``. A dropped stream is reopened (``Last-Event-ID``: no
        progress event is repeated) up to ``reconnects`` times in a row."""
        last_id: str | None = None
        failures = 0
        while True:
            headers = {"Accept": "text/event-stream"}
            if last_id is not None:
                headers["Last-Event-ID"] = last_id
            timeout = httpx.Timeout(self.http.timeout.connect, read=EVENTS_READ_TIMEOUT_S)
            try:
                with self.http.stream(
                    "GET", f"/v1/estimates/{job_id}/events", headers=headers, timeout=timeout
                ) as response:
                    if not response.is_success:
                        response.read()
                        raise error_from(response)
                    for kind, data, event_id in read_sse(response.iter_lines()):
                        failures = 0
                        event = parse_event(kind, data, event_id)
                        if event_id is not None:
                            last_id = event_id
                        yield event
                        if kind == "end":
                            return
            except httpx.TransportError as exc:
                failures += 1
                if failures > reconnects:
                    raise ServiceUnreachable(f"event stream of {job_id}: {exc!r}") from exc
                self._pause(BACKOFF_S * 2 ** (failures - 1))
                continue
            # the stream closed without an end event (the job expired): ask for its state
            failures += 1
            if failures > reconnects:
                raise ServiceUnreachable(f"event stream of {job_id} closed without an end")

    def wait(
        self, job_id: str, timeout_s: float | None = None, poll_s: float = POLL_S
    ) -> EstimatePublic:
        """The job once it has ended (succeeded, failed or cancelled): follows its event stream,
        and polls when the stream cannot be had. Raises :class:`WaitTimeout` after
        ``timeout_s``."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        if deadline is None:
            try:
                for event in self.events(job_id):
                    if event.job is not None:
                        return event.job
            except (ServiceUnreachable, ServiceUnavailable):
                pass  # fall back to polling
        while True:
            job = self.get(job_id)
            if job.status in TERMINAL_STATUSES:
                return job
            if deadline is not None and time.monotonic() >= deadline:
                raise WaitTimeout(job, timeout_s or 0.0)
            left = (
                poll_s if deadline is None else min(poll_s, max(0.0, deadline - time.monotonic()))
            )
            time.sleep(left)

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


def _image_part(image: ImageInput) -> tuple[str, bytes, str]:
    if isinstance(image, bytes):
        return "image", image, "application/octet-stream"
    path = Path(image)
    return (
        path.name,
        path.read_bytes(),
        _IMAGE_TYPES.get(path.suffix.lower(), "application/octet-stream"),
    )
