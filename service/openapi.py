"""The OpenAPI document, completed where FastAPI cannot infer it.

- Operation ids are the route functions' names (``create_estimate``), not FastAPI's
  ``create_estimate_v1_estimates_post``: clients generated from the document keep them.
- The multipart bodies of ``POST /v1/estimates`` and ``POST /v1/tracks`` describe their
  ``request`` part as ``application/json`` with the :class:`~schemas.jobs.EstimateCreate` /
  :class:`~schemas.track_jobs.TrackCreate` schema (the routes read it as text, to answer their
  own field errors), so the camera, pose, lighting and options models are in the components
  with their docs and examples.
- Every error answer is ``application/problem+json`` with the :class:`~schemas.problem.Problem`
  schema; every operation documents 422 (when it takes input), 500 and 503 (Redis away), and
  ``Retry-After`` on 202, 429 and 503.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from fastapi.routing import APIRoute
from pydantic.json_schema import models_json_schema

from schemas.jobs import EstimateCreate
from schemas.problem import PROBLEM_MEDIA_TYPE, Problem
from schemas.track_jobs import TrackCreate

_REF = "#/components/schemas/{model}"
_RETRY_AFTER = {
    "description": "Seconds to wait before trying again (or before polling the job).",
    "schema": {"type": "integer", "minimum": 0},
}
_GENERIC_ERRORS: dict[str, str] = {
    "500": "Internal error (logged; the body never carries a traceback).",
    "503": "The job store (Redis) is unreachable; retry after `Retry-After` seconds.",
}
_VALIDATION = "A field is invalid; `errors[].loc` names it, `errors[].msg` says why."
_ESTIMATE_BODY_DOC = (
    "`image`: the reference image (PNG, JPEG or TIFF, exactly the camera's size); `request`: "
    "the estimate request as JSON (EstimateCreate), sent as a form field or a file part."
)
_TRACK_BODY_DOC = (
    "`frames`: the sequence's images in order (repeat the part; PNG, JPEG or TIFF, exactly the "
    "camera's size); `request`: the track request as JSON (TrackCreate), sent as a form field "
    "or a file part."
)
_IMAGE_TYPES = "image/png, image/jpeg, image/tiff"
_BINARY = {"type": "string", "format": "binary", "contentMediaType": "application/octet-stream"}


def operation_id(route: APIRoute) -> str:
    """The route function's name: stable across path or method changes of the framework."""
    return route.name


def _schemas(*models: type[Any]) -> dict[str, Any]:
    _, top = models_json_schema([(m, "validation") for m in models], ref_template=_REF)
    return dict(top.get("$defs", {}))


def _multipart_body(
    files: str, file_schema: dict[str, Any], model: str, doc: str
) -> dict[str, Any]:
    """A submission's body: the ``files`` part(s) and the ``request`` part as ``model``."""
    return {
        "required": True,
        "description": doc,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": [files, "request"],
                    "properties": {
                        files: file_schema,
                        "request": {"$ref": _REF.format(model=model)},
                    },
                },
                "encoding": {
                    "request": {"contentType": "application/json"},
                    files: {"contentType": _IMAGE_TYPES},
                },
            }
        },
    }


#: The multipart bodies the document describes itself, by (method, path).
_BODIES = {
    ("post", "/v1/estimates"): _multipart_body(
        "image",
        {**_BINARY, "description": "Reference image: PNG, JPEG or TIFF."},
        "EstimateCreate",
        _ESTIMATE_BODY_DOC,
    ),
    ("post", "/v1/tracks"): _multipart_body(
        "frames",
        {"type": "array", "items": _BINARY, "description": "The frames, in order."},
        "TrackCreate",
        _TRACK_BODY_DOC,
    ),
}


def _problem_content() -> dict[str, Any]:
    return {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": _REF.format(model="Problem")}}}


def _takes_input(operation: dict[str, Any]) -> bool:
    return bool(operation.get("parameters") or operation.get("requestBody"))


def _complete_operation(operation: dict[str, Any], path: str) -> None:
    responses = operation.setdefault("responses", {})
    if _takes_input(operation):
        responses.setdefault("422", {"description": _VALIDATION})
    if path.startswith("/v1/"):
        for status, description in _GENERIC_ERRORS.items():
            responses.setdefault(status, {"description": description})
    for status, response in responses.items():
        if status[0] in "45":
            response["content"] = _problem_content()
            if response.get("description") == "Validation Error":
                response["description"] = _VALIDATION
        if status in ("202", "429", "503"):
            response.setdefault("headers", {})["Retry-After"] = _RETRY_AFTER


def complete(schema: dict[str, Any]) -> dict[str, Any]:
    """Fill in the document FastAPI built (in place; returned for convenience)."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components.update(_schemas(EstimateCreate, TrackCreate, Problem))
    for name in ("HTTPValidationError", "ValidationError"):
        components.pop(name, None)
    for path, operations in schema.get("paths", {}).items():
        for method, operation in operations.items():
            if (method, path) in _BODIES:
                old = operation["requestBody"]["content"]["multipart/form-data"]["schema"]
                components.pop(old["$ref"].rsplit("/", 1)[-1], None)
                operation["requestBody"] = _BODIES[method, path]
            _complete_operation(operation, path)
    return schema


def install(app: FastAPI) -> None:
    """Serve the completed document (built once, on first request)."""
    build: Callable[[], dict[str, Any]] = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = complete(build())
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
