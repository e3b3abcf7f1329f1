"""Running a stored job (an estimate, a track) on a worker: taking it from the queue, holding
its lease, and storing how it ended, whatever the work was.

A job reads its request from Redis and its inputs and model from the blob store, and writes its
progress and result to Redis and its artifacts to the blob store, so a worker never needs the
API's disk: workers on other machines share Redis and the blob store. A blob store that is down
or full is retried like a lost worker (the job goes back to the queue, after a pause) and fails
the job with ``store_unavailable`` on its last attempt. Workers run jobs in-process (see
:mod:`worker.jobs.runner`).
"""

from __future__ import annotations

import logging
import time
import traceback
from collections.abc import Callable
from typing import Any

import redis
from pydantic import BaseModel
from rq import get_current_job
from rq.timeouts import JobTimeoutException

from schemas.jobs import JobError
from schemas.settings import Settings, get_settings
from service.logs import log_context
from service.store import JobRecord, JobStats, JobStore, Keys, Leases, ModelStore, Reaper
from service.store.blobs import BlobStoreUnavailable
from worker.engine.exceptions import EstimationCancelled, ProxposeError
from worker.jobs.context import job_blobs, job_context, worker_name
from worker.jobs.lease import STOP_NOW, CancelFlag, LeaseKeeper
from worker.jobs.outage import (
    OUTAGE_ERRORS,
    OutageNotice,
    call_through_outage,
    is_outage,
    wait_for_redis,
)

log = logging.getLogger(__name__)

#: Pause before a job that found the blob store unavailable goes back to the queue, per
#: attempt so far, s (a store restarting has time to come back before the next attempt).
STORE_RETRY_PAUSE_S = 2.0
#: Longest a job waits for Redis to come back (to start, to store its result, to hand itself
#: back), s; past it the job is left to the lease and the reapers.
OUTAGE_WAIT_MAX_S = 600.0


#: The work of a job: run the engine on a started job and store the outcome (with
#: :func:`finish`); (status, failure code). Errors other than a stop requested through the flag
#: propagate, and :func:`run_stored_job` records them.
Work = Callable[[JobStore, CancelFlag, JobRecord, ModelStore, Settings], tuple[str, "str | None"]]


