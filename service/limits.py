"""Request body size limit, enforced while the body streams in (before any parsing)."""

from __future__ import annotations

import json
from collections.abc import Callable

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send


def _too_large(size: int, limit: int) -> list[dict[str, object]]:
    msg = f"the request body is {size} bytes or more, larger than the limit of {limit} bytes"
    return [{"loc": ["body"], "msg": msg, "type": "too_large"}]


class BodySizeLimitMiddleware:
    """Answers 413 when Content-Length, or the bytes actually received, exceed the limit.

    While the app reads the body, the overflow is raised as an HTTPException from ``receive``,
    which FastAPI's body parsing re-raises as is and the exception handler turns into a 413.
    """

    def __init__(self, app: ASGIApp, max_bytes: Callable[[], int]) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.max_bytes()
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await self._reject(send, int(declared), limit)
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise HTTPException(413, detail=_too_large(received, limit))
            return message

        await self.app(scope, limited_receive, send)

    @staticmethod
    async def _reject(send: Send, size: int, limit: int) -> None:
        body = json.dumps({"detail": _too_large(size, limit)}).encode()
        headers = [(b"content-type", b"application/json"), (b"content-length", b"%d" % len(body))]
        await send({"type": "http.response.start", "status": 413, "headers": headers})
        await send({"type": "http.response.body", "body": body})
