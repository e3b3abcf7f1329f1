"""Jobs in Redis (estimates, tracks): one hash per job, indexes for listing, the inputs (an
image, a track's frames), the artifacts.

The bytes are not in Redis: the image and the artifacts are blobs (``service.store.blobs``),
written before the Redis change that refers to them, so that nothing refers to a blob that is
not whole; the hash records their names and hashes. Jobs of an older deployment whose bytes are
still in Redis are read from there (until ``proxpose migrate-blobs`` moves them).

The status moves queued → running → succeeded | failed | cancelled; the one way back is a
reaper putting a running job whose worker died back in the queue (``service.store.leases``).
Every change goes through :mod:`service.store.transitions`, a WATCH/MULTI check-and-set, so
that the API cancelling a queued job, a worker starting it and a reaper recovering it cannot
both win; a worker's writes are fenced by its attempt number. A job is created and enqueued in one
transaction. Terminal jobs, their artifacts and idempotency keys expire after the retention.

A store built for a ``viewer`` (the caller's principal) sees only that principal's jobs, unless
it is an admin; the workers' stores see everything.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable, Sequence
from typing import Any

import redis
from redis.client import Pipeline

from schemas.jobs import JobError
from service.store.access import Principal
from service.store.blobs.base import (
    BlobStore,
    BlobStoreError,
    artifact_media_type,
    job_artifact_name,
    job_image_name,
    job_input_name,
)
from service.store.keys import Keys
from service.store.queues import Queues
from service.store.records import RESULT_Z_FIELD, JobRecord, pack_result, text, utc_now
from service.store.reservations import (
    RESERVE_SCRIPT,
    ActiveJobsLimitError,
    IdempotencyKeyTaken,
    claim_value,
)
from service.store.transitions import Current, Transitions

__all__ = ["ActiveJobsLimitError", "IdempotencyKeyTaken", "JobStore"]

log = logging.getLogger(__name__)

#: Positions scanned at most to fill one listing page (expired jobs are skipped and pruned).
LIST_SCAN_MAX = 1000
#: Characters of a failed job's traceback kept in its hash (the end: the raising frames and the
#: exception); a deep one would otherwise be most of the job's Redis memory.
TRACEBACK_MAX_CHARS = 4000
#: States in which a job counts against its owner's cap and may still change.
ACTIVE_STATUSES = ("queued", "running")


def _queued(
    job_id: str, model_id: str, request_json: str, max_iterations: int, fingerprint: str, owner: str
) -> JobRecord:
    """A new job's record (its sequence number and RQ id are given when it is stored)."""
    return JobRecord(
        id=job_id,
        status="queued",
        model_id=model_id,
        created_at=utc_now(),
        request=request_json,
        seq=0,
        max_iterations=max_iterations,
        owner=owner,
        fingerprint=fingerprint,
    )


