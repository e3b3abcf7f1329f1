"""``/v1/renders``: one render of a model at a pose, done by a worker while the client waits."""

from __future__ import annotations

import json
import math
import uuid

from fastapi import APIRouter, Response
from starlette.concurrency import run_in_threadpool

from schemas.jobs import RenderCreate
from schemas.names import BUILTIN_MODEL_IDS, JobErrorCode
from service.deps import AsyncRedisDep, KeysDep, ModelStoreDep, QueuesDep, SettingsDep
from service.errors import ApiError, field_error
from service.store import ModelStore, Queues

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
async def create_render(
    body: RenderCreate,
    models: ModelStoreDep,
    queues: QueuesDep,
    aredis: AsyncRedisDep,
    keys: KeysDep,
    settings: SettingsDep,
) -> Response:
    # The wait for the worker is awaited on the event loop (an async BLPOP), so renders in
    # flight hold no thread of the pool; the short synchronous store calls before and after it
    # run in the pool, one round trip or two each.
    render_id = uuid.uuid4().hex
    request_json = body.engine_request().model_dump_json(exclude_unset=True)
    timeout_s = settings.render_timeout_s
    await run_in_threadpool(
        _check_and_enqueue, body.model_id, models, queues, render_id, request_json, timeout_s
    )
    popped = await aredis.blpop([keys.render_done(render_id)], timeout=timeout_s)
    if popped is None:
        depth = await run_in_threadpool(_withdraw, queues, render_id)
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
    async with aredis.pipeline() as pipe:
        pipe.get(keys.render_png(render_id))
        pipe.delete(keys.render_png(render_id))
        png, _ = await pipe.execute()
    if png is None:
        raise ApiError(500, detail="the render's image expired before it could be sent")
    return Response(png, media_type="image/png")


def _check_and_enqueue(
    model_id: str,
    models: ModelStore,
    queues: Queues,
    render_id: str,
    request_json: str,
    timeout_s: float,
) -> None:
    """422 for an unknown model, 503 without a live worker, else the render is queued."""
    if model_id not in BUILTIN_MODEL_IDS and not models.exists(model_id):
        msg = f"no model '{model_id}' is registered (see GET /v1/models)"
        raise field_error(422, ("body", "model_id"), msg, "model_not_found")
    if queues.live_workers() == 0:
        raise ApiError(
            503,
            detail="no worker is running; start one with `proxpose worker`",
            code="no_worker",
            headers={"Retry-After": str(NO_WORKER_RETRY_AFTER_S)},
        )
    queues.enqueue_render(render_id, model_id, request_json, math.ceil(timeout_s))


def _withdraw(queues: Queues, render_id: str) -> int:
    """Take the timed-out render off its queue; the renders still queued."""
    queues.remove(queues.renders, render_id)
    return queues.depths()["renders"]
