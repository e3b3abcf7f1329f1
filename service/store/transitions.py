"""Check-and-set changes of a job's Redis hash: the one way a job's status changes.

A transition WATCHes the job's hash (and any other key its decision reads), reads GUARD_FIELDS,
asks a guard whether the change applies to the job as it is, and then sets the new fields in a
MULTI transaction together with whatever else belongs to the same change (queue entries, index
sets, the lease); a concurrent write to a watched key makes it start over. So the API cancelling
a queued job, a worker starting it and a reaper recovering it cannot both win. Used by the
job store (creation aside, every ending) and by the leases and reapers
(``service.store.leases``: starting, recovering, re-enqueueing).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import redis
from redis.client import Pipeline

from service.store.keys import Keys
from service.store.records import text

#: Fields read (under WATCH) to decide a transition.
GUARD_FIELDS = (
    "status",
    "attempts",
    "owner",
    "rq_id",
    "cancel_requested",
    "timeout_s",
    "worker",
    "lost",
    "kind",
)

#: The job's fields before a transition (None where absent).
Current = dict[str, str | None]
#: Whether the transition applies to the job as it is (may read more keys through the pipe,
#: which is still in WATCH mode then).
Guard = Callable[[Current, Pipeline], bool]
#: The fields to set: a dict, or a function of the current fields.
Fields = Mapping[str, str | bytes] | Callable[[Current], Mapping[str, str | bytes]]
#: More commands of the same transaction (the pipe is in MULTI mode then).
Extra = Callable[[Pipeline, Current], None]


class Transitions:
    """Atomic changes of the jobs in one Redis (``r`` returns bytes)."""

    def __init__(self, r: redis.Redis, keys: Keys, retention_s: int) -> None:
        self.r = r
        self.keys = keys
        self.retention_s = retention_s

    def apply(
        self,
        job_id: str,
        guard: Guard,
        fields: Fields,
        extra: Extra | None = None,
        *,
        watch: Sequence[str] = (),
        expire: bool = False,
    ) -> Current | None:
        """Atomically: if ``guard`` accepts the job's current fields, set ``fields`` and run
        ``extra`` in the same transaction (with ``expire``, the hash then expires after the
        retention). Returns the fields before, or None if the guard refused (or the job is
        gone)."""
        key = self.keys.job(job_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key, *watch)
                    values = pipe.hmget(key, GUARD_FIELDS)
                    current = {f: text(v) for f, v in zip(GUARD_FIELDS, values, strict=True)}  # type: ignore[arg-type]
                    if current["status"] is None or not guard(current, pipe):
                        pipe.unwatch()
                        return None
                    new = fields(current) if callable(fields) else fields
                    pipe.multi()
                    pipe.hset(key, mapping=new)  # type: ignore[arg-type]
                    if expire:
                        pipe.expire(key, self.retention_s)
                    if extra is not None:
                        extra(pipe, current)
                    pipe.execute()
                    return current
                except redis.WatchError:
                    continue

    def release(self, pipe: Pipeline, job_id: str, current: Current) -> None:
        """The clean-up of a job that ends (``pipe`` in MULTI): its image, flags and lease go,
        and it stops counting as running and against its owner's cap."""
        pipe.delete(
            self.keys.job_image(job_id), self.keys.job_cancel(job_id), self.keys.job_lease(job_id)
        )
        pipe.srem(self.keys.jobs_running, job_id)
        pipe.srem(self.keys.jobs_queued, job_id)
        pipe.srem(self.keys.owner_active(current["owner"] or "anonymous"), job_id)
