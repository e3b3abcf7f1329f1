"""The browser pages: ``/`` (estimates and the submit form), ``/estimates/{id}``,
``/tracks/{id}``, ``/models``.

The HTML is a server-rendered frame (layout, forms, labels, empty tables); the pages' scripts
(``service/static/*.js``) fill it from the JSON API under ``/v1``, so the pages and every other
client share one code path, and the frames carry no data. Two helpers the pages need live here
too: a model's framed default request and its cached preview render.

Access control: ``service.auth.AuthMiddleware`` covers every route here like the API (with API
keys configured, a browser without the key cookie is sent to the key form at ``/session``, and
the pages' same-origin fetches carry the cookie). The page routes are all on ``router``, so a
route-level dependency would go in one place. ``/static`` (scripts, styles) is mounted
separately by ``static_files()`` and stays public: a browser sends no credentials of its own
choosing when it loads a script or a stylesheet.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates
from starlette.concurrency import run_in_threadpool
from starlette.staticfiles import PathLike
from starlette.types import Scope

from schemas.camera import IMAGE_SIDE_MAX_PX, IMAGE_SIDE_MIN_PX
from schemas.models import MODEL_ID_PATTERN, ModelPublic
from schemas.settings import get_settings
from service.deps import (
    AsyncRedisDep,
    KeysDep,
    ModelStoreDep,
    QueuesDep,
    RedisDep,
    SettingsDep,
)
from service.errors import not_found
from service.pages import PreviewCache, preview_render, preview_tag, suggested_request
from service.routes.renders import create_render

PACKAGE_DIR = Path(__file__).resolve().parents[1]
TEMPLATES_DIR = PACKAGE_DIR / "templates"
STATIC_DIR = PACKAGE_DIR / "static"
#: Browsers may keep a preview this long without asking again, s (its URL names its content).
PREVIEW_MAX_AGE_S = 7 * 24 * 3600
#: Browsers may keep the icon this long, s.
FAVICON_MAX_AGE_S = 24 * 3600

_JOB_ID = re.compile(r"^[0-9a-f]{32}$")
_MODEL_ID = re.compile(MODEL_ID_PATTERN)
_SIDE = Query(ge=IMAGE_SIDE_MIN_PX, le=IMAGE_SIDE_MAX_PX, description="Image side, px.")

router = APIRouter(include_in_schema=False, tags=["pages"])
templates = Jinja2Templates(directory=str(TEMPLATES_DIR))


class _RevalidatedStaticFiles(StaticFiles):
    """Static files the browser revalidates on each use (ETag → 304), so an upgrade of the
    service is never mixed with stale scripts (module imports carry no version in their URL)."""

    def file_response(
        self, full_path: PathLike, stat_result: os.stat_result, scope: Scope, status_code: int = 200
    ) -> Response:
        response = super().file_response(full_path, stat_result, scope, status_code)
        response.headers["Cache-Control"] = "no-cache"
        return response


def static_files() -> StaticFiles:
    """The ``/static`` app: the pages' scripts and stylesheet (mount it public)."""
    return _RevalidatedStaticFiles(directory=STATIC_DIR)


def _page(request: Request, template: str, **context: Any) -> HTMLResponse:
    context["auth_enabled"] = get_settings().auth_enabled  # shows "Sign out"
    return templates.TemplateResponse(request, template, context)


@router.get("/", response_class=HTMLResponse)
def estimates_page(request: Request) -> HTMLResponse:
    return _page(request, "index.html", page="estimates", title="Estimates", script="index.js")


def _job_page(request: Request, job_id: str, noun: str, name: str) -> HTMLResponse:
    """The page of one job: template and script ``name`` (.html, .js), or a 404 page."""
    if not _JOB_ID.match(job_id):
        response = _page(request, "missing.html", page="", title=f"No such {noun}", what=job_id)
        response.status_code = 404
        return response
    title = f"{noun.capitalize()} {job_id[:8]}"
    return _page(
        request, f"{name}.html", page=name, title=title, script=f"{name}.js", job_id=job_id
    )


@router.get("/estimates/{job_id}", response_class=HTMLResponse)
def estimate_page(request: Request, job_id: str) -> HTMLResponse:
    return _job_page(request, job_id, "estimate", "estimate")


@router.get("/tracks/{job_id}", response_class=HTMLResponse)
def track_page(request: Request, job_id: str) -> HTMLResponse:
    return _job_page(request, job_id, "track", "track")


@router.get("/favicon.ico", response_class=FileResponse)
def favicon() -> FileResponse:
    """The icon browsers ask for on their own (pages other than ours, e.g. /session, too)."""
    return FileResponse(
        STATIC_DIR / "favicon.svg",
        media_type="image/svg+xml",
        headers={"Cache-Control": f"public, max-age={FAVICON_MAX_AGE_S}"},
    )


@router.get("/models", response_class=HTMLResponse)
def models_page(request: Request) -> HTMLResponse:
    return _page(request, "models.html", page="models", title="Models", script="models.js")


def _model_or_404(models: ModelStoreDep, model_id: str) -> ModelPublic:
    model = models.get(model_id) if _MODEL_ID.match(model_id) else None
    if model is None:
        raise not_found("model", model_id)
    return model


@router.get("/models/{model_id}/request.json")
def model_request(
    model_id: str,
    models: ModelStoreDep,
    width: Annotated[int, _SIDE] = 512,
    height: Annotated[int, _SIDE] = 512,
) -> dict[str, Any]:
    """The submit form's defaults: a request framing the model in a width × height image."""
    return suggested_request(_model_or_404(models, model_id), width, height)


@router.get("/models/{model_id}/preview.png", response_class=Response)
async def model_preview(
    model_id: str,
    models: ModelStoreDep,
    queues: QueuesDep,
    r: RedisDep,
    aredis: AsyncRedisDep,
    keys: KeysDep,
    settings: SettingsDep,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """The model's preview PNG, rendered once by a worker through ``POST /v1/renders``'s code
    and kept in Redis. Without a worker it answers 503 at once (the page shows a placeholder).
    The wait for the render holds no thread (as ``POST /v1/renders``)."""
    model = await run_in_threadpool(_model_or_404, models, model_id)
    etag = f'"{preview_tag(model)}"'
    headers = {"ETag": etag, "Cache-Control": f"private, max-age={PREVIEW_MAX_AGE_S}"}
    if if_none_match == etag:
        return Response(status_code=304, headers=headers)
    cache = PreviewCache(r, keys)
    png = await run_in_threadpool(cache.get, model)
    if png is None:
        rendered = await create_render(
            preview_render(model), models, queues, aredis, keys, settings
        )
        png = bytes(rendered.body)
        await run_in_threadpool(cache.put, model, png)
    return Response(png, media_type="image/png", headers=headers)
