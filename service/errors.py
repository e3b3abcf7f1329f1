"""Error answers: every error is RFC 9457 problem details (:mod:`schemas.problem`), built by
:func:`service.problems.problem`; every 4xx names the field and the problem; nothing leaks a
traceback.

Routes raise :class:`ApiError` (an HTTPException with a stable ``code`` and field errors), or
the helpers below; FastAPI's own errors (validation, 404 of an unknown path, 405) and those of
Starlette's form parser go through the same handlers.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

import redis
from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from schemas.problem import PROBLEM_MEDIA_TYPE
from service.problems import problem
from service.store.blobs import BlobStoreUnavailable

log = logging.getLogger(__name__)

#: Longest id echoed back in an error message, characters.
ECHO_MAX_CHARS = 80
#: Retry-After of a 503 while Redis is unreachable, s.
REDIS_DOWN_RETRY_AFTER_S = 5
#: Starlette's message for a multipart form field over its 1 MiB cap. Starlette 1.10 answers it
#: 400 with the parser's text as the only sign of its cause (one MultiPartException class with a
#: message, re-raised as HTTPException(400, detail=message) in starlette/requests.py, _get_form;
#: FastAPI's form_limits sets the cap but not the answer), so we know it by its text and answer
#: 413 (tests/test_framework_limits.py fails if the text or the signal changes).
STARLETTE_PART_TOO_LARGE = "Part exceeded maximum size"
#: The same for a field of a urlencoded form (FormParser), in its own words.
STARLETTE_FIELD_TOO_LARGE = "Field exceeded maximum size"
#: Starlette's message for a form with more file parts than its parser takes (1,000), answered
#: 400 the same way: a request with that many images is too large for every route we have.
STARLETTE_TOO_MANY_FILES = "Too many files"


class ApiError(HTTPException):
    """An error answer: status, ``detail`` in words, a stable ``code``, the field errors."""

    def __init__(
        self,
        status_code: int,
        detail: str | None = None,
        *,
        code: str | None = None,
        errors: Sequence[dict[str, Any]] = (),
        headers: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__(status_code, detail=detail, headers=dict(headers) if headers else None)
        self.code = code
        self.errors = list(errors)
        self.text = detail  # HTTPException fills detail with the reason phrase when None


class ProblemResponse(JSONResponse):
    media_type = PROBLEM_MEDIA_TYPE


def field_error(status_code: int, loc: Sequence[str | int], msg: str, type_: str) -> ApiError:
    """An HTTP error about one field: ``loc`` as FastAPI spells it, e.g. ("body", "image")."""
    return ApiError(status_code, code=type_, errors=[{"loc": list(loc), "msg": msg, "type": type_}])


def validation_failed(exc: ValidationError, prefix: Sequence[str | int]) -> ApiError:
    """A 422 listing pydantic's errors, located under ``prefix`` (e.g. ("body", "request"))."""
    return ApiError(
        422, code="validation_error", errors=_errors(exc.errors(include_url=False), prefix)
    )


def not_found(what: str, ident: str) -> ApiError:
    return ApiError(404, f"{what} '{echo(ident)}' not found", code="not_found")


def echo(text: str) -> str:
    """``text`` as an error message may quote it: at most ECHO_MAX_CHARS characters."""
    return text if len(text) <= ECHO_MAX_CHARS else text[:ECHO_MAX_CHARS] + "…"


def _errors(errors: Sequence[object], prefix: Sequence[str | int] = ()) -> list[dict[str, Any]]:
    out = []
    for e in errors:
        assert isinstance(e, dict)
        out.append({"loc": [*prefix, *e["loc"]], "msg": e["msg"], "type": e["type"]})
    return out


def problem_response(
    request: Request,
    status: int,
    detail: str | None = None,
    *,
    code: str | None = None,
    errors: Sequence[dict[str, Any]] = (),
    headers: Mapping[str, str] | None = None,
) -> ProblemResponse:
    body = problem(status, detail, code=code, errors=errors, instance=request.url.path)
    return ProblemResponse(body, status_code=status, headers=dict(headers) if headers else None)


async def _request_validation(request: Request, exc: Exception) -> ProblemResponse:
    assert isinstance(exc, RequestValidationError)
    # FastAPI's default echoes each "input"; an upload or a long body has no place in an error.
    return problem_response(request, 422, code="validation_error", errors=_errors(exc.errors()))


async def _http_error(request: Request, exc: Exception) -> ProblemResponse:
    assert isinstance(exc, StarletteHTTPException)
    headers = getattr(exc, "headers", None)
    if isinstance(exc, ApiError):
        return problem_response(
            request, exc.status_code, exc.text, code=exc.code, errors=exc.errors, headers=headers
        )
    if (msg := _form_too_large(exc)) is not None:
        errors = [{"loc": ["body"], "msg": msg, "type": "too_large"}]
        return problem_response(request, 413, msg, code="too_large", errors=errors)
    if isinstance(exc.detail, list):  # FastAPI's field-error shape
        return problem_response(request, exc.status_code, errors=exc.detail, headers=headers)
    detail = exc.detail if isinstance(exc.detail, str) else None
    return problem_response(request, exc.status_code, detail, headers=headers)


def _form_too_large(exc: StarletteHTTPException) -> str | None:
    """What Starlette's 400 for a form over its parser's limits means, in our words (None:
    another 400); known by the parser's text (see STARLETTE_PART_TOO_LARGE)."""
    detail = str(exc.detail)
    if exc.status_code != 400:
        return None
    if detail.startswith((STARLETTE_PART_TOO_LARGE, STARLETTE_FIELD_TOO_LARGE)):
        return (
            "a form field is larger than 1 MiB; send the request JSON as a file part "
            "(curl -F request=@request.json)"
        )
    if detail.startswith(STARLETTE_TOO_MANY_FILES):
        return f"too many file parts in one request: {detail}"
    return None


async def _redis_down(request: Request, exc: Exception) -> ProblemResponse:
    log.error("Redis error on %s %s: %s", request.method, request.url.path, exc)
    return problem_response(
        request,
        503,
        "the job store (Redis) is unreachable; try again shortly",
        code="unavailable",
        headers={"Retry-After": str(REDIS_DOWN_RETRY_AFTER_S)},
    )


#: Retry-After of an answer refused because the blob store is down, s.
BLOB_STORE_RETRY_AFTER_S = 5


async def _blob_store_down(request: Request, exc: Exception) -> ProblemResponse:
    assert isinstance(exc, BlobStoreUnavailable)
    log.error("blob store error on %s %s: %s", request.method, request.url.path, exc)
    return problem_response(
        request,
        503,
        f"the blob store ({exc.store}) is unavailable; try again shortly",
        code="store_unavailable",
        headers={"Retry-After": str(BLOB_STORE_RETRY_AFTER_S)},
    )


async def _internal(request: Request, exc: Exception) -> ProblemResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return problem_response(request, 500, "internal server error", code="internal_error")


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, _request_validation)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(redis.ConnectionError, _redis_down)
    app.add_exception_handler(redis.TimeoutError, _redis_down)
    app.add_exception_handler(BlobStoreUnavailable, _blob_store_down)
    app.add_exception_handler(Exception, _internal)
