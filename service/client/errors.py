"""The client's errors: :class:`ApiError` and a subclass per status, carrying the problem
details (:class:`~schemas.problem.Problem`) the service answered."""

from __future__ import annotations

import json
from collections.abc import Mapping

import httpx

from schemas.jobs import JobSummary
from schemas.problem import Problem
from schemas.track_jobs import TrackPublic


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

    def __init__(self, job: JobSummary, timeout_s: float) -> None:
        self.job = job
        kind = "track" if isinstance(job, TrackPublic) else "estimate"
        super().__init__(f"{kind} {job.id} is still {job.status} after {timeout_s:g} s")


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
