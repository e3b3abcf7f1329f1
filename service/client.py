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
from dataclasses import dataclass
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
    Progress,
    RenderCreate,
)
from schemas.models import ModelList, ModelPublic
from schemas.problem import Problem
from schemas.version import __version__

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


# ----------------------------------------------------------------------------- errors
class ProxposeClientError(Exception):
    """Base of the client's errors."""


class ServiceUnreachable(ProxposeClientError):
    """No answer from the service (connection refused, dropped, timed out) after the retries."""


class ApiError(ProxposeClientError):
    """The service answered an error; ``problem`` holds its problem details."""

    def __init__(self, status: int, problem: Problem, headers: Mapping[str, str]) -> None:
        self.status = status
        self.problem = problem
        self.code = problem.code
        self.errors = problem.errors
        self.retry_after_s = _retry_after(headers)
        super().__init__(f"{status} {problem.code}: {problem.detail}")


class BadRequest(ApiError):
    """400 or 422: a field is invalid (``errors`` names each)."""


class Unauthorized(ApiError):
    """401: no valid API key."""


class Forbidden(ApiError):
    """403: the key may not do that (a quota, a cross-site request)."""


class NotFound(ApiError):
    """404: no such job, model or artifact (or another key's)."""


class Conflict(ApiError):
    """409: the job has already ended, a model is built in, an idempotent retry is in flight."""


class PayloadTooLarge(ApiError):
    """413: an upload or the request JSON is over its limit."""


class UnsupportedMediaType(ApiError):
    """415: the body is not of the type the route reads."""


class RateLimited(ApiError):
    """429: too many submissions, or too many active jobs; see ``retry_after_s``."""


class ServiceUnavailable(ApiError):
    """503: the service cannot serve now (its Redis is away, no worker for a render)."""


class ServerError(ApiError):
    """500 or another 5xx."""


_BY_STATUS: dict[int, type[ApiError]] = {
    400: BadRequest,
    401: Unauthorized,
    403: Forbidden,
    404: NotFound,
    409: Conflict,
    413: PayloadTooLarge,
    415: UnsupportedMediaType,
    422: BadRequest,
    429: RateLimited,
    503: ServiceUnavailable,
}


class WaitTimeout(ProxposeClientError):
    """``wait`` gave up before the job ended; ``job`` is its last state."""

    def __init__(self, job: EstimatePublic, timeout_s: float) -> None:
        self.job = job
        super().__init__(f"estimate {job.id} is still {job.status} after {timeout_s:g} s")


def _retry_after(headers: Mapping[str, str]) -> float | None:
    value = headers.get("retry-after")
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None  # an HTTP date: not sent by this service


def error_from(response: httpx.Response) -> ApiError:
    """The typed error of an error answer (a non-problem body is wrapped in one)."""
    try:
        problem = Problem.model_validate(response.json())
    except (ValueError, json.JSONDecodeError):
        problem = Problem(
            type="about:blank",
            title=response.reason_phrase or "Error",
            status=response.status_code,
            detail=response.text[:500] or response.reason_phrase or "error",
            code="http_" + str(response.status_code),
        )
    cls = _BY_STATUS.get(
        response.status_code, ServerError if response.status_code >= 500 else ApiError
    )
    return cls(response.status_code, problem, response.headers)


# ----------------------------------------------------------------------------- events
@dataclass(frozen=True)
class JobEvent:
    """One event of a job's stream: ``status`` (``status`` set), ``progress`` (``progress``
    set, after every iteration) or ``end`` (``job`` set: the final resource)."""

    kind: str
    status: JobStatus | None = None
    progress: Progress | None = None
    job: EstimatePublic | None = None
    id: str | None = None


def _parse_event(kind: str, data: str, event_id: str | None) -> JobEvent:
    if kind == "progress":
        return JobEvent(kind, progress=Progress.model_validate_json(data), id=event_id)
    if kind == "end":
        job = EstimatePublic.model_validate_json(data)
        return JobEvent(kind, status=job.status, job=job, id=event_id)
    payload = json.loads(data)
    return JobEvent(kind, status=payload.get("status"), id=event_id)


def _sse(lines: Iterator[str]) -> Iterator[tuple[str, str, str | None]]:
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
                    for kind, data, event_id in _sse(response.iter_lines()):
                        failures = 0
                        event = _parse_event(kind, data, event_id)
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
