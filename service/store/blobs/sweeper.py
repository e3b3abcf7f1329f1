"""The blob sweep: delete every blob no job or model refers to any more, and count the rest.

Redis decides what lives: a job's hash expires with the retention, a model's with its last
owner. A blob is deleted when

* it belongs to a job (``jobs/<id>/...``) whose hash is gone (expired after the retention), or
  to an ended job that does not refer to it (its image; the artifacts of a superseded attempt);
* it is a model file (``models/<id>/<sha256>``) whose model is gone or has other content;

blobs of a job not in Redis yet, or of a model whose metadata does not name them yet (the bytes
are written before their record), are kept for ORPHAN_GRACE_S. One worker per period sweeps
(``sweep_if_due``); ``proxpose migrate-blobs`` sweeps too. The census (objects and bytes kept)
goes to Redis for /metrics.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import redis

from schemas.jobs import TERMINAL_STATUSES
from service.store.blobs.base import BlobEntry, BlobStore
from service.store.keys import Keys

log = logging.getLogger(__name__)

#: A blob whose job or model is not in Redis is kept this long (its record may be on its
#: way: the bytes are written first), s.
ORPHAN_GRACE_S = 3600.0
#: Whether to keep each blob of a batch, given the time now (Unix s).
Verdicts = Callable[[list[BlobEntry], float], list[bool]]
#: Records read per Redis round trip, and blobs per delete call.
BATCH = 500


@dataclass
class SweepReport:
    """What a sweep did: blobs (and bytes) deleted, and kept."""

    deleted: int = 0
    deleted_bytes: int = 0
    objects: int = 0
    bytes: int = 0

    def count(self, entry: BlobEntry, keep: bool) -> None:
        if keep:
            self.objects += 1
            self.bytes += entry.size_bytes
        else:
            self.deleted += 1
            self.deleted_bytes += entry.size_bytes


class BlobSweeper:
    """Sweeps ``blobs`` against the records in Redis ``r`` (bytes-returning client)."""

    def __init__(
        self, r: redis.Redis, keys: Keys, blobs: BlobStore, grace_s: float = ORPHAN_GRACE_S
    ) -> None:
        self.r, self.keys, self.blobs, self.grace_s = r, keys, blobs, grace_s

    def sweep_if_due(self, period_s: float) -> SweepReport | None:
        """Sweep unless another process did within ``period_s``."""
        if not self.r.set(self.keys.blob_sweep_lock, "1", nx=True, ex=max(1, int(period_s))):
            return None
        return self.sweep()

    def sweep(self) -> SweepReport:
        """Delete the blobs nothing refers to; record and return the census."""
        report = SweepReport()
        now = time.time()
        self._sweep(self.blobs.list("jobs/"), self._job_verdicts, report, now)
        self._sweep(self.blobs.list("models/"), self._model_verdicts, report, now)
        pipe = self.r.pipeline()
        census = self.keys.blob_census
        pipe.hset(census, mapping={"objects": report.objects, "bytes": report.bytes, "at": now})
        pipe.hincrby(census, "swept", report.deleted)
        pipe.execute()
        if report.deleted:
            log.info(
                "blob sweep: deleted %d blobs (%d bytes); %d blobs (%d bytes) kept",
                *(report.deleted, report.deleted_bytes, report.objects, report.bytes),
            )
        return report

    def _sweep(
        self, entries: Iterable[BlobEntry], verdicts: Verdicts, report: SweepReport, now: float
    ) -> None:
        batch: list[BlobEntry] = []
        for entry in entries:
            batch.append(entry)
            if len(batch) >= BATCH:
                self._decide(batch, verdicts, report, now)
                batch = []
        if batch:
            self._decide(batch, verdicts, report, now)

    def _decide(
        self, batch: list[BlobEntry], verdicts: Verdicts, report: SweepReport, now: float
    ) -> None:
        keep = verdicts(batch, now)
        doomed = [e.name for e, k in zip(batch, keep, strict=True) if not k]
        for entry, k in zip(batch, keep, strict=True):
            report.count(entry, k)
        if doomed:
            self.blobs.delete(doomed)

    def _young(self, entry: BlobEntry, now: float) -> bool:
        return now - entry.modified_s < self.grace_s

    def _job_verdicts(self, batch: list[BlobEntry], now: float) -> list[bool]:
        ids = sorted({e.name.split("/")[1] for e in batch if e.name.count("/") >= 2})
        pipe = self.r.pipeline(transaction=False)
        for job_id in ids:
            pipe.hmget(self.keys.job(job_id), ["status", "artifact_blobs"])
        records = dict(zip(ids, pipe.execute(), strict=True))
        keep = []
        for entry in batch:
            parts = entry.name.split("/")
            status, refs = records.get(parts[1], (None, None)) if len(parts) >= 3 else (None, None)
            if status is None:  # expired (or not written yet)
                keep.append(self._young(entry, now))
            elif status.decode() in TERMINAL_STATUSES:
                wanted = {str(r["blob"]) for r in json.loads(refs or b"{}").values()}
                keep.append(entry.name in wanted)
            else:  # queued or running: its image, the artifacts of an attempt finishing
                keep.append(True)
        return keep

    def _model_verdicts(self, batch: list[BlobEntry], now: float) -> list[bool]:
        ids = sorted({e.name.split("/")[1] for e in batch if e.name.count("/") == 2})
        pipe = self.r.pipeline(transaction=False)
        for model_id in ids:
            pipe.hget(self.keys.model(model_id), "meta")
        metas = dict(zip(ids, pipe.execute(), strict=True))
        keep = []
        for entry in batch:
            parts = entry.name.split("/")
            meta = metas.get(parts[1]) if len(parts) == 3 else None
            current = meta is not None and json.loads(meta).get("sha256") == parts[2]
            keep.append(current or self._young(entry, now))  # young: its meta is on its way
        return keep
