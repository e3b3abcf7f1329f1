"""Riding out a Redis outage: a worker waits for Redis with capped backoff instead of exiting,
and says so once per outage (not one traceback per retry).

Inside a job, progress writes and cancel-flag reads that fail are skipped (the estimate goes on);
the job's last write (its result) waits for Redis; any other Redis error ends the attempt, which
is handed back to the queue once Redis answers (``worker.jobs.estimate``). Between jobs, the
runner restarts RQ's work loop after Redis is back (``worker.jobs.runner``). A job is never
lost: when this worker cannot hand it back, its lease lapses and a reaper requeues it; and
never finished twice: a result is stored only by the attempt that holds the job.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import redis

log = logging.getLogger(__name__)

#: Errors that mean "Redis is not reachable now" (a restart, a network cut, a full restart from
#: the AOF while it loads), as opposed to a bug in a command.
OUTAGE_ERRORS: tuple[type[Exception], ...] = (
    redis.ConnectionError,
    redis.TimeoutError,
    redis.exceptions.BusyLoadingError,
)
#: First pause of the wait for Redis, s; doubled up to OUTAGE_BACKOFF_MAX_S.
OUTAGE_BACKOFF_S = 0.5
OUTAGE_BACKOFF_MAX_S = 10.0


def is_outage(exc: BaseException) -> bool:
    """Whether ``exc`` (or what it was raised from) is Redis being unreachable."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, OUTAGE_ERRORS):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


class OutageNotice:
    """Logs the first failure of an outage and the recovery, and nothing in between."""

    def __init__(self, what: str) -> None:
        self.what = what
        self.since: float | None = None
        self._lock = threading.Lock()

    def failed(self, exc: BaseException) -> None:
        with self._lock:
            if self.since is None:
                self.since = time.monotonic()
                log.warning(
                    "%s: Redis is unreachable (%s); retrying until it is back", self.what, exc
                )

    def ok(self) -> None:
        with self._lock:
            if self.since is not None:
                log.warning(
                    "%s: Redis is back after %.1f s", self.what, time.monotonic() - self.since
                )
                self.since = None


def wait_for_redis(
    r: redis.Redis,
    notice: OutageNotice,
    stop: Callable[[], bool] = lambda: False,
    max_wait_s: float | None = None,
) -> bool:
    """Block until Redis answers a PING (True), ``stop()`` turns true or ``max_wait_s`` passes
    (False), pausing with capped exponential backoff."""
    deadline = None if max_wait_s is None else time.monotonic() + max_wait_s
    pause = OUTAGE_BACKOFF_S
    while not stop():
        try:
            r.ping()
            notice.ok()
            return True
        except OUTAGE_ERRORS as exc:
            notice.failed(exc)
        if deadline is not None and time.monotonic() >= deadline:
            return False
        time.sleep(pause)
        pause = min(OUTAGE_BACKOFF_MAX_S, pause * 2)
    return False


def call_through_outage(
    fn: Callable[[], object],
    r: redis.Redis,
    notice: OutageNotice,
    stop: Callable[[], bool] = lambda: False,
    max_wait_s: float | None = None,
) -> object:
    """``fn()``, retried after waiting for Redis whenever it fails for an outage (up to
    ``max_wait_s`` in all; then the last error is raised)."""
    deadline = None if max_wait_s is None else time.monotonic() + max_wait_s
    while True:
        try:
            result = fn()
            notice.ok()
            return result
        except OUTAGE_ERRORS as exc:
            notice.failed(exc)
            left = None if deadline is None else deadline - time.monotonic()
            if (left is not None and left <= 0) or not wait_for_redis(r, notice, stop, left):
                raise
