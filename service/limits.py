"""Request body size limit, enforced while the body streams in (before any parsing).

Ours, not FastAPI's ``max_body_size`` (app, router or route): with FastAPI 0.165 / Starlette
1.10, a body whose Content-Length is over that limit is answered with a plain-text 413 whatever
our handlers answer (``RequestBodyLimitResponder.send_with_limit`` in
starlette/middleware/body_limit.py swaps the response for ``PlainTextResponse("Content Too
Large")``), so the 413 could not be problem details naming ``body``.
tests/test_framework_limits.py records that behaviour and fails once it changes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import ApiError
from service.problems import send_problem


def _too_large(size: int, limit: int) -> list[dict[str, Any]]:
    msg = f"the request body is {size} bytes or more, larger than the limit of {limit} bytes"
    return [{"loc": ["body"], "msg": msg, "type": "too_large"}]


class BodySizeLimitMiddleware:
    """Answers 413 when Content-Length, or the bytes actually received, exceed the limit
    (``max_bytes(path)``: a route that takes several files has a larger one).

    While the app reads the body, the overflow is raised as an ApiError from ``receive``,
    which FastAPI's body parsing re-raises as is and the exception handler turns into a 413.
    """

    def __init__(self, app: ASGIApp, max_bytes: Callable[[str], int]) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.max_bytes(scope["path"])
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            errors = _too_large(int(declared), limit)
            await send_problem(
                send, 413, errors[0]["msg"], code="too_large", errors=errors, instance=scope["path"]
            )
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise ApiError(413, code="too_large", errors=_too_large(received, limit))
            return message

        await self.app(scope, limited_receive, send)