def _interruption(exc: BaseException) -> BaseException | None:
    """A stop or a timeout signal in ``exc``'s chain: the signal handlers raise them wherever
    the worker is, and the renderer may wrap them (Dr.Jit turns them into a RuntimeError)."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, SystemExit | KeyboardInterrupt | JobTimeoutException):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def run_stored_job(job_id: str, work: Work) -> None:
    """Run stored job ``job_id`` (its RQ job's entry point calls this with its work)."""
    settings, r, keys = job_context()
    blobs = job_blobs(settings)
    store = JobStore(r, keys, settings.retention_s, blobs=blobs)
    leases = Leases(store, settings.job_lease_s)
    job = get_current_job()
    worker = worker_name()
    notice = OutageNotice(f"job {job_id}")
    record = call_through_outage(
        lambda: leases.start(job_id, worker, job.id if job is not None else ""),
        r,
        notice,
        STOP_NOW.is_set,
        OUTAGE_WAIT_MAX_S,
    )
    if not isinstance(record, JobRecord):
        log.info("job %s is no longer queued (cancelled, expired or requeued): skipped", job_id)
        return
    attempt = record.attempts
    timeout_s = record.timeout_s or settings.job_timeout_s
    t0 = time.monotonic()
    status, code = "failed", None
    with log_context(job_id=job_id, attempt=attempt, worker=worker):
        log.info(
            "job %s: attempt %d started (%s, model %s)",
            *(job_id, attempt, record.kind, record.model_id),
        )
        with LeaseKeeper(leases, job_id, attempt) as keeper:
            flag = CancelFlag(leases, keeper, timeout_s)
            try:
                models = ModelStore(r, keys, blobs=blobs)
                status, code = work(store, flag, record, models, settings)
            except BaseException as exc:
                if is_outage(exc) and _interruption(exc) is None:
                    status, code = _hand_back_after_outage(store, leases, record, attempt, notice)
                    return  # not an error of the RQ job: it only carried this attempt
                status, code = _failed(store, leases, flag, record, exc, timeout_s, settings)
                if not isinstance(exc, Exception) or code == "internal_error":
                    raise  # a stop signal ends the worker; RQ keeps internal errors too
            finally:
                log.info("job %s: attempt %d ended: %s %s", job_id, attempt, status, code or "")
                if status not in ("superseded", "stopped", "retried", "interrupted"):
                    _record_stats(r, keys, record.kind, status, time.monotonic() - t0, code)


class ProgressReport:
    """Stores and publishes a running job's progress (``progress``, and ``event`` if what
    listeners get differs); through a Redis outage the job goes on without it. A report the
    store refuses means another attempt holds the job: the flag then stops this one."""

    def __init__(self, flag: CancelFlag, job_id: str) -> None:
        self.flag, self.job_id = flag, job_id
        self.notice = OutageNotice(f"job {job_id}: progress")

    def __call__(self, progress: BaseModel, event: BaseModel | None = None) -> None:
        keeper = self.flag.keeper
        try:
            if not self.flag.leases.set_progress(self.job_id, keeper.attempt, progress, event):
                keeper.lost.set()
            self.notice.ok()
        except OUTAGE_ERRORS as exc:  # progress is a report: the job goes on without it
            self.notice.failed(exc)


def cancelled(
    store: JobStore, flag: CancelFlag, record: JobRecord, exc: EstimationCancelled
) -> tuple[str, str | None]:
    """The engine stopped at the flag: a client's cancel is stored; any other reason (a stop,
    a timeout, a superseded attempt) is ``exc`` again, for :func:`_failed`."""
    if flag.reason != "cancelled":
        raise exc
    finish(store, record, flag.keeper.attempt, "cancelled")
    return "cancelled", None


def finish(store: JobStore, record: JobRecord, attempt: int, status: str, **outcome: Any) -> None:
    """Store the outcome, waiting for Redis through an outage (up to OUTAGE_WAIT_MAX_S): only
    the attempt that still holds the job can store it, so a late one is dropped, not doubled."""
    notice = OutageNotice(f"job {record.id}: storing its {status}")
    finished = call_through_outage(
        lambda: store.finish(record.id, status, attempt=attempt, **outcome),
        store.r,
        notice,
        STOP_NOW.is_set,
        OUTAGE_WAIT_MAX_S,
    )
    if not finished:
        log.warning(
            "job %s: attempt %d was superseded; its %s is dropped", record.id, attempt, status
        )


def _failed(
    store: JobStore,
    leases: Leases,
    flag: CancelFlag,
    record: JobRecord,
    exc: BaseException,
    timeout_s: float,
    settings: Settings,
) -> tuple[str, str | None]:
    """Record why the attempt ended early; (status, failure code). A stopping worker gives the
    job back to the queue, a superseded attempt writes nothing, the rest fail the job."""
    attempt = flag.keeper.attempt
    interruption = _interruption(exc)
    reason = flag.reason if isinstance(exc, EstimationCancelled) else None
    if reason == "stopped" or isinstance(interruption, SystemExit | KeyboardInterrupt):
        log.warning(
            "job %s: the worker is stopping; attempt %d goes back to the queue", record.id, attempt
        )
        _give_back(leases, store, record.id, attempt, settings.job_max_attempts)
        return "stopped", None
    if reason == "superseded":
        log.warning("job %s: attempt %d stopped: another attempt holds the job", record.id, attempt)
        return "superseded", None
    if reason == "timeout" or isinstance(interruption, JobTimeoutException):
        message = f"the {record.kind} ran longer than the job timeout ({timeout_s:g} s)"
        tb = traceback.format_exc()
        finish(
            store,
            record,
            attempt,
            "failed",
            error=JobError(code="timeout", message=message),
            traceback=tb,
        )
        return "failed", "timeout"
    if isinstance(exc, BlobStoreUnavailable):
        return _store_unavailable(store, leases, record, attempt, exc, settings)
    if isinstance(exc, ProxposeError):
        finish(store, record, attempt, "failed", error=JobError(code=exc.code, message=str(exc)))
        return "failed", exc.code
    log.exception("job %s: internal error", record.id)
    message = "internal error in the worker (the traceback is in the job record)"
    error = JobError(code="internal_error", message=message)
    finish(store, record, attempt, "failed", error=error, traceback=traceback.format_exc())
    return "failed", "internal_error"


def _store_unavailable(
    store: JobStore,
    leases: Leases,
    record: JobRecord,
    attempt: int,
    exc: BlobStoreUnavailable,
    settings: Settings,
) -> tuple[str, str | None]:
    """The blob store failed: queue the job again after a pause, or fail it on its last
    attempt (a store down for good must not keep a job forever)."""
    if attempt < settings.job_max_attempts:
        log.warning("job %s: attempt %d: %s; it goes back to the queue", record.id, attempt, exc)
        time.sleep(STORE_RETRY_PAUSE_S * attempt)
        why = "the blob store is unavailable"
        _give_back(leases, store, record.id, attempt, settings.job_max_attempts, why)
        return "retried", None
    log.error("job %s: attempt %d: %s; no attempt left", record.id, attempt, exc)
    message = (
        f"the blob store ({exc.store}) was unavailable (down or full) on each of the job's "
        f"{attempt} attempts"
    )
    error = JobError(code="store_unavailable", message=message)
    finish(store, record, attempt, "failed", error=error)
    return "failed", "store_unavailable"


def _hand_back_after_outage(
    store: JobStore, leases: Leases, record: JobRecord, attempt: int, notice: OutageNotice
) -> tuple[str, str | None]:
    """The attempt met Redis away: wait for it, then put the job back in the queue at once (if
    Redis stays away, the lease lapses meanwhile and any worker's reaper requeues it)."""
    log.warning("job %s: attempt %d interrupted by a Redis outage", record.id, attempt)
    settings = get_settings()
    if wait_for_redis(store.r, notice, STOP_NOW.is_set, OUTAGE_WAIT_MAX_S):
        _give_back(leases, store, record.id, attempt, settings.job_max_attempts)
    return "interrupted", None


def _record_stats(
    r: redis.Redis, keys: Keys, kind: str, status: str, seconds: float, code: str | None
) -> None:
    try:
        JobStats(r, keys).record(kind, status, seconds, code)
    except OUTAGE_ERRORS as exc:  # statistics are not worth waiting for
        log.warning("could not record the job's statistics: %s", exc)


def _give_back(
    leases: Leases,
    store: JobStore,
    job_id: str,
    attempt: int,
    max_attempts: int,
    why: str = "its worker is stopping",
) -> None:
    """Put the job back in the queue now (a stopping worker, a blob store outage), instead of
    when its lease lapses."""
    try:
        if leases.drop(job_id, attempt):
            Reaper(store, max_attempts).recover(job_id, why=why)
    except redis.RedisError as exc:  # the lease lapses and a reaper requeues it
        log.warning("job %s: could not requeue it now (%s); a reaper will", job_id, exc)
