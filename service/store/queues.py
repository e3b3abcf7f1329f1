"""The RQ side: the two queues, enqueueing by dotted name, removal, and live workers.

Jobs are enqueued by name ("worker.jobs.estimate.run_estimate_job") so the API never imports the
engine; their arguments are plain strings, serialised as JSON (no pickle in Redis).

An estimate is enqueued inside the same Redis transaction that creates (or requeues) its
record, so a crash between the two cannot leave a queued record that no worker will ever see.
Each enqueueing gets its own RQ id, ``<job id>-<n>``: an attempt that a reaper gave up on can
neither be started twice nor clobber the RQ job of the next attempt.
"""

from __future__ import annotations

import redis
from redis.client import Pipeline
from rq import Queue, Worker
from rq.exceptions import NoSuchJobError
from rq.job import Job
from rq.registry import StartedJobRegistry
from rq.serializers import JSONSerializer

from service.store.keys import Keys

#: The RQ job functions, by dotted name (jobs enqueued under the names before the worker was
#: split into packages, "worker.jobs.run_estimate_job" and "worker.jobs.run_render_job", still
#: resolve: see worker/jobs/__init__.py).
ESTIMATE_JOB = "worker.jobs.estimate.run_estimate_job"
RENDER_JOB = "worker.jobs.render.run_render_job"
TRACK_JOB = "worker.jobs.track.run_track_job"
#: The job function of each kind of stored job (all on the estimate queue).
JOB_FUNCTIONS = {"estimate": ESTIMATE_JOB, "track": TRACK_JOB}
#: How long RQ keeps its own record of a failed job (ours lives in the job hash), s.
RQ_FAILURE_TTL_S = 24 * 3600
#: RQ's own timeout of an estimate is this much longer than the job's: the job stops itself at
#: its timeout before a render (cleanly); RQ's alarm is the backstop for a job that hangs.
RQ_TIMEOUT_GRACE_S = 60


class Queues:
    """The estimate and render queues on one Redis."""

    def __init__(self, r: redis.Redis, keys: Keys) -> None:
        self.r = r
        self.keys = keys
        self.estimates = Queue(keys.estimate_queue, connection=r, serializer=JSONSerializer)
        self.renders = Queue(keys.render_queue, connection=r, serializer=JSONSerializer)

    def all(self) -> list[Queue]:
        """Queues in the order workers take jobs from them: quick renders first."""
        return [self.renders, self.estimates]

    @staticmethod
    def estimate_rq_id(job_id: str, n: int) -> str:
        """RQ id of the ``n``-th enqueueing (1-based) of estimate ``job_id``."""
        return f"{job_id}-{n}"

    @staticmethod
    def next_estimate_rq_id(job_id: str, current: str | None) -> str:
        """RQ id of the enqueueing after the one with RQ id ``current``."""
        n = int(current.rsplit("-", 1)[1]) if current and "-" in current else 0
        return Queues.estimate_rq_id(job_id, n + 1)

    def estimates_known(self) -> set[str]:
        """RQ ids of the estimates RQ has: waiting in the queue or started by a worker."""
        pipe = self.r.pipeline(transaction=False)
        pipe.lrange(self.estimates.key, 0, -1)
        pipe.zrange(StartedJobRegistry(queue=self.estimates).key, 0, -1)
        waiting, started = pipe.execute()
        return {w.decode() for w in waiting} | {s.decode().split(":", 1)[0] for s in started}

    def enqueue_estimate(
        self,
        pipe: Pipeline,
        job_id: str,
        rq_id: str,
        timeout_s: int,
        at_front: bool = False,
        kind: str | None = "estimate",
    ) -> None:
        """Queue stored job ``job_id`` (an estimate, or a job of another ``kind`` of
        JOB_FUNCTIONS) as RQ job ``rq_id`` in ``pipe`` (a MULTI transaction; its commands run
        when the caller executes it)."""
        kind = kind or "estimate"  # a record older than the kinds is an estimate
        job = self.estimates.create_job(
            JOB_FUNCTIONS[kind],
            args=(job_id,),
            job_id=rq_id,
            timeout=timeout_s + RQ_TIMEOUT_GRACE_S,
            result_ttl=0,
            failure_ttl=RQ_FAILURE_TTL_S,
            description=f"{kind} {job_id}",
        )
        self.estimates.enqueue_job(job, pipeline=pipe, at_front=at_front)

    def forget_estimate(self, pipe: Pipeline, rq_id: str) -> None:
        """Drop the RQ records of an abandoned execution (``pipe`` in MULTI): the job hash and
        its entries in the started registry, which RQ would otherwise fail ~timeout later."""
        registry = StartedJobRegistry(queue=self.estimates)
        members: list[bytes] = self.r.zrange(registry.key, 0, -1)  # type: ignore[assignment]
        entries = [e for e in members if e.split(b":", 1)[0] == rq_id.encode()]
        if entries:
            pipe.zrem(registry.key, *entries)
        pipe.delete(Job.key_for(rq_id))

    def enqueue_render(
        self, render_id: str, model_id: str, request_json: str, timeout_s: int
    ) -> None:
        self.renders.enqueue(
            RENDER_JOB,
            render_id,
            model_id,
            request_json,
            job_id=render_id,
            job_timeout=timeout_s,
            ttl=timeout_s,  # not started by then: the caller has given up, so drop it
            result_ttl=0,
            failure_ttl=RQ_FAILURE_TTL_S,
            description=f"render {render_id}",
        )

    def remove(self, queue: Queue, job_id: str) -> bool:
        """Take a job out of ``queue`` if no worker has picked it up; True if removed."""
        if not queue.remove(job_id):
            return False
        try:
            Job.fetch(job_id, connection=self.r, serializer=JSONSerializer).delete()
        except NoSuchJobError:
            pass
        return True

    def depths(self) -> dict[str, int]:
        """Jobs waiting, by queue ('estimates', 'renders')."""
        return {"estimates": self.estimates.count, "renders": self.renders.count}

    def live_workers(self) -> int:
        """Workers registered on the estimate queue whose heartbeat key has not expired."""
        return len(Worker.all(queue=self.estimates))
