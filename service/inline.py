"""Estimate submissions stored on the event loop while that is safe and cheap.

A submission's own work is ~1.5 ms of CPU, most of it the job's Redis commands (a Lua
reservation, one MULTI) and a small blob write. Run in the thread pool, as FastAPI runs a sync
route, the submissions of a burst share the GIL with each other and with the event loop: all of
them finish near the end of the burst (50 at once: server p99 45–97 ms on 2 cores). Run on the
loop, each one runs to its end in turn, and the same burst stays under 50 ms (bench/README.md,
"Eighth look").

The loop must not wait on anything slow, so a submission is stored inline only when

- its image is small (``INLINE_MAX_IMAGE_BYTES``: still in memory, hashed and written in
  well under a millisecond) and the blob store is the local file store (the flusher thread does
  its fsyncs; an S3 put is a network call);
- Redis answers at once: the inline client has a short socket timeout (``SOCKET_TIMEOUT_S``)
  and retries a dropped connection once, without sleeping and not after a timeout;
- the last inline submissions did: one that fails on Redis (down, hung) or takes longer than
  ``SLOW_S`` (a remote Redis, a slow disk) sends the next ``PAUSE_S`` seconds of submissions to
  the thread pool, which rides out short outages with its backoff and waits on a hung Redis
  in a thread, not on the loop. The pause is logged once. (The submission that meets a hung
  Redis holds the loop for one timeout, or up to three when it has reserved its place and
  claimed an Idempotency-Key: giving them back times out too.)

The rate limiter's Redis call (service/ratelimit.py) goes through the same client and pause.

Everything else (tracks, renders, models, large images) goes through the thread pool as before.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, TypeVar

import redis
from redis.backoff import NoBackoff
from redis.retry import Retry
from starlette.concurrency import run_in_threadpool

from service.store.blobs import CountingBlobStore
from service.store.blobs.files import FileBlobStore

log = logging.getLogger(__name__)

#: Largest image stored on the loop, bytes (Starlette keeps an upload up to 1 MiB in memory).
INLINE_MAX_IMAGE_BYTES = 1024 * 1024
#: The inline Redis client's socket timeout, s: the longest the loop waits on one Redis call
#: (a healthy local Redis answers a submission's commands in well under a millisecond).
SOCKET_TIMEOUT_S = 1.0
#: An inline submission slower than this (wall time) pauses inline submissions, s.
SLOW_S = 0.05
#: How long inline submissions stay paused after a failure or a slow one, s.
PAUSE_S = 30.0

T = TypeVar("T")


def inline_client(url: str, **options: Any) -> redis.Redis:
    """A Redis client for the loop: short timeouts, one immediate retry of a dropped
    connection (a pooled connection that died with a Redis restart), no sleeping."""
    return redis.Redis.from_url(
        url,
        socket_timeout=SOCKET_TIMEOUT_S,
        socket_connect_timeout=SOCKET_TIMEOUT_S,
        # a timeout is not retried: the loop would wait twice
        retry=Retry(NoBackoff(), 1, supported_errors=(redis.ConnectionError,)),
        **options,
    )


class InlineSubmissions:
    """Decides where a submission's work runs, and runs it there (see the module docstring)."""

    def __init__(
        self,
        r: redis.Redis | None,
        blobs: CountingBlobStore,
        clock: Callable[[], float] = time.monotonic,
        on_pause: Callable[[], None] = lambda: None,
    ) -> None:
        self.r = r  # None: never inline (turned off in the settings)
        self.local_blobs = isinstance(blobs.inner, FileBlobStore)
        self.clock = clock
        self.on_pause = on_pause  # counts the pauses (/metrics)
        self.paused_until = 0.0

    def ready(self) -> bool:
        """Redis work may run on the loop now (a client, and not paused)."""
        return self.r is not None and self.clock() >= self.paused_until

    def usable(self, image_bytes: int) -> bool:
        """A submission of ``image_bytes`` may be stored on the loop now."""
        return self.ready() and self.local_blobs and image_bytes <= INLINE_MAX_IMAGE_BYTES

    def pause(self, why: str) -> None:
        if self.clock() >= self.paused_until:
            log.warning("submissions go through the thread pool for %.0f s: %s", PAUSE_S, why)
            self.on_pause()
        self.paused_until = self.clock() + PAUSE_S

    def guard(self, work: Callable[[redis.Redis], T]) -> T:
        """``work(r)`` with the inline client, here (on the loop); a Redis failure or a slow
        run pauses inline runs (the failure is raised)."""
        assert self.r is not None
        start = self.clock()
        try:
            result = work(self.r)
        except (redis.ConnectionError, redis.TimeoutError) as exc:
            self.pause(f"Redis failed on the loop ({type(exc).__name__}: {exc})")
            raise
        took = self.clock() - start
        if took > SLOW_S:
            self.pause(f"Redis work took {took * 1000:.0f} ms on the loop")
        return result

    async def run(
        self, image_bytes: int, inline: Callable[[redis.Redis], T], pooled: Callable[[], T]
    ) -> T:
        """``inline(r)`` on the loop with the inline client ``r`` when usable, else
        ``pooled()`` in the thread pool."""
        if self.usable(image_bytes):
            return self.guard(inline)
        return await run_in_threadpool(pooled)
