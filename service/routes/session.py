"""``/session``: the key form for browsers, when API keys are configured.

A browser cannot send an Authorization header when it navigates, so a page asked for without
a key is redirected here; the form posts the key, which is checked and kept in an HttpOnly,
SameSite=Strict cookie (``proxpose_api_key``) that then authenticates the pages and their
same-origin API calls. Scripts and other clients send ``Authorization: Bearer`` instead.
"""

from __future__ import annotations

import html
from typing import Annotated

from fastapi import APIRouter, Form, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse

from schemas.settings import API_KEY_MIN_CHARS
from service.auth import COOKIE_NAME, identify
from service.deps import SettingsDep

router = APIRouter(prefix="/session", include_in_schema=False)

#: How long a remembered key stays in the browser, s.
REMEMBER_S = 30 * 24 * 3600
#: Longest key accepted by the form (longer is not a key), characters.
KEY_MAX_CHARS = 512

_FORM = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>proxpose: API key</title>
<meta name="viewport" content="width=device-width, initial-scale=1"></head>
<body><main>
<h1>proxpose</h1>
<p>This service needs an API key.</p>{message}
<form method="post" action="/session">
<input type="hidden" name="next" value="{next}">
<label>API key <input type="password" name="api_key" required minlength="{min_chars}"
 maxlength="{max_chars}" autocomplete="current-password" autofocus></label>
<label><input type="checkbox" name="remember" value="1"> remember on this browser</label>
<button type="submit">Continue</button>
</form></main></body></html>
"""


def _safe_next(target: str) -> str:
    """A local path to return to (never another site: no scheme, no '//' or backslash)."""
    if not target.startswith("/") or target.startswith("//") or "\\" in target:
        return "/"
    return target


def _form(target: str, message: str = "", status: int = 200) -> HTMLResponse:
    paragraph = f"\n<p><strong>{html.escape(message)}</strong></p>" if message else ""
    page = _FORM.format(
        message=paragraph,
        next=html.escape(_safe_next(target)),
        min_chars=API_KEY_MIN_CHARS,
        max_chars=KEY_MAX_CHARS,
    )
    return HTMLResponse(page, status_code=status, headers={"Cache-Control": "no-store"})


@router.get("")
def key_form(next: Annotated[str, Query(max_length=2048)] = "/") -> HTMLResponse:
    return _form(next)


@router.post("", response_model=None)
def sign_in(
    request: Request,
    settings: SettingsDep,
    api_key: Annotated[str, Form(max_length=KEY_MAX_CHARS)],
    next: Annotated[str, Form(max_length=2048)] = "/",
    remember: Annotated[str | None, Form(max_length=1)] = None,
) -> HTMLResponse | RedirectResponse:
    if not settings.auth_enabled:
        return RedirectResponse(_safe_next(next), status_code=303)
    if identify(settings, api_key.strip()) is None:
        return _form(next, "That key is not valid here.", status=401)
    response = RedirectResponse(_safe_next(next), status_code=303)
    response.set_cookie(
        COOKIE_NAME,
        api_key.strip(),
        max_age=REMEMBER_S if remember else None,
        path="/",
        secure=request.url.scheme == "https",
        httponly=True,
        samesite="strict",
    )
    return response


@router.post("/logout")
def sign_out() -> RedirectResponse:
    response = RedirectResponse("/session", status_code=303)
    response.delete_cookie(COOKIE_NAME, path="/", httponly=True, samesite="strict")
    return response
