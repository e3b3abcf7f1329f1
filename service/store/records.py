"""A job as stored in its Redis hash, decoded: strings and JSON, no behaviour.

The hash holds the job's metadata and result; its bytes (image, artifacts) are in the blob store
(``service.store.blobs``) under the names it records. The result JSON, most of a finished job's
hash (its iteration history, ~0.7 kB per iteration), is kept zlib-compressed in ``result_z``
(about a third of the size); records of an older deployment have it plain in ``result``.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from schemas.jobs import TERMINAL_STATUSES, Progress

#: Hash field of the zlib-compressed result JSON (bytes); ``result`` is the older, plain one.
RESULT_Z_FIELD = "result_z"
#: zlib level of the result: the best ratio, and still well under a millisecond for a result.
RESULT_ZLIB_LEVEL = 9


def utc_now() -> str:
    """Current time, ISO 8601 UTC (the stored timestamp format)."""
    return datetime.now(UTC).isoformat()


def text(value: bytes | str | None) -> str | None:
    return value.decode() if isinstance(value, bytes) else value


def pack_result(result_json: str) -> bytes:
    """The result JSON as stored in ``RESULT_Z_FIELD``."""
    return zlib.compress(result_json.encode(), RESULT_ZLIB_LEVEL)


def unpack_result(packed: bytes) -> str:
    """The result JSON back from ``RESULT_Z_FIELD``."""
    return zlib.decompress(packed).decode()


@dataclass
class JobRecord:
    """A job (an estimate or a track). ``attempts`` counts the starts by a worker; ``rq_id``
    names the RQ job of the current enqueueing; ``lost`` lists the attempts whose worker died
    (for operators)."""

    id: str
    status: str
    model_id: str
    created_at: str
    request: str
    seq: int
    max_iterations: int
    owner: str = "anonymous"
    attempts: int = 0
    rq_id: str = ""
    timeout_s: int = 0
    started_at: str | None = None
    finished_at: str | None = None
    progress: dict[str, Any] | None = None
    result: str | None = None
    error: dict[str, str] | None = None
    artifacts: list[str] = field(default_factory=list)
    #: Where the bytes are: the image's blob name, and per artifact {"blob", "sha256",
    #: "bytes"}; empty for a job of an older deployment, whose bytes are still in Redis.
    image_blob: str | None = None
    artifact_blobs: dict[str, dict[str, Any]] = field(default_factory=dict)
    worker: str | None = None
    cancel_requested: bool = False
    fingerprint: str = ""
    lost: list[dict[str, Any]] = field(default_factory=list)
    #: What the job runs: 'estimate' (one image) or 'track' (a sequence of frames).
    kind: str = "estimate"
    #: A job of several inputs (a track): per input {"name": file name, "blob": blob name}.
    inputs: list[dict[str, str]] = field(default_factory=list)

    @classmethod
    def from_hash(cls, raw: dict[bytes, bytes]) -> JobRecord:
        packed = raw.get(RESULT_Z_FIELD.encode())
        h = {k.decode(): v.decode() for k, v in raw.items() if k != RESULT_Z_FIELD.encode()}
        return cls(
            id=h["id"],
            status=h["status"],
            model_id=h["model_id"],
            created_at=h["created_at"],
            request=h["request"],
            seq=int(h["seq"]),
            max_iterations=int(h["max_iterations"]),
            owner=h.get("owner") or "anonymous",
            attempts=int(h.get("attempts") or 0),
            rq_id=h.get("rq_id", ""),
            timeout_s=int(h.get("timeout_s") or 0),
            started_at=h.get("started_at") or None,
            finished_at=h.get("finished_at") or None,
            progress=json.loads(h["progress"]) if h.get("progress") else None,
            result=unpack_result(packed) if packed else h.get("result") or None,
            error=json.loads(h["error"]) if h.get("error") else None,
            artifacts=json.loads(h.get("artifacts") or "[]"),
            image_blob=h.get("image_blob") or None,
            artifact_blobs=json.loads(h.get("artifact_blobs") or "{}"),
            worker=h.get("worker") or None,
            cancel_requested=h.get("cancel_requested") == "1",
            fingerprint=h.get("fingerprint", ""),
            lost=json.loads(h.get("lost") or "[]"),
            kind=h.get("kind") or "estimate",
            inputs=json.loads(h.get("inputs") or "[]"),
        )

    def queued_hash(self) -> dict[str, str]:
        """The Redis hash a new queued job is stored as (``from_hash`` reads it back; the
        fields that are still unset are left out)."""
        return {
            "id": self.id,
            "status": self.status,
            "model_id": self.model_id,
            "created_at": self.created_at,
            "request": self.request,
            "seq": str(self.seq),
            "max_iterations": str(self.max_iterations),
            "owner": self.owner,
            "attempts": str(self.attempts),
            "rq_id": self.rq_id,
            "timeout_s": str(self.timeout_s),
            "fingerprint": self.fingerprint,
            "kind": self.kind,
            **({"image_blob": self.image_blob} if self.image_blob else {}),
            **({"inputs": json.dumps(self.inputs)} if self.inputs else {}),
        }

    @property
    def terminal(self) -> bool:
        return self.status in TERMINAL_STATUSES

    def progress_model(self) -> Progress:
        if self.progress:
            return Progress.model_validate(self.progress)
        return Progress(max_iterations=self.max_iterations)
