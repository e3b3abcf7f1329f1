"""The FastAPI application: wiring only (routers, middleware, error handlers, Redis clients,
the blob store).

Run with ``uvicorn service.main:app`` or ``proxpose serve``. Settings are read when the app
starts (lifespan), not at import, so tests set the environment and clear the settings cache.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, MutableMapping
from contextlib import asynccontextmanager
from typing import Any

import redis
import redis.asyncio
from fastapi import FastAPI
from redis.asyncio.retry import Retry as AsyncRetry
from redis.backoff import ExponentialBackoff
from redis.driver_info import DriverInfo
from redis.retry import Retry

from schemas.settings import Settings, get_settings
from schemas.version import __version__
from service.auth import AuthMiddleware, document_bearer_auth
from service.errors import install_error_handlers
from service.headers import ConfiguredCORSMiddleware, SecurityHeadersMiddleware
from service.inline import InlineSubmissions, inline_client
from service.limits import BodySizeLimitMiddleware
from service.logs import adopt_uvicorn_loggers, configure_logging
from service.metrics import Metrics, MetricsMiddleware
from service.openapi import install as install_openapi
from service.openapi import operation_id
from service.ratelimit import SubmissionRateLimitMiddleware
from service.resources import TRACKS_PATH
from service.routes import (
    docs,
    estimates,
    health,
    metrics,
    models,
    pages,
    renders,
    session,
    tracks,
)
from service.store import Keys, Queues
from service.store.blobs import open_blob_store
from service.store.budget import warn_if_unbounded
from service.uploads import load_image_codecs

log = logging.getLogger(__name__)

#: Seconds to wait for a connection to Redis.
REDIS_CONNECT_TIMEOUT_S = 5.0
#: The longest the sync client waits for one command's answer, s.
REDIS_COMMAND_TIMEOUT_S = 5.0
#: A pooled Redis connection idle this long is checked (PING) before it is used, s.
REDIS_HEALTH_CHECK_S = 2
#: Retries of a Redis command on a dropped connection, and the longest pause between two, s.
REDIS_RETRIES = 3
REDIS_RETRY_CAP_S = 0.5
#: Connections each Redis client of the API opens as it starts. A burst of submissions then
#: finds them open instead of opening one per request in flight (a TCP connection and two
#: CLIENT SETINFO round trips each, while the burst waits); ~30 were opened by the first burst
#: of 50 submissions.
WARM_CONNECTIONS = 32
#: The name of the API's Redis connections (CLIENT LIST).
API_CLIENT_NAME = "proxpose-api"
#: Allowance for the multipart framing and the request JSON beside the largest file, bytes.
BODY_OVERHEAD_BYTES = 1024 * 1024

DESCRIPTION = """\
Estimates the 6-DoF pose of a known target (spacecraft, asteroid) from one camera image by
rendering its 3D model and aligning the render to the image.

