"""Error answers: every 4xx names the field and the problem; nothing leaks a traceback.

Field errors use FastAPI's shape, ``{"detail": [{"loc": [...], "msg": "...", "type": "..."}]}``,
whether pydantic or an explicit check found them; other errors are ``{"detail": "..."}``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import redis
from fastapi import FastAPI, HTTPException, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.store.blobs import BlobStoreUnavailable

log = logging.getLogger(__name__)

#: Longest id echoed back in an error message, characters.
ECHO_MAX_CHARS = 80
#: Starlette's message for a multipart form field over its 1 MiB cap (answered 400 otherwise).
_PART_TOO_LARGE = "Part exceeded maximum size"


def field_error(status_code: int, loc: Sequence[str | int], msg: str, type_: str) -> HTTPException:
    """An HTTP error about one field: ``loc`` as FastAPI spells it, e.g. ("body", "image")."""
    return HTTPException(status_code, detail=[{"loc": list(loc), "msg": msg, "type": type_}])


def validation_failed(exc: ValidationError, prefix: Sequence[str | int]) -> HTTPException:
    """A 422 listing pydantic's errors, located under ``prefix`` (e.g. ("body", "request"))."""
    return HTTPException(422, detail=_errors(exc.errors(include_url=False), prefix))


def not_found(what: str, ident: str) -> HTTPException:
    return HTTPException(404, detail=f"{what} '{echo(ident)}' not found")


def echo(text: str) -> str:
    """``text`` as an error message may quote it: at most ECHO_MAX_CHARS characters."""
    return text if len(text) <= ECHO_MAX_CHARS else text[:ECHO_MAX_CHARS] + "…"


def _errors(errors: Sequence[object], prefix: Sequence[str | int] = ()) -> list[dict[str, object]]:
    out = []
    for e in errors:
        assert isinstance(e, dict)
        out.append({"loc": [*prefix, *e["loc"]], "msg": e["msg"], "type": e["type"]})
    return out


async def _request_validation(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    # FastAPI's default echoes each "input"; an upload or a long body has no place in an error.
    return JSONResponse({"detail": _errors(exc.errors())}, status_code=422)


async def _http_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    if exc.status_code == 400 and str(exc.detail).startswith(_PART_TOO_LARGE):
        msg = (
            "a form field is larger than 1 MiB; send the request JSON as a file part "
            "(curl -F request=@request.json)"
        )
        return JSONResponse(
            {"detail": [{"loc": ["body"], "msg": msg, "type": "too_large"}]}, status_code=413
        )
    return await http_exception_handler(request, exc)


async def _redis_down(request: Request, exc: Exception) -> JSONResponse:
    log.error("Redis error on %s %s: %s", request.method, request.url.path, exc)
    return JSONResponse(
        {"detail": "the job store (Redis) is unreachable; try again shortly"}, status_code=503
    )


#: Retry-After of an answer refused because the blob store is down, s.
BLOB_STORE_RETRY_AFTER_S = 5


async def _blob_store_down(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, BlobStoreUnavailable)
    log.error("blob store error on %s %s: %s", request.method, request.url.path, exc)
    return JSONResponse(
        {"detail": f"the blob store ({exc.store}) is unavailable; try again shortly"},
        status_code=503,
        headers={"Retry-After": str(BLOB_STORE_RETRY_AFTER_S)},
    )


async def _internal(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return JSONResponse({"detail": "internal server error"}, status_code=500)


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, _request_validation)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(redis.ConnectionError, _redis_down)
    app.add_exception_handler(redis.TimeoutError, _redis_down)
    app.add_exception_handler(BlobStoreUnavailable, _blob_store_down)
    app.add_exception_handler(Exception, _internal)
