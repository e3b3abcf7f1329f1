"""What every call of the client goes through: the transport (retries, typed errors) and the
calls every kind of job shares (submit, get, events, wait, cancel, artifact), parametrised by
its :class:`~service.client.events.JobKind` so estimates and tracks run the same code."""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
from pydantic import BaseModel

from schemas.jobs import TERMINAL_STATUSES
from schemas.version import __version__
from service.client.errors import (
    ServiceUnavailable,
    ServiceUnreachable,
    WaitTimeout,
    error_from,
)
from service.client.events import J, JobEvent, JobKind, P, parse_event, read_sse

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
#: Leading bytes of the image formats the service reads, and their media types.
_IMAGE_MAGIC = {b"\x89PNG": "image/png", b"\xff\xd8\xff": "image/jpeg"}
_IMAGE_MAGIC |= {b"II*\x00": "image/tiff", b"MM\x00*": "image/tiff"}

ImageInput = bytes | str | Path
#: A multipart part: (file name, bytes, content type).
Part = tuple[str, bytes, str]


class Calls:
    """The transport and the job calls shared by every kind of job (see :class:`Client`)."""

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

    # ------------------------------------------------------------------ jobs of any kind
    def _submit(
        self,
        kind: JobKind[P, J],
        parts: Sequence[tuple[str, Part]],
        request: BaseModel | Mapping[str, Any],
        idempotency_key: str | None,
    ) -> J:
        """Queue a job: multipart ``parts`` plus the ``request`` part, with an Idempotency-Key
        (generated when none is given, so a retried submission returns the same job)."""
        files = [*parts, ("request", ("request.json", _request_text(request), "application/json"))]
        headers = {"Idempotency-Key": idempotency_key or uuid.uuid4().hex}
        return self._json(  # type: ignore[no-any-return]
            "POST", kind.path, kind.public, files=files, headers=headers, idempotent=True
        )

    def _get(self, kind: JobKind[P, J], job_id: str) -> J:
        return self._json("GET", f"{kind.path}/{job_id}", kind.public)  # type: ignore[no-any-return]

    def _cancel(self, kind: JobKind[P, J], job_id: str) -> J:
        return self._json("DELETE", f"{kind.path}/{job_id}", kind.public)  # type: ignore[no-any-return]

    def _artifact(self, kind: JobKind[P, J], job_id: str, name: str) -> bytes:
        path = f"{kind.path}/{job_id}/artifacts/{name}"
        return self._request("GET", path, idempotent=True).content

    def _events(
        self, kind: JobKind[P, J], job_id: str, reconnects: int
    ) -> Iterator[JobEvent[P, J]]:
        """The job's events until ``end``. A dropped stream is reopened (``Last-Event-ID``: no
        progress event is repeated) up to ``reconnects`` times in a row."""
        last_id: str | None = None
        failures = 0
        while True:
            headers = {"Accept": "text/event-stream"}
            if last_id is not None:
                headers["Last-Event-ID"] = last_id
            timeout = httpx.Timeout(self.http.timeout.connect, read=EVENTS_READ_TIMEOUT_S)
            path = f"{kind.path}/{job_id}/events"
            try:
                with self.http.stream("GET", path, headers=headers, timeout=timeout) as response:
                    if not response.is_success:
                        response.read()
                        raise error_from(response)
                    for name, data, event_id in read_sse(response.iter_lines()):
                        failures = 0
                        event = parse_event(kind, name, data, event_id)
                        if event_id is not None:
                            last_id = event_id
                        yield event
                        if name == "end":
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

    def _wait(self, kind: JobKind[P, J], job_id: str, timeout_s: float | None, poll_s: float) -> J:
        """The job once it has ended: follows its event stream, and polls when the stream
        cannot be had. Raises :class:`WaitTimeout` after ``timeout_s``."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        if deadline is None:
            try:
                for event in self._events(kind, job_id, EVENTS_RECONNECTS):
                    if event.job is not None:
                        return event.job
            except (ServiceUnreachable, ServiceUnavailable):
                pass  # fall back to polling
        while True:
            job = self._get(kind, job_id)
            if job.status in TERMINAL_STATUSES:
                return job
            if deadline is not None and time.monotonic() >= deadline:
                raise WaitTimeout(job, timeout_s or 0.0)
            left = (
                poll_s if deadline is None else min(poll_s, max(0.0, deadline - time.monotonic()))
            )
            time.sleep(left)


def _request_text(request: BaseModel | Mapping[str, Any]) -> bytes:
    """The ``request`` part: a model as it was set, a dict as given (the service validates it
    and answers each bad field)."""
    if isinstance(request, BaseModel):
        return request.model_dump_json(exclude_unset=True, by_alias=True).encode()
    return json.dumps(dict(request)).encode()


def image_part(image: ImageInput) -> Part:
    """A file part of ``image`` (a path or bytes), typed as the OpenAPI document's encoding
    lists (PNG, JPEG, TIFF) by its leading bytes, else by its suffix."""
    data = image if isinstance(image, bytes) else Path(image).read_bytes()
    name = "image" if isinstance(image, bytes) else Path(image).name
    sniffed = next((t for magic, t in _IMAGE_MAGIC.items() if data.startswith(magic)), None)
    suffix = Path(name).suffix.lower()
    return name, data, sniffed or _IMAGE_TYPES.get(suffix, "application/octet-stream")
