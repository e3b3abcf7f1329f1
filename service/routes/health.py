"""Liveness and readiness probes.

``/readyz`` means "this API can accept and serve requests": Redis answers. Workers are not part
of it (an orchestrator must not pull the API while workers restart: jobs queue up meanwhile);
their count and the queue depths are in the body, in ``/healthz`` and in ``/metrics``.
"""

from __future__ import annotations

import asyncio

import redis
from fastapi import APIRouter
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from schemas.problem import PROBLEM_MEDIA_TYPE
from service.deps import KeysDep, RedisDep
from service.problems import problem
from service.store import Queues

router = APIRouter(tags=["health"])

#: Longest /healthz waits for the worker count, s.
HEALTH_DETAIL_S = 1.0
#: Retry-After of a readiness probe answered 503, s.
NOT_READY_RETRY_AFTER_S = 5


class Readiness(BaseModel):
    ready: bool = Field(description="The API can serve requests (Redis answers).")
    redis: bool = Field(description="Redis answered.")
    workers: int = Field(description="Live workers (registered, heartbeat not expired).")
    queue_depth: dict[str, int] = Field(default_factory=dict, description="Jobs waiting.")
    reason: str | None = Field(default=None, description="Why not ready, or a warning.")


class Liveness(BaseModel):
    status: str = Field(description="'ok': the API process answers.", examples=["ok"])
    workers: int | None = Field(
        default=None, description="Live workers, when Redis answered (null otherwise)."
    )


def _state(r: redis.Redis, keys: KeysDep) -> tuple[int, dict[str, int]]:
    r.ping()
    queues = Queues(r, keys)
    return queues.live_workers(), queues.depths()


@router.get(
    "/healthz",
    response_model=Liveness,
    summary="Liveness: the API process answers (with the live worker count when known)",
)
async def healthz(r: RedisDep, keys: KeysDep) -> Liveness:
    # a liveness probe must answer even when Redis hangs: the worker count is a bounded extra
    try:
        workers, _ = await asyncio.wait_for(run_in_threadpool(_state, r, keys), HEALTH_DETAIL_S)
    except (redis.RedisError, TimeoutError):
        return Liveness(status="ok")
    return Liveness(status="ok", workers=workers)


@router.get(
    "/readyz",
    response_model=Readiness,
    summary="Readiness: Redis answers (workers are reported, not required)",
    responses={503: {"description": "Redis does not answer: not ready."}},
)
async def readyz(r: RedisDep, keys: KeysDep) -> JSONResponse:
    try:
        workers, depths = await run_in_threadpool(_state, r, keys)
    except redis.RedisError as exc:
        body = problem(
            503,
            f"Redis unreachable: {exc}",
            code="unavailable",
            instance="/readyz",
        )
        body |= Readiness(ready=False, redis=False, workers=0).model_dump()
        headers = {"Retry-After": str(NOT_READY_RETRY_AFTER_S)}
        return JSONResponse(body, status_code=503, headers=headers, media_type=PROBLEM_MEDIA_TYPE)
    reason = None if workers else "no worker is running: jobs queue until one starts"
    ready = Readiness(ready=True, redis=True, workers=workers, queue_depth=depths, reason=reason)
    return JSONResponse(ready.model_dump())
