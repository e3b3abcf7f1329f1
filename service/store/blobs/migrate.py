"""Moving the bytes an older deployment kept in Redis to the blob store.

Until it runs, those jobs and models keep working: the stores read a record's bytes from Redis
when the record names no blob. Each move writes the blob, then points the record at it and
deletes the Redis copy in one transaction, so a reader finds the bytes in one place or the
other at every moment, and the command can be stopped and run again (it resumes). The API and
the workers may keep running meanwhile. Afterwards it sweeps the blob store (``sweeper``).
Finished jobs' plain ``result`` fields are compressed into ``result_z`` on the way (a third of
the size; both read the same).
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Iterator
from dataclasses import dataclass

import redis

from schemas.jobs import TERMINAL_STATUSES
from service.store.blobs.base import (
    BlobStore,
    job_artifact_name,
    job_image_name,
    model_file_name,
)
from service.store.keys import Keys
from service.store.records import RESULT_Z_FIELD, pack_result

log = logging.getLogger(__name__)

#: Keys asked for per SCAN step.
SCAN_COUNT = 500


@dataclass
class MigrationReport:
    """What was moved (images, artifacts, model files, bytes), dropped (Redis copies of
    ended jobs' images, and of records that are gone) and compressed (plain results)."""

    images: int = 0
    artifacts: int = 0
    models: int = 0
    bytes: int = 0
    dropped: int = 0
    results: int = 0


class BlobMigration:
    """Moves the blobs in Redis ``r`` (bytes-returning client) under ``keys`` to ``blobs``."""

    def __init__(self, r: redis.Redis, keys: Keys, blobs: BlobStore) -> None:
        self.r, self.keys, self.blobs = r, keys, blobs
        p = re.escape(keys.prefix)
        self._image = re.compile(rf"^{p}:job:([0-9a-f]{{32}}):image$")
        self._artifact = re.compile(rf"^{p}:job:([0-9a-f]{{32}}):artifact:([A-Za-z0-9_-]+)$")
        self._model = re.compile(rf"^{p}:model:([A-Za-z0-9_-]+):data$")
        self._job = re.compile(rf"^{p}:job:([0-9a-f]{{32}})$")

    def run(self) -> MigrationReport:
        report = MigrationReport()
        self._images(report)
        self._artifacts(report)
        self._models(report)
        self._results(report)
        return report

    def _scan(self, pattern: str, regex: re.Pattern[str]) -> Iterator[tuple[str, re.Match[str]]]:
        for raw in self.r.scan_iter(match=pattern, count=SCAN_COUNT):
            key = raw.decode()
            match = regex.match(key)
            if match:
                yield key, match

    def _move(self, key: str, record: str, field: str, value: object, blob: str) -> bool:
        """Point ``record``'s ``field`` at the blob and delete ``key`` in one transaction (a
        dict ``value`` is merged into the field's JSON); False if the record is gone."""
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(record)
                    if not pipe.exists(record):
                        pipe.multi()
                        pipe.delete(key)
                        pipe.execute()
                        self.blobs.delete([blob])
                        return False
                    if isinstance(value, dict):
                        merged = json.loads(pipe.hget(record, field) or b"{}")  # type: ignore[arg-type]
                        value = json.dumps(merged | value)
                    pipe.multi()
                    pipe.hset(record, field, str(value))
                    pipe.delete(key)
                    pipe.execute()
                    return True
                except redis.WatchError:
                    continue

    def _images(self, report: MigrationReport) -> None:
        for key, match in self._scan(f"{self.keys.prefix}:job:*:image", self._image):
            job_id = match.group(1)
            status = self.r.hget(self.keys.job(job_id), "status")
            data = self.r.get(key)
            if data is None:
                continue
            if status is None or status.decode() in TERMINAL_STATUSES:  # type: ignore[union-attr]
                self.r.delete(key)  # an ended job needs its image no more
                report.dropped += 1
                continue
            blob = job_image_name(job_id)
            self.blobs.put(blob, data)  # type: ignore[arg-type]
            if self._move(key, self.keys.job(job_id), "image_blob", blob, blob):
                report.images += 1
                report.bytes += len(data)  # type: ignore[arg-type]
            else:
                report.dropped += 1

    def _artifacts(self, report: MigrationReport) -> None:
        import hashlib

        for key, match in self._scan(f"{self.keys.prefix}:job:*:artifact:*", self._artifact):
            job_id, name = match.groups()
            data: bytes | None = self.r.get(key)  # type: ignore[assignment]
            if data is None:
                continue
            blob = job_artifact_name(job_id, "migrated", name)
            self.blobs.put(blob, data, "image/png")
            ref = {"blob": blob, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
            if self._move(key, self.keys.job(job_id), "artifact_blobs", {name: ref}, blob):
                report.artifacts += 1
                report.bytes += len(data)
            else:
                report.dropped += 1

    def _models(self, report: MigrationReport) -> None:
        import hashlib

        for key, match in self._scan(f"{self.keys.prefix}:model:*:data", self._model):
            model_id = match.group(1)
            meta = self.r.hget(self.keys.model(model_id), "meta")
            data: bytes | None = self.r.get(key)  # type: ignore[assignment]
            if data is None:
                continue
            sha = json.loads(meta).get("sha256") if meta else None  # type: ignore[arg-type]
            if sha is None or hashlib.sha256(data).hexdigest() != sha:
                log.warning("model %s: its Redis copy matches no registration: dropped", model_id)
                self.r.delete(key)
                report.dropped += 1
                continue
            blob = model_file_name(model_id, sha)
            self.blobs.put(blob, data)
            self.r.delete(key)  # the store reads the blob first: the copy is not needed
            report.models += 1
            report.bytes += len(data)

    def _results(self, report: MigrationReport) -> None:
        for key, _match in self._scan(f"{self.keys.prefix}:job:*", self._job):
            with self.r.pipeline() as pipe:
                while True:
                    try:
                        pipe.watch(key)
                        plain: bytes | None = pipe.hget(key, "result")  # type: ignore[assignment]
                        if plain is None:
                            pipe.unwatch()
                            break
                        pipe.multi()
                        pipe.hset(key, RESULT_Z_FIELD, pack_result(plain.decode()))
                        pipe.hdel(key, "result")
                        pipe.execute()
                        report.results += 1
                        break
                    except redis.WatchError:
                        continue
