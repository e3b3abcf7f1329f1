"""Liveness and readiness probes."""

from __future__ import annotations

import redis
from fastapi import APIRouter
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from service.deps import KeysDep, RedisDep
from service.store import Queues

router = APIRouter(tags=["health"])


class Readiness(BaseModel):
    ready: bool
    redis: bool = Field(description="Redis answered.")
    workers: int = Field(description="Live workers (registered, heartbeat not expired).")
    queue_depth: dict[str, int] = Field(default_factory=dict, description="Jobs waiting.")
    reason: str | None = Field(default=None, description="Why not ready.")


@router.get("/healthz", summary="Liveness: the API process answers")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get(
    "/readyz",
    response_model=Readiness,
    summary="Readiness: Redis reachable and at least one worker alive",
    responses={503: {"model": Readiness, "description": "Not ready (the body says why)."}},
)
def readyz(r: RedisDep, keys: KeysDep) -> JSONResponse:
    try:
        r.ping()
        queues = Queues(r, keys)
        workers, depths = queues.live_workers(), queues.depths()
    except redis.RedisError as exc:
        body = Readiness(ready=False, redis=False, workers=0, reason=f"Redis unreachable: {exc}")
        return JSONResponse(body.model_dump(), status_code=503)
    reason = None if workers else "no worker is running (start one with `proxpose worker`)"
    body = Readiness(
        ready=workers > 0, redis=True, workers=workers, queue_depth=depths, reason=reason
    )
    return JSONResponse(body.model_dump(), status_code=200 if workers else 503)
