"""API keys: who is calling, decided before the request body is read.

Keys come from the settings (``PROXPOSE_API_KEYS``, ``PROXPOSE_ADMIN_API_KEYS``). With none
set, every caller is the anonymous admin (one open deployment). With keys set, every path but
the public ones (probes, metrics, the OpenAPI docs, static assets, the key form) needs a key:
``Authorization: Bearer <key>``, or the ``proxpose_api_key`` cookie that ``POST /session``
sets for browsers (HttpOnly, SameSite=Strict; with a cookie, a state-changing request must come
from the same origin). The presented key is compared with every configured key in constant
time. The principal is left in ``request.state.principal`` for the routes (``PrincipalDep``).
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable
from http.cookies import SimpleCookie
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import Depends, FastAPI, HTTPException, Request
from starlette.types import ASGIApp, Receive, Scope, Send

from schemas.settings import Settings
from service.problems import send_problem
from service.store import ANONYMOUS, Principal

#: Paths that never need a key: probes, metrics, the API description, the key form.
PUBLIC_PATHS = frozenset(
    {
        "/healthz",
        "/readyz",
        "/metrics",
        "/openapi.json",
        "/docs",
        "/docs/oauth2-redirect",
        "/redoc",
        "/session",
        "/session/logout",
        "/favicon.ico",
    }
)
#: Path prefixes that never need a key (scripts and styles: a browser cannot send a header).
PUBLIC_PREFIXES = ("/static/",)
#: Cookie carrying the key for browser navigations (set by POST /session).
COOKIE_NAME = "proxpose_api_key"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
CHALLENGE = 'Bearer realm="proxpose"'


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode("utf-8", "surrogateescape")).digest()


def identify(settings: Settings, token: str) -> Principal | None:
    """The principal whose key is ``token``, or None. Every configured key is compared, in
    constant time (digests of equal length), whatever matches first."""
    presented = _digest(token)
    found = None
    for admin, table in ((False, settings.api_keys), (True, settings.admin_api_keys)):
        for name, key in table.items():
            if hmac.compare_digest(presented, _digest(key)) and found is None:
                found = Principal(name, admin)
    return found


def is_public(path: str) -> bool:
    return path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)


def _headers(scope: Scope) -> dict[bytes, bytes]:
    return {k.lower(): v for k, v in scope.get("headers", [])}


def _credentials(headers: dict[bytes, bytes]) -> tuple[str | None, bool]:
    """(the presented key, whether it came in the cookie)."""
    auth = headers.get(b"authorization", b"").decode("latin-1").strip()
    scheme, _, token = auth.partition(" ")
    if scheme.lower() == "bearer" and token.strip():
        return token.strip(), False
    cookie = headers.get(b"cookie")
    if cookie:
        jar: SimpleCookie = SimpleCookie()
        try:
            jar.load(cookie.decode("latin-1"))
        except Exception:  # a malformed Cookie header is no credential
            return None, False
        if COOKIE_NAME in jar and jar[COOKIE_NAME].value:
            return jar[COOKIE_NAME].value, True
    return None, False


def same_origin(scope: Scope, headers: dict[bytes, bytes]) -> bool:
    """Whether a browser request comes from a page of this service (CSRF check for cookie
    authentication; SameSite=Strict already keeps the cookie off cross-site requests)."""
    origin = headers.get(b"origin")
    if origin is not None:
        host = headers.get(b"host", b"").decode("latin-1")
        return origin.decode("latin-1") == f"{scope.get('scheme', 'http')}://{host}"
    site = headers.get(b"sec-fetch-site")
    return site is None or site in (b"same-origin", b"none")


def _wants_html(scope: Scope, headers: dict[bytes, bytes]) -> bool:
    return scope.get("method") == "GET" and b"text/html" in headers.get(b"accept", b"")


class AuthMiddleware:
    """Authenticates every non-public request before the app reads its body: 401 without a
    valid key (a browser navigation is sent to the key form instead), 403 for a cross-site
    state change carried by the cookie."""

    def __init__(self, app: ASGIApp, settings: Callable[[], Settings]) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        settings = self.settings()
        state = scope.setdefault("state", {})
        if not settings.auth_enabled:
            state["principal"] = ANONYMOUS
            await self.app(scope, receive, send)
            return
        if is_public(scope["path"]):
            await self.app(scope, receive, send)
            return
        headers = _headers(scope)
        token, via_cookie = _credentials(headers)
        principal = identify(settings, token) if token else None
        if principal is None:
            if _wants_html(scope, headers):
                target = quote(scope["path"], safe="/")
                await _redirect(send, f"/session?next={target}")
                return
            why = "invalid API key" if token else "this API needs a key"
            detail = f"{why}: send the header 'Authorization: Bearer <key>'"
            await send_problem(
                send,
                401,
                detail,
                code="unauthorized",
                instance=scope["path"],
                headers=[(b"www-authenticate", CHALLENGE.encode())],
            )
            return
        if via_cookie and scope["method"] not in SAFE_METHODS and not same_origin(scope, headers):
            await send_problem(
                send,
                403,
                "cross-site request refused (cookie credentials)",
                code="cross_site",
                instance=scope["path"],
            )
            return
        state["principal"] = principal
        await self.app(scope, receive, send)


async def _redirect(send: Send, location: str) -> None:
    headers = [(b"content-length", b"0"), (b"location", location.encode())]
    await send({"type": "http.response.start", "status": 303, "headers": headers})
    await send({"type": "http.response.body", "body": b""})


async def get_principal(request: Request) -> Principal:
    """The caller, as AuthMiddleware identified it (401 if it did not)."""
    principal = request.scope.get("state", {}).get("principal")
    if not isinstance(principal, Principal):
        raise HTTPException(
            401, detail="this API needs a key", headers={"WWW-Authenticate": CHALLENGE}
        )
    return principal


PrincipalDep = Annotated[Principal, Depends(get_principal)]


def document_bearer_auth(app: FastAPI) -> None:
    """Declare the Bearer scheme in the OpenAPI schema on every non-public operation, so that
    /docs offers "Authorize" and clients' generators know the header."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = build()
        schemes = schema.setdefault("components", {}).setdefault("securitySchemes", {})
        schemes["apiKey"] = {
            "type": "http",
            "scheme": "bearer",
            "description": "An API key of PROXPOSE_API_KEYS or PROXPOSE_ADMIN_API_KEYS (needed "
            "only when keys are configured).",
        }
        for path, operations in schema.get("paths", {}).items():
            if not is_public(path):
                for operation in operations.values():
                    operation.setdefault("security", [{"apiKey": []}])
                    operation.setdefault("responses", {}).setdefault(
                        "401", {"description": "No valid API key (when keys are configured)."}
                    )
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
