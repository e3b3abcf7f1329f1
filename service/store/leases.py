"""Crash safety: a running job holds a lease its worker renews; reapers recover lapsed ones.

A worker that starts a job takes the lease ``job:<id>:lease`` (value: the attempt number, TTL
``lease_s``) and renews it from a thread every ``lease_s / LEASE_RENEWALS`` seconds. If the worker
is killed, crashes (segfault, out of memory) or hangs without the GIL, the lease lapses. Every
worker sweeps the running jobs every few seconds (and the API checks the job it is asked about);
a running job without a lease is

* cancelled, if a client had asked it to stop;
* queued again (at the front, with a new RQ id) while it has been started fewer than
  ``max_attempts`` times, so another worker re-runs it;
* failed with ``worker_lost`` otherwise: a job that kills every worker it lands on (a poison
  input) does not take the queue down.

A worker that was only slow (its lease lapsed, then it came back) finds its attempt number
superseded at its next renewal, progress report or cancel poll and drops its work; its writes
are fenced by the attempt number, so two attempts never both write a result.

A job can also be lost before it starts: a worker killed between taking it from the RQ queue
and starting it. The orphan sweep (one worker every ORPHAN_SWEEP_S) enqueues again a queued job
that RQ has neither waiting nor started at two sweeps in a row.
"""

from __future__ import annotations

import json
import logging

from pydantic import BaseModel
from redis.client import Pipeline

from schemas.jobs import JobError
from service.store.jobs import JobStore
from service.store.queues import Queues
from service.store.records import JobRecord, utc_now
from service.store.stats import JobStats
from service.store.transitions import Current

log = logging.getLogger(__name__)

#: Renewals per lease period: a lease survives LEASE_RENEWALS - 1 missed renewals.
LEASE_RENEWALS = 6
#: Job timeout of a requeued job whose record predates the stored timeout, s.
DEFAULT_TIMEOUT_S = 900
#: Period of the orphan sweep (one worker per period does it), s. A job RQ lost is enqueued
#: again within two periods.
ORPHAN_SWEEP_S = 30

# KEYS: job hash, lease. ARGV: attempt, lease ms. Renews the lease if the attempt still runs.
_RENEW = """
local s = redis.call('HMGET', KEYS[1], 'status', 'attempts')
if s[1] == 'running' and s[2] == ARGV[1] then
  redis.call('SET', KEYS[2], ARGV[1], 'PX', ARGV[2])
  return 1
end
return 0
"""
# KEYS: lease. ARGV: attempt. Deletes the lease if this attempt holds it.
_DROP = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('DEL', KEYS[1])
end
return 0
"""
# KEYS: job hash, events channel. ARGV: attempt, progress JSON, event JSON.
_PROGRESS = """
local s = redis.call('HMGET', KEYS[1], 'status', 'attempts')
if s[1] == 'running' and s[2] == ARGV[1] then
  redis.call('HSET', KEYS[1], 'progress', ARGV[2])
  redis.call('PUBLISH', KEYS[2], ARGV[3])
  return 1