Register a model (`/v1/models`; the demo satellite is `demo-sat`), submit an image with a
request (`POST /v1/estimates`), then poll the job, stream its progress (`/events`), and fetch
the result and the PNG artifacts. Jobs run on workers that share only Redis with the API.
"""


def request_body_limit(settings: Settings, path: str = "") -> int:
    """Largest request body accepted at ``path``: its largest upload plus framing (a track's
    frames at /v1/tracks; elsewhere an image or a model)."""
    if path == TRACKS_PATH:
        return settings.max_track_bytes + BODY_OVERHEAD_BYTES
    return max(settings.max_image_bytes, settings.max_model_bytes) + BODY_OVERHEAD_BYTES


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings = get_settings()
    configure_logging(settings.log_format, quiet=("rq",))
    adopt_uvicorn_loggers()
    url = settings.effective_redis_url()
    # A hung Redis must not hang requests for long (see each client's socket timeout).
    # After a Redis restart the pooled connections are dead: a connection idle for
    # REDIS_HEALTH_CHECK_S is pinged (and remade) before use, and a command that meets a dropped
    # connection is retried, so the first requests after an outage succeed instead of a 503.
    reconnect: dict[str, Any] = {
        "socket_connect_timeout": REDIS_CONNECT_TIMEOUT_S,
        "health_check_interval": REDIS_HEALTH_CHECK_S,
        "retry_on_error": [redis.ConnectionError, redis.TimeoutError],
        # redis-py looks its own version up in the installed packages' metadata for every new
        # connection (~0.3 ms of CPU each) unless it is given
        "driver_info": DriverInfo(lib_version=redis.__version__),
        "client_name": API_CLIENT_NAME,  # how CLIENT LIST names the API's connections
    }
    # the sync client makes no blocking call (the render wait is the async client's): a
    # command that takes longer than REDIS_COMMAND_TIMEOUT_S is a Redis that hangs, and is not
    # sent again (a dropped connection is)
    dropped = (redis.ConnectionError,)
    app.state.redis = redis.Redis.from_url(
        url,
        socket_timeout=REDIS_COMMAND_TIMEOUT_S,
        retry=Retry(
            ExponentialBackoff(cap=REDIS_RETRY_CAP_S), REDIS_RETRIES, supported_errors=dropped
        ),
        **(reconnect | {"retry_on_error": list(dropped)}),
    )
    # the render wait (an async BLPOP) is the async client's longest call too
    app.state.aredis = redis.asyncio.Redis.from_url(
        url,
        socket_timeout=settings.render_timeout_s + REDIS_CONNECT_TIMEOUT_S,
        retry=AsyncRetry(ExponentialBackoff(cap=REDIS_RETRY_CAP_S), REDIS_RETRIES),
        **reconnect,
    )
    app.state.blobs = open_blob_store(settings)
    # small estimate submissions are stored on the event loop through a client with short
    # timeouts, while Redis answers quickly (service/inline.py)
    fast = None
    if settings.inline_submissions:
        fast = inline_client(
            url,
            health_check_interval=REDIS_HEALTH_CHECK_S,
            driver_info=reconnect["driver_info"],
            client_name=API_CLIENT_NAME,
        )
    paused = app.state.metrics.inline_paused.inc
    app.state.inline = InlineSubmissions(fast, app.state.blobs, on_pause=paused)
    keys = Keys(settings.redis_prefix)
    app.state.store_source = (app.state.redis, keys)
    app.state.queues = Queues(app.state.redis, keys)  # shared by the requests' job stores
    warn_if_unbounded(app.state.redis, "API")
    warm = await warm_pools(app.state.redis, app.state.aredis, WARM_CONNECTIONS)
    if fast is not None and warm:
        # the loop runs inline submissions in turn: one connection is all they use
        fast.connection_pool.release(fast.connection_pool.get_connection())
    load_image_codecs()
    await warm_routes(app)
    try:
        yield
    finally:
        app.state.store_source = app.state.queues = None
        app.state.redis.close()
        if fast is not None:
            fast.close()
        await app.state.aredis.aclose()


async def warm_pools(r: redis.Redis, ar: redis.asyncio.Redis, n: int) -> bool:
    """Open ``n`` connections in each client's pool and put them back (True); when Redis does
    not answer, the ones opened so far (the first requests then open theirs, as after an
    outage) and False."""
    held, aheld = [], []
    try:
        for _ in range(n):
            held.append(r.connection_pool.get_connection())
        for _ in range(n):
            aheld.append(await ar.connection_pool.get_connection())
    except (redis.RedisError, OSError) as exc:
        log.warning("Redis connections not opened in advance: %s", exc)
        return False
    finally:
        for connection in held:
            r.connection_pool.release(connection)
        for aconnection in aheld:
            await ar.connection_pool.release(aconnection)
    return True


async def warm_routes(app: FastAPI) -> None:
    """Route one request that matches nothing, straight to the router (no middleware, no
    metrics): FastAPI builds each router's routes (their dependencies, body fields and
    validators; ~23 ms in all) when a request first looks through them. Done as the API
    starts, the first burst of requests does not wait behind it on the event loop."""
    scope: dict[str, Any] = {
        "type": "http",
        "http_version": "1.1",
        "method": "GET",
        "scheme": "http",
        "path": "/.warm-up",
        "raw_path": b"/.warm-up",
        "root_path": "",
        "query_string": b"",
        "headers": [],
        "server": None,
        "client": None,
    }  # no "app": an unmatched path is then answered 404 by the router itself

    async def receive() -> dict[str, Any]:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: MutableMapping[str, Any]) -> None:
        pass

    await app.router(scope, receive, send)


def create_app() -> FastAPI:
    app = FastAPI(
        title="proxpose",
        version=__version__,
        summary="Pose of a known target from one image, as a service",
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # /docs is service.routes.docs: Swagger UI from local files
        redoc_url=None,
        generate_unique_id_function=operation_id,
    )
    app.state.metrics = Metrics()
    app.state.metrics.watch_store(
        lambda: getattr(app.state, "store_source", None), lambda: getattr(app.state, "blobs", None)
    )
    # innermost first: the rate limit needs the principal; authentication and the size limit
    # answer before the body is read; CORS answers preflights before authentication
    app.add_middleware(SubmissionRateLimitMiddleware, settings=get_settings)
    app.add_middleware(AuthMiddleware, settings=get_settings)
    app.add_middleware(
        BodySizeLimitMiddleware, max_bytes=lambda path: request_body_limit(get_settings(), path)
    )
    app.add_middleware(ConfiguredCORSMiddleware, settings=get_settings)
    app.add_middleware(SecurityHeadersMiddleware)
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)  # outermost: counts 4xx
    install_error_handlers(app)
    document_bearer_auth(app)
    install_openapi(app)  # after: its document, with the security schemes, is completed
    for module in (health, metrics, models, estimates, tracks, renders, session):
        app.include_router(module.router)
    app.include_router(pages.router)  # the browser pages
    app.include_router(docs.router)  # /docs, offline
    app.mount("/static", pages.static_files(), name="static")  # public: scripts, styles
    return app


app = create_app()
