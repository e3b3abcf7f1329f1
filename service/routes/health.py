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
from service.deps import BlobStoreDep, KeysDep, RedisDep
from service.problems import problem
from service.store import Queues
from service.store.blobs import BlobStore, BlobStoreUnavailable

router = APIRouter(tags=["health"])

#: Longest /healthz waits for the worker count, s.
HEALTH_DETAIL_S = 1.0
#: Longest /readyz waits for Redis (and, apart, for the blob store), s: a Redis that hangs is
#: not ready, and the probe says so instead of waiting out the client's timeouts and retries.
READY_WAIT_S = 2.0
#: Retry-After of a readiness probe answered 503, s.
NOT_READY_RETRY_AFTER_S = 5


class Readiness(BaseModel):
    ready: bool = Field(description="The API can serve requests (Redis and the blob store answer).")
    redis: bool = Field(description="Redis answered.")
    blob_store: bool = Field(default=False, description="The blob store answered.")
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
    summary="Readiness: Redis and the blob store answer (workers are reported, not required)",
    responses={503: {"description": "Redis or the blob store does not answer: not ready."}},
)
async def readyz(r: RedisDep, keys: KeysDep, blobs: BlobStoreDep) -> JSONResponse:
    try:
        blob_reason = await asyncio.wait_for(run_in_threadpool(_blob_problem, blobs), READY_WAIT_S)
    except TimeoutError:
        blob_reason = f"blob store did not answer within {READY_WAIT_S:g} s"
    try:
        workers, depths = await asyncio.wait_for(run_in_threadpool(_state, r, keys), READY_WAIT_S)
    except (redis.RedisError, TimeoutError) as exc:
        why = str(exc) or f"no answer within {READY_WAIT_S:g} s"
        reason = "; ".join(filter(None, [f"Redis unreachable: {why}", blob_reason]))
        return _not_ready(reason, Readiness(ready=False, redis=False,
                          blob_store=blob_reason is None, workers=0, reason=reason))  # fmt: skip
    if blob_reason is not None:
        body = Readiness(ready=False, redis=True, blob_store=False, workers=workers,
                         queue_depth=depths, reason=blob_reason)  # fmt: skip
        return _not_ready(blob_reason, body)
    warning = None if workers else "no worker is running: jobs queue until one starts"
    ready = Readiness(
        ready=True, redis=True, blob_store=True, workers=workers, queue_depth=depths, reason=warning
    )
    return JSONResponse(ready.model_dump())


def _blob_problem(blobs: BlobStore) -> str | None:
    try:
        blobs.ping()
    except BlobStoreUnavailable as exc:
        return f"blob store ({exc.store}) unavailable"
    return None


def _not_ready(reason: str, state: Readiness) -> JSONResponse:
    body = problem(503, reason, code="unavailable", instance="/readyz") | state.model_dump()
    headers = {"Retry-After": str(NOT_READY_RETRY_AFTER_S)}
    return JSONResponse(body, status_code=503, headers=headers, media_type=PROBLEM_MEDIA_TYPE)
