"""Dependencies of the routes, as ``Annotated`` aliases.

The Redis clients and the blob store live on ``app.state`` (made in the lifespan from the
settings of that moment); stores are cheap views over them, built per request for the caller
(``PrincipalDep``): a job or model store sees only the caller's records unless the caller is an
admin.

Every dependency is ``async def`` although none awaits: FastAPI runs a sync dependency in the
thread pool, and those hand-offs (several per request) cost more than the work itself. FastAPI
also solves every node of a route's dependency graph on every request (~20 µs each): a hot route
that needs most of them takes ``CallerDep``, one node, instead of a dozen.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import redis
import redis.asyncio
from fastapi import Depends, Request

from schemas.settings import Settings, get_settings
from service.auth import PrincipalDep, get_principal
from service.errors import ApiError
from service.store import JobStore, Keys, ModelStore, Principal, Queues
from service.store.blobs import BlobStore


async def current_settings() -> Settings:
    return get_settings()


SettingsDep = Annotated[Settings, Depends(current_settings)]


async def get_redis(request: Request) -> redis.Redis:
    return request.app.state.redis  # type: ignore[no-any-return]


async def get_async_redis(request: Request) -> redis.asyncio.Redis:
    return request.app.state.aredis  # type: ignore[no-any-return]


RedisDep = Annotated[redis.Redis, Depends(get_redis)]
AsyncRedisDep = Annotated[redis.asyncio.Redis, Depends(get_async_redis)]


async def get_blob_store(request: Request) -> BlobStore:
    return request.app.state.blobs  # type: ignore[no-any-return]


BlobStoreDep = Annotated[BlobStore, Depends(get_blob_store)]


async def get_keys(settings: SettingsDep) -> Keys:
    return Keys(settings.redis_prefix)


KeysDep = Annotated[Keys, Depends(get_keys)]


def _queues(request: Request, r: redis.Redis, keys: Keys) -> Queues:
    """The app's Queues (made in the lifespan: two RQ queue objects, ~15 µs to make) when they
    are on ``r`` under ``keys``, else new ones."""
    shared: Queues | None = getattr(request.app.state, "queues", None)
    if shared is not None and shared.r is r and shared.keys == keys:
        return shared
    return Queues(r, keys)


def _job_store(
    request: Request, r: redis.Redis, keys: Keys, settings: Settings, principal: Principal
) -> JobStore:
    return JobStore(
        r,
        keys,
        settings.retention_s,
        viewer=principal,
        queues=_queues(request, r, keys),
        blobs=request.app.state.blobs,
    )


async def get_job_store(
    request: Request,
    r: RedisDep,
    keys: KeysDep,
    settings: SettingsDep,
    principal: PrincipalDep,
) -> JobStore:
    return _job_store(request, r, keys, settings, principal)


async def get_model_store(
    r: RedisDep, keys: KeysDep, principal: PrincipalDep, blobs: BlobStoreDep
) -> ModelStore:
    return ModelStore(r, keys, viewer=principal, blobs=blobs)


async def get_queues(r: RedisDep, keys: KeysDep) -> Queues:
    return Queues(r, keys)


JobStoreDep = Annotated[JobStore, Depends(get_job_store)]
ModelStoreDep = Annotated[ModelStore, Depends(get_model_store)]
QueuesDep = Annotated[Queues, Depends(get_queues)]


@dataclass(frozen=True)
class Caller:
    """What a submission needs, as one dependency: the settings, the caller, and the caller's
    job and model stores (the same objects as SettingsDep, PrincipalDep, JobStoreDep and
    ModelStoreDep give)."""

    settings: Settings
    principal: Principal
    jobs: JobStore
    models: ModelStore


async def get_caller(request: Request) -> Caller:
    principal = await get_principal(request)  # 401 without one, as PrincipalDep
    return _caller(request, get_settings(), principal, request.app.state.redis)


def _caller(request: Request, settings: Settings, principal: Principal, r: redis.Redis) -> Caller:
    """The caller with its job and model stores on the Redis client ``r``."""
    keys = Keys(settings.redis_prefix)
    return Caller(
        settings=settings,
        principal=principal,
        jobs=_job_store(request, r, keys, settings, principal),
        models=ModelStore(r, keys, viewer=principal, blobs=request.app.state.blobs),
    )


CallerDep = Annotated[Caller, Depends(get_caller)]


def caller_on(request: Request, caller: Caller, r: redis.Redis) -> Caller:
    """``caller`` with its job and model stores on the Redis client ``r``."""
    return _caller(request, caller.settings, caller.principal, r)


FORM_TYPES = ("multipart/form-data", "application/x-www-form-urlencoded")


async def require_multipart(request: Request) -> None:
    """415 unless the body is a form: multipart/form-data, or a urlencoded form (which cannot
    carry the files, so validation then names the missing file field with a 422)."""
    content_type = request.headers.get("content-type", "").lower()
    if not content_type.startswith(FORM_TYPES):
        got = content_type.split(";")[0].strip() or "none"
        raise ApiError(
            415,
            f"the body must be multipart/form-data (got {got}); see the curl examples",
            code="unsupported_media_type",
        )


Multipart = Depends(require_multipart)
