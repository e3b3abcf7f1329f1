"""What every blob store is: a protocol, its errors, the blob names, and operation counters.

Blobs are the bytes of the service (reference images, artifact PNGs, model files); Redis keeps
only their names, hashes and sizes. A name is a relative, slash-separated path of
``[A-Za-z0-9._-]`` segments (no ``..``), the same on every backend, so the filesystem backend
can use it as a path and the S3 one as an object key under its prefix.
"""

from __future__ import annotations

import re
import threading
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Protocol

#: A valid blob name: slash-separated segments of letters, digits, '.', '_' and '-'.
_NAME = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]*(/[A-Za-z0-9_-][A-Za-z0-9._-]*)*$")


class BlobStoreError(Exception):
    """Something went wrong in the blob store."""


class BlobStoreUnavailable(BlobStoreError):
    """The blob store cannot be reached, refuses the operation or is full. ``store`` names it
    in a few words ("filesystem", "S3 bucket 'x'"), fit for a client; ``reason`` (the backend's
    error) is for the logs."""

    code = "store_unavailable"

    def __init__(self, store: str, reason: str) -> None:
        super().__init__(f"the blob store ({store}) is unavailable: {reason}")
        self.store = store
        self.reason = reason


def check_name(name: str) -> str:
    """``name`` if it is a valid blob name, else ValueError (never a path outside the store)."""
    if not _NAME.match(name) or len(name) > 512:
        raise ValueError(f"not a valid blob name: {name[:80]!r}")
    return name


# ------------------------------------------------------------------ the names the service uses
def job_prefix(job_id: str) -> str:
    return f"jobs/{job_id}/"


def job_image_name(job_id: str) -> str:
    """The uploaded reference image of a job (deleted when the job ends)."""
    return f"{job_prefix(job_id)}image"


def job_input_name(job_id: str, index: int) -> str:
    """Input ``index`` of a job of several inputs (a track's frames; deleted when it ends)."""
    return f"{job_prefix(job_id)}input/{index:05d}"


def job_artifact_name(job_id: str, attempt: int | str, name: str) -> str:
    """One artifact of a job, per attempt, so a superseded attempt never overwrites the
    artifacts of the attempt that won (``attempt`` is 'migrated' for blobs moved from Redis).
    A name without a suffix is a PNG ('overlay_final'); others keep theirs ('track.csv')."""
    return f"{job_prefix(job_id)}a{attempt}/{name}{'' if '.' in name else '.png'}"


#: Media types of the artifacts that are not PNGs, by suffix.
ARTIFACT_MEDIA_TYPES = {".csv": "text/csv; charset=utf-8", ".json": "application/json"}


def artifact_media_type(name: str) -> str:
    """The media type an artifact called ``name`` is stored and served as."""
    suffix = name[name.rfind(".") :] if "." in name else ""
    return ARTIFACT_MEDIA_TYPES.get(suffix, "image/png")


def model_file_name(model_id: str, sha256: str) -> str:
    """A model's file, by id and content hash (an upload of the demo's bytes has another id)."""
    return f"models/{model_id}/{sha256}"


@dataclass(frozen=True)
class BlobEntry:
    """A listed blob: its name, size and last modification (Unix time, s)."""

    name: str
    size_bytes: int
    modified_s: float


class BlobStore(Protocol):
    """Bytes by name. Writes are atomic (a reader sees the old bytes, the new ones or none,
    never part of them); failures of the backend raise BlobStoreUnavailable."""

    #: The store as a URL without credentials (for logs and the CLI).
    url: str
    #: The store in a few words, fit for a client ("filesystem", "S3 bucket 'x'").
    description: str

    def put(self, name: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        """Store ``data`` under ``name`` (replacing what was there)."""
        ...

    def get(self, name: str) -> bytes | None:
        """The bytes under ``name``, or None if there are none."""
        ...

    def delete(self, names: Iterable[str]) -> None:
        """Remove the blobs (absent ones are no error)."""
        ...

    def list(self, prefix: str) -> Iterator[BlobEntry]:
        """The blobs whose name starts with ``prefix`` (a directory such as 'jobs/')."""
        ...

    def ping(self) -> None:
        """Return if the store answers and accepts writes, else raise BlobStoreUnavailable."""
        ...


@dataclass
class BlobOps:
    """Counts of one process's blob operations: (op, outcome) → n, and bytes moved each way."""

    ops: Counter[tuple[str, str]] = field(default_factory=Counter)
    bytes_written: int = 0
    bytes_read: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add(self, op: str, outcome: str, n_bytes: int = 0) -> None:
        with self._lock:
            self.ops[(op, outcome)] += 1
            if op == "put":
                self.bytes_written += n_bytes
            elif op == "get":
                self.bytes_read += n_bytes

    def snapshot(self) -> tuple[dict[tuple[str, str], int], int, int]:
        with self._lock:
            return dict(self.ops), self.bytes_written, self.bytes_read


class CountingBlobStore:
    """A blob store that counts its operations in ``ops`` (what /metrics exports)."""

    def __init__(self, inner: BlobStore) -> None:
        self.inner = inner
        self.url = inner.url
        self.description = inner.description
        self.ops = BlobOps()

    def put(self, name: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        try:
            self.inner.put(name, data, content_type)
        except BlobStoreError:
            self.ops.add("put", "error")
            raise
        self.ops.add("put", "ok", len(data))

    def get(self, name: str) -> bytes | None:
        try:
            data = self.inner.get(name)
        except BlobStoreError:
            self.ops.add("get", "error")
            raise
        self.ops.add("get", "ok" if data is not None else "missing", len(data or b""))
        return data

    def delete(self, names: Iterable[str]) -> None:
        names = list(names)
        if not names:
            return
        try:
            self.inner.delete(names)
        except BlobStoreError:
            self.ops.add("delete", "error")
            raise
        self.ops.add("delete", "ok")

    def list(self, prefix: str) -> Iterator[BlobEntry]:
        try:
            yield from self.inner.list(prefix)
        except BlobStoreError:
            self.ops.add("list", "error")
            raise
        self.ops.add("list", "ok")

    def ping(self) -> None:
        try:
            self.inner.ping()
        except BlobStoreError:
            self.ops.add("ping", "error")
            raise
        self.ops.add("ping", "ok")
