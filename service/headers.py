"""Response headers for browsers: security headers on HTML pages, and CORS only if configured.

Every response gets ``X-Content-Type-Options: nosniff``. HTML responses also get a Content
Security Policy without inline scripts (the pages load their scripts from /static), unless the
route set a policy of its own (``/docs`` allows its one inline script by hash), framing
forbidden (``frame-ancestors 'none'`` and ``X-Frame-Options: DENY``) and no Referer.

CORS is off (no Access-Control-* headers: browsers keep other origins out) unless
``PROXPOSE_CORS_ORIGINS`` lists origins; it is read per request, not at import.
"""

from __future__ import annotations

from collections.abc import Callable

from starlette.middleware.cors import CORSMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from schemas.settings import Settings

PAGE_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
    "connect-src 'self'; font-src 'self'; object-src 'none'; base-uri 'none'; "
    "form-action 'self'; frame-ancestors 'none'"
)
HTML_HEADERS = [
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
    (b"cross-origin-opener-policy", b"same-origin"),
]
#: Request headers a cross-origin client may send, and response headers it may read.
CORS_ALLOW_HEADERS = ["Authorization", "Content-Type", "Idempotency-Key"]
CORS_EXPOSE_HEADERS = ["Location", "Retry-After", "Idempotent-Replayed"]


class SecurityHeadersMiddleware:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                names = {k.lower() for k, _ in headers}
                if b"x-content-type-options" not in names:
                    headers.append((b"x-content-type-options", b"nosniff"))
                content_type = dict(headers).get(b"content-type", b"")
                if content_type.startswith(b"text/html"):
                    if b"content-security-policy" not in names:
                        headers.append((b"content-security-policy", PAGE_CSP.encode()))
                    headers += [h for h in HTML_HEADERS if h[0] not in names]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


class ConfiguredCORSMiddleware:
    """Starlette's CORS for ``settings.cors_origins``; a no-op when the list is empty."""

    def __init__(self, app: ASGIApp, settings: Callable[[], Settings]) -> None:
        self.app = app
        self.settings = settings
        self._cors: dict[tuple[str, ...], CORSMiddleware] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        origins = tuple(self.settings().cors_origins) if scope["type"] == "http" else ()
        if not origins:
            await self.app(scope, receive, send)
            return
        cors = self._cors.get(origins)
        if cors is None:
            cors = CORSMiddleware(
                self.app,
                allow_origins=list(origins),
                allow_methods=["GET", "POST", "DELETE"],
                allow_headers=CORS_ALLOW_HEADERS,
                expose_headers=CORS_EXPOSE_HEADERS,
                allow_credentials=False,
                max_age=600,
            )
            self._cors = {origins: cors}
        await cors(scope, receive, send)
