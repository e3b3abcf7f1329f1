"""Liveness and readiness probes."""

from __future__ import annotations

import redis
from fastapi import APIRouter
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from service.deps import BlobStoreDep, KeysDep, RedisDep
from service.store import Queues
from service.store.blobs import BlobStoreUnavailable

router = APIRouter(tags=["health"])


class Readiness(BaseModel):
    ready: bool
    redis: bool = Field(description="Redis answered.")
    blob_store: bool = Field(default=False, description="The blob store answered.")
    workers: int = Field(description="Live workers (registered, heartbeat not expired).")
    queue_depth: dict[str, int] = Field(default_factory=dict, description="Jobs waiting.")
    reason: str | None = Field(default=None, description="Why not ready.")


@router.get("/healthz", summary="Liveness: the API process answers")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get(
    "/readyz",
    response_model=Readiness,
    summary="Readiness: Redis and the blob store reachable, at least one worker alive",
    responses={503: {"model": Readiness, "description": "Not ready (the body says why)."}},
)
def readyz(r: RedisDep, keys: KeysDep, blobs: BlobStoreDep) -> JSONResponse:
    blob_reason = None
    try:
        blobs.ping()
    except BlobStoreUnavailable as exc:
        blob_reason = f"blob store ({exc.store}) unavailable"
    try:
        r.ping()
        queues = Queues(r, keys)
        workers, depths = queues.live_workers(), queues.depths()
    except redis.RedisError as exc:
        reason = "; ".join(filter(None, [f"Redis unreachable: {exc}", blob_reason]))
        body = Readiness(
            ready=False, redis=False, blob_store=blob_reason is None, workers=0, reason=reason
        )
        return JSONResponse(body.model_dump(), status_code=503)
    no_worker = None if workers else "no worker is running (start one with `proxpose worker`)"
    why = "; ".join(filter(None, [blob_reason, no_worker])) or None
    body = Readiness(
        ready=why is None,
        redis=True,
        blob_store=blob_reason is None,
        workers=workers,
        queue_depth=depths,
        reason=why,
    )
    return JSONResponse(body.model_dump(), status_code=200 if why is None else 503)
