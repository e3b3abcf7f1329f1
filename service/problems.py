"""The one builder of error answers (RFC 9457 problem details, :mod:`schemas.problem`).

Used by the exception handlers (:mod:`service.errors`) and by the ASGI middlewares that answer
before a route runs (size limit, authentication, rate limit); no FastAPI here, so middlewares
stay plain ASGI.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from http import HTTPStatus
from typing import Any

from starlette.types import Send

from schemas.problem import PROBLEM_MEDIA_TYPE, problem_type

#: Default ``code`` of an error by HTTP status.
STATUS_CODES: dict[int, str] = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    409: "conflict",
    413: "too_large",
    415: "unsupported_media_type",
    422: "validation_error",
    429: "rate_limited",
    500: "internal_error",
    503: "unavailable",
    504: "timeout",
}


def default_code(status: int) -> str:
    return STATUS_CODES.get(status, "client_error" if status < 500 else "server_error")


def title(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


def describe_errors(errors: Sequence[dict[str, Any]]) -> str:
    """A one-line ``detail`` for field errors: 'request.camera.fx: msg (and 2 more)'."""
    first = errors[0]
    where = ".".join(str(p) for p in first["loc"] if p != "body") or "body"
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{where}: {first['msg']}{more}"


def problem(
    status: int,
    detail: str | None = None,
    *,
    code: str | None = None,
    errors: Sequence[dict[str, Any]] = (),
    instance: str | None = None,
) -> dict[str, Any]:
    """The problem details object for an error (``detail`` defaults to the field errors')."""
    if detail is None:
        detail = describe_errors(errors) if errors else title(status)
    code = code or default_code(status)
    body: dict[str, Any] = {
        "type": problem_type(code),
        "title": title(status),
        "status": status,
        "detail": detail,
        "code": code,
    }
    if instance is not None:
        body["instance"] = instance
    if errors:
        body["errors"] = [
            {"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in errors
        ]
    return body


def encode(body: dict[str, Any]) -> bytes:
    return json.dumps(body, ensure_ascii=False).encode()


async def send_problem(
    send: Send,
    status: int,
    detail: str,
    *,
    code: str | None = None,
    instance: str | None = None,
    headers: Sequence[tuple[bytes, bytes]] = (),
    errors: Sequence[dict[str, Any]] = (),
) -> None:
    """Answer an ASGI request with a problem (for middlewares that answer before the app)."""
    body = encode(problem(status, detail, code=code, errors=errors, instance=instance))
    head = [
        (b"content-type", PROBLEM_MEDIA_TYPE.encode()),
        (b"content-length", b"%d" % len(body)),
        *headers,
    ]
    await send({"type": "http.response.start", "status": status, "headers": head})
    await send({"type": "http.response.body", "body": body})
