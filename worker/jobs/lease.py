"""The running job's side of crash safety: renewing its lease, and the flag the engine polls.

:class:`LeaseKeeper` renews the lease from a thread (see ``service.store.leases``), so that a
worker that dies is noticed; :class:`CancelFlag` is the engine's ``should_cancel``, read before
every render.
"""

from __future__ import annotations

import logging
import threading
import time
from types import TracebackType

import redis

from service.store import Leases
from worker.jobs.outage import OUTAGE_ERRORS, OutageNotice

log = logging.getLogger(__name__)

#: Least time between two Redis reads of a job's cancel flag, s.
CANCEL_POLL_S = 0.2
#: Set by the worker process on a cold shutdown while a job runs (see worker.jobs.runner): the
#: job stops before its next render and goes back to the queue, instead of being interrupted by
#: an exception in the middle of whatever it was doing.
STOP_NOW = threading.Event()


class LeaseKeeper:
    """Renews the running job's lease from a thread (see ``service.store.leases``), so that a
    worker that dies is noticed; sets ``lost`` when the job has been taken from this attempt."""

    def __init__(self, leases: Leases, job_id: str, attempt: int) -> None:
        self.leases, self.job_id, self.attempt = leases, job_id, attempt
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"lease-{job_id}", daemon=True)

    def _run(self) -> None:
        notice = OutageNotice(f"job {self.job_id}: lease of attempt {self.attempt}")
        while not self._stop.wait(self.leases.renew_interval_s):
            try:
                if not self.leases.renew(self.job_id, self.attempt):
                    log.warning("job %s: attempt %d no longer holds the job", *self._ids())
                    self.lost.set()
                    return
                notice.ok()
            except OUTAGE_ERRORS as exc:
                notice.failed(exc)
            except redis.RedisError as exc:
                log.warning(
                    "job %s: could not renew the lease of attempt %d: %s", *self._ids(), exc
                )

    def _ids(self) -> tuple[str, int]:
        return self.job_id, self.attempt

    def __enter__(self) -> LeaseKeeper:
        self._thread.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


class CancelFlag:
    """``should_cancel`` for the engine, read before every render: true once a client asked the
    job to stop, this attempt no longer holds the job, the job's time is up, or the worker is
    stopping cold. ``reason`` says which; Redis is read at most every CANCEL_POLL_S."""

    def __init__(self, leases: Leases, keeper: LeaseKeeper, timeout_s: float) -> None:
        self.leases, self.keeper = leases, keeper
        self.deadline = time.monotonic() + timeout_s
        self.reason: str | None = None
        self._last_poll = float("-inf")

    def __call__(self) -> bool:
        if self.reason is None:
            self.reason = self._check()
        return self.reason is not None

    def _check(self) -> str | None:
        if STOP_NOW.is_set():
            return "stopped"
        if self.keeper.lost.is_set():
            return "superseded"
        now = time.monotonic()
        if now > self.deadline:
            return "timeout"
        if now - self._last_poll < CANCEL_POLL_S:
            return None
        self._last_poll = now
        try:
            owned, cancel = self.leases.check(self.keeper.job_id, self.keeper.attempt)
        except OUTAGE_ERRORS:  # Redis away: go on (the lease keeper reports the outage)
            return None
        if not owned:
            self.keeper.lost.set()
            return "superseded"
        return "cancelled" if cancel else None