end
return 0
"""


class Leases:
    """The worker's side of running a job: start it, renew its lease, report, check it."""

    def __init__(self, store: JobStore, lease_s: float) -> None:
        self.store = store
        self.keys = store.keys
        self.lease_ms = max(1000, int(lease_s * 1000))
        self._renew = store.r.register_script(_RENEW)
        self._progress = store.r.register_script(_PROGRESS)
        self._drop = store.r.register_script(_DROP)

    @property
    def renew_interval_s(self) -> float:
        return self.lease_ms / 1000.0 / LEASE_RENEWALS

    def start(self, job_id: str, worker: str, rq_id: str) -> JobRecord | None:
        """queued → running as the next attempt, taking the lease; None when the job is not
        queued (cancelled, expired) or ``rq_id`` is not its current enqueueing (stale)."""

        def guard(current: Current, pipe: Pipeline) -> bool:
            return current["status"] == "queued" and current["rq_id"] in (rq_id, None, "")

        def fields(current: Current) -> dict[str, str]:
            attempt = int(current["attempts"] or 0) + 1
            return {
                "status": "running",
                "started_at": utc_now(),
                "worker": worker,
                "attempts": str(attempt),
                "progress": "",
            }

        def extra(pipe: Pipeline, current: Current) -> None:
            attempt = int(current["attempts"] or 0) + 1
            pipe.set(self.keys.job_lease(job_id), str(attempt), px=self.lease_ms)
            pipe.sadd(self.keys.jobs_running, job_id)
            pipe.srem(self.keys.jobs_queued, job_id)

        if self.store.transitions.apply(job_id, guard, fields, extra) is None:
            return None
        self.store.publish(job_id, "status", {"status": "running"})
        return self.store.get(job_id)

    def renew(self, job_id: str, attempt: int) -> bool:
        """Extend the lease; False if this attempt no longer runs (recovered, ended)."""
        keys = [self.keys.job(job_id), self.keys.job_lease(job_id)]
        return bool(self._renew(keys=keys, args=[attempt, self.lease_ms]))

    def drop(self, job_id: str, attempt: int) -> bool:
        """Let go of the lease now (a stopping worker), so that a reaper requeues the job at
        once; False if this attempt did not hold it."""
        return bool(self._drop(keys=[self.keys.job_lease(job_id)], args=[attempt]))

    def check(self, job_id: str, attempt: int) -> tuple[bool, bool]:
        """(this attempt still runs the job, a client asked it to stop)."""
        pipe = self.store.r.pipeline(transaction=False)
        pipe.hmget(self.keys.job(job_id), ["status", "attempts"])
        pipe.exists(self.keys.job_cancel(job_id))
        (status, attempts), cancel = pipe.execute()
        return status == b"running" and attempts == str(attempt).encode(), bool(cancel)

    def set_progress(
        self, job_id: str, attempt: int, progress: BaseModel, event: BaseModel | None = None
    ) -> bool:
        """Store the progress and publish it (or ``event``, when what is stored is more than
        what a listener needs: a track stores all its frames so far, its event carries one);
        False (nothing written) if the attempt is stale."""
        data = progress.model_dump_json()
        published = (event or progress).model_dump(mode="json")
        message = json.dumps({"event": "progress", "data": published})
        keys = [self.keys.job(job_id), self.keys.job_events(job_id)]
        return bool(self._progress(keys=keys, args=[attempt, data, message]))


