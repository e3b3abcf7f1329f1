"""``/docs``: Swagger UI from the service's own files, so the API docs work offline.

FastAPI's built-in ``/docs`` and ``/redoc`` load their scripts from a CDN and are blank without
Internet access; the app turns them off (``docs_url=None, redoc_url=None``) and this router
serves Swagger UI from ``service/static/swagger/`` (``swagger-ui-dist``, vendored; version and
license there). ``/redoc`` redirects here (ReDoc is not vendored).

Content Security Policy: ``service.headers.SecurityHeadersMiddleware`` gives the docs paths
their own policy (``DOCS_CSP``, which allows inline scripts). This page carries a second, stricter
policy of its own, and a browser enforces both: scripts only from this origin plus the one
inline bootstrap script that ``get_swagger_ui_html`` emits, allowed by its SHA-256 hash (computed
from the HTML, so it follows FastAPI's template); no CDN. Styles may be inline (Swagger UI sets
style attributes); images from this origin or ``data:`` (its icons).
"""

from __future__ import annotations

import base64
import hashlib
import re
from functools import lru_cache

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, RedirectResponse

router = APIRouter(include_in_schema=False, tags=["docs"])

#: Where ``/static`` serves ``service/static/swagger/``.
ASSETS = "/static/swagger"
SWAGGER_JS_URL = f"{ASSETS}/swagger-ui-bundle.js"
SWAGGER_CSS_URL = f"{ASSETS}/swagger-ui.css"
SWAGGER_FAVICON_URL = f"{ASSETS}/favicon-32x32.png"
#: Swagger UI settings beside FastAPI's defaults: no call to the online validator.
SWAGGER_UI_PARAMETERS = {"validatorUrl": None}
_INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.DOTALL)


def docs_csp(html: str) -> str:
    """The page's policy: this origin, plus the inline scripts of ``html`` by their hashes."""
    hashes = " ".join(
        "'sha256-" + base64.b64encode(hashlib.sha256(s.encode()).digest()).decode() + "'"
        for s in _INLINE_SCRIPT.findall(html)
    )
    return (
        f"default-src 'none'; script-src 'self' {hashes}; style-src 'self' 'unsafe-inline'; "
        "img-src 'self' data:; connect-src 'self'; font-src 'self'; object-src 'none'; "
        "base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
    )


@lru_cache(maxsize=4)
def _page(openapi_url: str, title: str) -> tuple[bytes, str]:
    html = get_swagger_ui_html(
        openapi_url=openapi_url,
        title=title,
        swagger_js_url=SWAGGER_JS_URL,
        swagger_css_url=SWAGGER_CSS_URL,
        swagger_favicon_url=SWAGGER_FAVICON_URL,
        swagger_ui_parameters=SWAGGER_UI_PARAMETERS,
    )
    body = bytes(html.body)
    return body, docs_csp(body.decode())


@router.api_route("/docs", methods=["GET", "HEAD"], response_class=HTMLResponse)
def swagger_ui(request: Request) -> HTMLResponse:
    """Swagger UI for the app's OpenAPI document, from local assets."""
    app = request.app
    openapi_url = request.scope.get("root_path", "") + (app.openapi_url or "/openapi.json")
    body, csp = _page(openapi_url, f"{app.title} – API docs")
    return HTMLResponse(body, headers={"Content-Security-Policy": csp})


@router.api_route("/redoc", methods=["GET", "HEAD"])
def redoc() -> RedirectResponse:
    """The former ReDoc page: the docs are at ``/docs``."""
    return RedirectResponse("/docs", status_code=307)