class JobStore:
    """Reads and writes jobs (of each kind, ``JobRecord.kind``). ``r`` is a bytes-returning
    Redis client; ``blobs`` holds the inputs and artifacts (for the methods that use them)."""

    def __init__(
        self,
        r: redis.Redis,
        keys: Keys,
        retention_s: int,
        viewer: Principal | None = None,
        queues: Queues | None = None,
        blobs: BlobStore | None = None,
    ) -> None:
        self.r = r
        self.keys = keys
        self.retention_s = retention_s
        self.viewer = viewer
        self._blobs = blobs
        self.queues = queues if queues is not None else Queues(r, keys)
        self.transitions = Transitions(r, keys, retention_s)
        self._reserve = r.register_script(RESERVE_SCRIPT)

    @property
    def blobs(self) -> BlobStore:
        if self._blobs is None:
            raise RuntimeError("this JobStore was made without a blob store")
        return self._blobs

    # ------------------------------------------------------------------ create and read
    def create(
        self,
        job_id: str,
        model_id: str,
        request_json: str,
        max_iterations: int,
        image: bytes,
        fingerprint: str,
        *,
        owner: str,
        timeout_s: int,
        max_active: int = 0,
        idempotency_key: str | None = None,
    ) -> JobRecord:
        """Store a new queued job with its image and enqueue it. The image goes to the blob
        store first: if that fails (BlobStoreUnavailable), nothing is written or enqueued.

        With ``idempotency_key``, the owner's key is first claimed for this job for the
        retention; IdempotencyKeyTaken if an earlier request has it. A claim stays when the
        create fails afterwards: :meth:`release_idempotency` gives it back.

        Raises ActiveJobsLimitError when ``max_active`` > 0 and the owner has that many queued
        or running jobs. The claim, the check and the job's place in the owner's active set are
        one Lua call, so concurrent submissions can neither overshoot the cap nor make each
        other retry (a WATCH on the shared set did: 50 at once took ~0.2 s each); the job itself
        is then written and enqueued in one MULTI transaction."""
        record = _queued(job_id, model_id, request_json, max_iterations, fingerprint, owner)
        record.timeout_s, record.image_blob = timeout_s, job_image_name(job_id)
        return self._create(record, {job_image_name(job_id): image}, max_active, idempotency_key)

    def create_track(
        self,
        job_id: str,
        model_id: str,
        request_json: str,
        frames: Sequence[tuple[str, bytes]],
        fingerprint: str,
        *,
        owner: str,
        timeout_s: int,
        max_active: int = 0,
        idempotency_key: str | None = None,
    ) -> JobRecord:
        """Store a new queued track job with its frames ((file name, bytes), in order) and
        enqueue it, like :meth:`create` (its progress counts frames)."""
        inputs = [
            {"name": name, "blob": job_input_name(job_id, k)}
            for k, (name, _data) in enumerate(frames)
        ]
        record = _queued(job_id, model_id, request_json, len(frames), fingerprint, owner)
        record.timeout_s, record.kind, record.inputs = timeout_s, "track", inputs
        blobs = {ref["blob"]: data for ref, (_name, data) in zip(inputs, frames, strict=True)}
        return self._create(record, blobs, max_active, idempotency_key)

    def _create(
        self,
        record: JobRecord,
        inputs: dict[str, bytes],
        max_active: int,
        idempotency_key: str | None,
    ) -> JobRecord:
        """Claim the idempotency key and reserve the owner's place, write the inputs, then the
        record and its queue entry in one transaction; on any failure after the reservation,
        undo what was done (but for the claim)."""
        job_id, owner = record.id, record.owner
        active = self.keys.owner_active(owner)
        keys = [active, self.keys.jobs_seq]
        args: list[str | int] = [job_id, max_active]
        if idempotency_key is not None:
            keys.append(self.keys.idempotency(owner, idempotency_key))
            args += [claim_value(job_id, record.fingerprint), self.retention_s]
        reply = self._reserve(keys=keys, args=args)
        if reply[0] == -2:
            raise IdempotencyKeyTaken(json.loads(reply[1]))
        seq = int(reply[0])
        if seq < 0:
            raise ActiveJobsLimitError(max_active)
        record.seq = seq
        record.rq_id = Queues.estimate_rq_id(job_id, 1)
        written: list[str] = []
        try:
            for name, data in inputs.items():
                self.blobs.put(name, data)
                written.append(name)
            with self.r.pipeline(transaction=True) as pipe:
                pipe.multi()  # explicit: RQ's enqueue checks for it
                pipe.hset(self.keys.job(job_id), mapping=record.queued_hash())  # type: ignore[arg-type]
                pipe.zadd(self.keys.kind_index(record.kind), {job_id: seq})
                pipe.zadd(self.keys.owner_jobs(owner, record.kind), {job_id: seq})
                pipe.sadd(self.keys.jobs_queued, job_id)
                self.queues.enqueue_estimate(
                    pipe, job_id, record.rq_id, record.timeout_s, kind=record.kind
                )
                pipe.execute()
        except BaseException:
            self.r.srem(active, job_id)  # give the reserved place back
            self._forget_blobs(written)
            raise
        return record

    def get(self, job_id: str) -> JobRecord | None:
        """The job, or None if it does not exist or the viewer may not see it."""
        raw = self.r.hgetall(self.keys.job(job_id))
        if not raw:
            return None
        record = JobRecord.from_hash(raw)  # type: ignore[arg-type]
        return record if self.viewer is None or self.viewer.can_see(record.owner) else None

    def get_image(self, record: JobRecord) -> bytes | None:
        """The job's reference image (None once the job has ended)."""
        if record.image_blob:
            return self.blobs.get(record.image_blob)
        return self.r.get(self.keys.job_image(record.id))  # type: ignore[return-value]

    def get_input(self, record: JobRecord, index: int) -> bytes | None:
        """Input ``index`` of a job of several inputs (None once the job has ended)."""
        return self.blobs.get(record.inputs[index]["blob"])

    def artifact_etag(self, record: JobRecord, name: str) -> str | None:
        """The SHA-256 of an artifact, known without reading it (None for an older job's)."""
        ref = record.artifact_blobs.get(name)
        return str(ref["sha256"]) if ref else None

    def get_artifact(self, record: JobRecord, name: str) -> bytes | None:
        """An artifact's bytes; None if the job has no such artifact or its blob is gone."""
        if name not in record.artifacts:
            return None
        ref = record.artifact_blobs.get(name)
        if ref is not None:
            return self.blobs.get(str(ref["blob"]))
        return self.r.get(self.keys.job_artifact(record.id, name))  # type: ignore[return-value]

    def list_page(
        self,
        limit: int,
        before_seq: int | None,
        where: Callable[[JobRecord], bool] | None = None,
        kind: str = "estimate",
    ) -> tuple[list[JobRecord], int | None]:
        """Up to ``limit`` jobs, newest first, created before ``before_seq`` (and for which
        ``where`` holds); and the cursor of the next page (None on the last). A page scans at
        most LIST_SCAN_MAX index entries: a sparse filter may give a short page with a cursor.
        Index entries of expired jobs are pruned on the way."""
        index = self.keys.kind_index(kind)
        if self.viewer is not None and not self.viewer.admin:
            index = self.keys.owner_jobs(self.viewer.name, kind)
        found: list[JobRecord] = []
        upper = f"({before_seq}" if before_seq is not None else "+inf"
        scanned, exhausted, last_seq = 0, False, None
        while len(found) <= limit and scanned < LIST_SCAN_MAX:
            batch: list[tuple[bytes, float]] = self.r.zrevrangebyscore(  # type: ignore[assignment]
                index, upper, "-inf", start=0, num=limit + 1, withscores=True
            )
            if not batch:
                exhausted = True
                break
            ids = [text(member) or "" for member, _score in batch]
            pipe = self.r.pipeline()
            for job_id in ids:
                pipe.hgetall(self.keys.job(job_id))
            gone = []
            scores = [int(score) for _member, score in batch]
            for job_id, seq, raw in zip(ids, scores, pipe.execute(), strict=True):
                if len(found) > limit:
                    break
                last_seq = seq
                if not raw:
                    gone.append(job_id)
                    continue
                record = JobRecord.from_hash(raw)
                if where is None or where(record):
                    found.append(record)
            if gone:
                self.r.zrem(index, *gone)
            scanned += len(batch)
            upper = f"({last_seq}"
        page = found[:limit]
        if len(found) > limit:
            return page, page[-1].seq
        # the scan budget ran out before the end of the index: go on from where it stopped
        return page, last_seq if not exhausted and scanned >= LIST_SCAN_MAX else None

    # ------------------------------------------------------------------ idempotency
    def release_idempotency(self, owner: str, key: str) -> None:
        self.r.delete(self.keys.idempotency(owner, key))

    # ------------------------------------------------------------------ endings
    def finish(
        self,
        job_id: str,
        status: str,
        *,
        attempt: int | None = None,
        from_statuses: Sequence[str] = ACTIVE_STATUSES,
        error: JobError | None = None,
        result_json: str | None = None,
        artifacts: dict[str, bytes] | None = None,
        traceback: str | None = None,
    ) -> bool:
        """Move the job to a terminal ``status``; False if it was not in ``from_statuses`` or,
        with ``attempt``, if that attempt is no longer the running one (fenced off).

        The artifacts are written to the blob store first (BlobStoreUnavailable if it fails,
        and nothing changes); after the change the image blob goes, or, when the change was
        refused, the artifacts just written."""
        refs = self._put_artifacts(job_id, attempt, artifacts or {})
        fields: dict[str, str | bytes] = {"status": status, "finished_at": utc_now()}
        if error is not None:
            fields["error"] = error.model_dump_json()
        if result_json is not None:
            fields[RESULT_Z_FIELD] = pack_result(result_json)
        if artifacts:
            fields["artifacts"] = json.dumps(list(artifacts))
            fields["artifact_blobs"] = json.dumps(refs)
        if traceback:
            # for operators (redis-cli; an internal error's whole one is in the worker's log)
            fields["traceback"] = traceback[-TRACEBACK_MAX_CHARS:]

        def guard(current: Current, pipe: Pipeline) -> bool:
            if current["status"] not in from_statuses:
                return False
            return attempt is None or (
                current["status"] == "running" and current["attempts"] == str(attempt)
            )

        def extra(pipe: Pipeline, current: Current) -> None:
            self.transitions.release(pipe, job_id, current)

        done = self.transitions.apply(job_id, guard, fields, extra, expire=True) is not None
        if done:
            self._forget_blobs(self._input_blobs(job_id))
            self.publish(job_id, "status", {"status": status})
        else:
            self._forget_blobs([str(ref["blob"]) for ref in refs.values()])
        return done

    def _input_blobs(self, job_id: str) -> list[str]:
        """The blobs of a job's inputs: its image, or its frames."""
        raw = self.r.hget(self.keys.job(job_id), "inputs")
        frames = [str(ref["blob"]) for ref in json.loads(raw)] if raw else []  # type: ignore[arg-type]
        return [job_image_name(job_id), *frames]

    def _put_artifacts(
        self, job_id: str, attempt: int | None, artifacts: dict[str, bytes]
    ) -> dict[str, dict[str, object]]:
        refs: dict[str, dict[str, object]] = {}
        for name, data in artifacts.items():
            blob = job_artifact_name(job_id, attempt if attempt is not None else 0, name)
            self.blobs.put(blob, data, artifact_media_type(name))
            refs[name] = {
                "blob": blob,
                "sha256": hashlib.sha256(data).hexdigest(),
                "bytes": len(data),
            }
        return refs

    def _forget_blobs(self, names: list[str]) -> None:
        """Delete blobs nothing refers to any more; on failure the sweeper deletes them later."""
        if self._blobs is None or not names:
            return
        try:
            self._blobs.delete(names)
        except BlobStoreError as exc:
            log.warning("could not delete %d blobs now (%s); the sweep will", len(names), exc)

    def request_cancel(self, job_id: str) -> JobRecord | None:
        """Cancel a queued job now (and take it out of the queue), or ask a running one to
        stop; returns the record after."""
        record = self.get(job_id)
        if record is None or record.terminal:
            return record
        if record.status == "queued" and self.finish(
            job_id, "cancelled", from_statuses=("queued",)
        ):
            self.queues.remove(self.queues.estimates, record.rq_id)
            return self.get(job_id)
        # running (or started in the meantime): the worker polls this flag before each render
        pipe = self.r.pipeline()
        pipe.set(self.keys.job_cancel(job_id), "1", ex=self.retention_s)
        pipe.hset(self.keys.job(job_id), "cancel_requested", "1")
        pipe.execute()
        self.publish(job_id, "status", {"status": "running", "cancel_requested": True})
        return self.get(job_id)

    # ------------------------------------------------------------------ helpers
    def publish(self, job_id: str, event: str, data: dict[str, Any]) -> None:
        self.r.publish(self.keys.job_events(job_id), json.dumps({"event": event, "data": data}))
