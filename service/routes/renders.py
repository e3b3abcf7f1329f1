"""``/v1/renders``: one render of a model at a pose, done by a worker while the client waits."""

from __future__ import annotations

import json
import math
import uuid

from fastapi import APIRouter, Response

from schemas.jobs import RenderCreate
from schemas.names import BUILTIN_MODEL_IDS, JobErrorCode
from service.deps import KeysDep, ModelStoreDep, QueuesDep, RedisDep, SettingsDep
from service.errors import ApiError, field_error

router = APIRouter(prefix="/v1/renders", tags=["renders"])

#: Retry-After of a render refused because no worker runs, s.
NO_WORKER_RETRY_AFTER_S = 10

#: Engine error codes that are the request's fault, with the field they concern.
_CLIENT_ERRORS: dict[JobErrorCode, tuple[str, ...]] = {
    "empty_render": ("body", "pose"),
    "invalid_pose": ("body", "pose"),
    "invalid_model": ("body", "model_id"),
    "model_too_large": ("body", "model_id"),
    "model_not_found": ("body", "model_id"),
    "invalid_input": ("body",),
}


@router.post(
    "",
    response_class=Response,
    summary="Render a model at a pose (PNG)",
    description="The render runs on a worker (renders go before queued estimates); the call "
    "waits for it up to render_timeout_s.",
    responses={
        200: {"content": {"image/png": {}}, "description": "The 8-bit sRGB render."},
        422: {"description": "A field is invalid, or the model is not visible at the pose."},
        429: {"description": "The key submits too fast; see `Retry-After`."},
        503: {"description": "No worker is running."},
        504: {"description": "No worker finished the render in time."},
    },
)
def create_render(
    body: RenderCreate,
    models: ModelStoreDep,
    queues: QueuesDep,
    r: RedisDep,
    keys: KeysDep,
    settings: SettingsDep,
) -> Response:
    if body.model_id not in BUILTIN_MODEL_IDS and not models.exists(body.model_id):
        msg = f"no model '{body.model_id}' is registered (see GET /v1/models)"
        raise field_error(422, ("body", "model_id"), msg, "model_not_found")
    if queues.live_workers() == 0:
        raise ApiError(
            503,
            detail="no worker is running; start one with `proxpose worker`",
            code="no_worker",
            headers={"Retry-After": str(NO_WORKER_RETRY_AFTER_S)},
        )
    render_id = uuid.uuid4().hex
    request_json = body.engine_request().model_dump_json(exclude_unset=True)
    timeout_s = settings.render_timeout_s
    queues.enqueue_render(render_id, body.model_id, request_json, math.ceil(timeout_s))
    popped = r.blpop([keys.render_done(render_id)], timeout=timeout_s)
    if popped is None:
        queues.remove(queues.renders, render_id)
        depth = queues.depths()["renders"]
        raise ApiError(
            504,
            detail=f"no worker finished the render within {timeout_s:g} s "
            f"({depth} renders still queued); try again or add workers",
            code="timeout",
        )
    outcome = json.loads(popped[1])
    if outcome["status"] != "succeeded":
        error = outcome["error"]
        if error["code"] in _CLIENT_ERRORS:
            raise field_error(422, _CLIENT_ERRORS[error["code"]], error["message"], error["code"])
        raise ApiError(
            500, detail=f"render failed: {error['message']} [{error['code']}]", code=error["code"]
        )
    pipe = r.pipeline()
    pipe.get(keys.render_png(render_id))
    pipe.delete(keys.render_png(render_id))
    png, _ = pipe.execute()
    if png is None:
        raise ApiError(500, detail="the render's image expired before it could be sent")
    return Response(png, media_type="image/png")