class Reaper:
    """Recovers running jobs whose lease lapsed (see the module docstring)."""

    def __init__(self, store: JobStore, max_attempts: int) -> None:
        self.store = store
        self.keys = store.keys
        self.max_attempts = max_attempts

    def reconcile(self, record: JobRecord) -> JobRecord:
        """The record, after recovering it if it runs on a worker whose lease has lapsed (the
        API checks the job it is asked about, besides the workers' sweeps)."""
        if record.status != "running" or self.store.r.exists(self.keys.job_lease(record.id)):
            return record
        self.recover(record.id)
        return self.store.get(record.id) or record

    def sweep(self) -> list[tuple[str, str]]:
        """Check every running job; (job id, what was done) for each one recovered."""
        r = self.store.r
        ids = [m.decode() for m in r.smembers(self.keys.jobs_running)]  # type: ignore[union-attr]
        if not ids:
            return []
        pipe = r.pipeline(transaction=False)
        for job_id in ids:
            pipe.exists(self.keys.job_lease(job_id))
        done = []
        for job_id, leased in zip(ids, pipe.execute(), strict=True):
            if not leased:
                outcome = self.recover(job_id)
                if outcome is not None:
                    done.append((job_id, outcome))
        return done

    def recover(self, job_id: str, why: str = "its lease lapsed") -> str | None:
        """Requeue, fail or cancel running job ``job_id`` if its lease has lapsed; what was
        done ('requeued', 'failed', 'cancelled'), or None if the job needed nothing."""
        lease = self.keys.job_lease(job_id)
        verdict: dict[str, str] = {}

        def guard(current: Current, pipe: Pipeline) -> bool:
            if current["status"] != "running":
                pipe.srem(self.keys.jobs_running, job_id)  # a stale entry (under WATCH: ok)
                return False
            return not pipe.exists(lease)

        def fields(current: Current) -> dict[str, str]:
            outcome, out = self._verdict(job_id, current)
            verdict.update(outcome=outcome, rq_id=out.get("rq_id", ""))
            return out

        def extra(pipe: Pipeline, current: Current) -> None:
            queues = self.store.queues
            if current["rq_id"]:
                queues.forget_estimate(pipe, current["rq_id"])
            if verdict["outcome"] == "requeued":
                pipe.srem(self.keys.jobs_running, job_id)
                pipe.sadd(self.keys.jobs_queued, job_id)
                timeout_s = int(current["timeout_s"] or 0) or DEFAULT_TIMEOUT_S
                queues.enqueue_estimate(
                    pipe, job_id, verdict["rq_id"], timeout_s, at_front=True, kind=current["kind"]
                )
            else:
                pipe.expire(self.keys.job(job_id), self.store.retention_s)
                self.store.transitions.release(pipe, job_id, current)

        before = self.store.transitions.apply(job_id, guard, fields, extra, watch=(lease,))
        if before is None:
            return None
        outcome = verdict["outcome"]
        log.warning(
            "job %s: the worker of attempt %s is gone (%s): %s",
            *(job_id, before["attempts"], why, outcome),
            extra={"job_id": job_id, "attempt": before["attempts"], "outcome": outcome},
        )
        self.store.publish(job_id, "status", {"status": "queued" if verdict["rq_id"] else outcome})
        if outcome != "requeued":
            code = "worker_lost" if outcome == "failed" else None
            JobStats(self.store.r, self.keys).count(before["kind"] or "estimate", outcome, code)
        return outcome

    def _verdict(self, job_id: str, current: Current) -> tuple[str, dict[str, str]]:
        """What becomes of a running job whose worker is gone, and its new fields: cancelled
        if a client asked, failed after max_attempts starts, else queued under a new RQ id."""
        attempt = int(current["attempts"] or 0)
        lost = json.loads(current["lost"] or "[]")
        lost.append({"attempt": attempt, "worker": current["worker"], "at": utc_now()})
        out = {"lost": json.dumps(lost)}
        if current["cancel_requested"] == "1":
            return "cancelled", out | {"status": "cancelled", "finished_at": utc_now()}
        if attempt >= self.max_attempts:
            error = JobError(
                code="worker_lost",
                message=f"the worker running this job stopped (killed, crashed or out of memory) "
                f"on each of its {attempt} attempts; it is not retried again",
            )
            return "failed", out | {
                "status": "failed",
                "finished_at": utc_now(),
                "error": error.model_dump_json(),
            }
        rq_id = Queues.next_estimate_rq_id(job_id, current["rq_id"])
        return "requeued", out | {
            "status": "queued",
            "rq_id": rq_id,
            "started_at": "",
            "worker": "",
            "progress": "",
        }

    # ------------------------------------------------------------------ orphans
    def sweep_orphans(self) -> list[str]:
        """Re-enqueue queued jobs that RQ lost (a worker killed between taking a job from the
        queue and starting it; a queue emptied by hand): those missing from RQ at two sweeps in
        a row under the same RQ id. One worker per ORPHAN_SWEEP_S does it; returns their ids."""
        r = self.store.r
        if not r.set(self.keys.orphan_sweep_lock, "1", nx=True, ex=ORPHAN_SWEEP_S):
            return []
        ids = [m.decode() for m in r.smembers(self.keys.jobs_queued)]  # type: ignore[union-attr]
        pipe = r.pipeline(transaction=False)
        for job_id in ids:
            pipe.hget(self.keys.job(job_id), "rq_id")
        queued = {j: q.decode() for j, q in zip(ids, pipe.execute(), strict=True) if q}
        known = self.store.queues.estimates_known()
        missing = {job_id: rq_id for job_id, rq_id in queued.items() if rq_id not in known}
        before = {k.decode(): v.decode() for k, v in r.hgetall(self.keys.orphan_suspects).items()}  # type: ignore[union-attr]
        confirmed = {j: q for j, q in missing.items() if before.get(j) == q}
        pipe = r.pipeline()
        pipe.delete(self.keys.orphan_suspects)
        suspects = {j: q for j, q in missing.items() if j not in confirmed}
        if suspects:
            pipe.hset(self.keys.orphan_suspects, mapping=suspects)  # type: ignore[arg-type]
        pipe.execute()
        return [job_id for job_id, rq_id in confirmed.items() if self._reenqueue(job_id, rq_id)]

    def _reenqueue(self, job_id: str, rq_id: str) -> bool:
        new_rq_id = Queues.next_estimate_rq_id(job_id, rq_id)

        def guard(current: Current, pipe: Pipeline) -> bool:
            return current["status"] == "queued" and current["rq_id"] == rq_id

        def extra(pipe: Pipeline, current: Current) -> None:
            queues = self.store.queues
            queues.forget_estimate(pipe, rq_id)
            timeout_s = int(current["timeout_s"] or 0) or DEFAULT_TIMEOUT_S
            queues.enqueue_estimate(
                pipe, job_id, new_rq_id, timeout_s, at_front=True, kind=current["kind"]
            )

        done = self.store.transitions.apply(job_id, guard, {"rq_id": new_rq_id}, extra) is not None
        if done:
            log.warning(
                "job %s: queued but missing from RQ (as %s): enqueued again",
                job_id,
                rq_id,
                extra={"job_id": job_id},
            )
        return done
