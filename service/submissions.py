"""What the job resources (``/v1/estimates``, ``/v1/tracks``) share: reading the multipart
parts of a submission (the request JSON, images), idempotency keys, the per-key cap, finding
the caller's job, and serving an artifact with its ETag."""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Callable, Sequence
from typing import Annotated, TypeVar

from fastapi import Header, Request, Response, UploadFile
from pydantic import BaseModel, ValidationError

from schemas.camera import Camera
from schemas.jobs import CREATE_EXAMPLE
from schemas.names import BUILTIN_MODEL_IDS
from schemas.settings import Settings
from service.errors import ApiError, echo, field_error, not_found, validation_failed
from service.store import (
    ActiveJobsLimitError,
    IdempotencyKeyTaken,
    JobRecord,
    JobStore,
    ModelStore,
    Reaper,
)
from service.uploads import UploadRejected, inspect_image

RequestModel = TypeVar("RequestModel", bound=BaseModel)
#: The Idempotency-Key header of a submission.
IdempotencyKey = Annotated[
    str | None, Header(alias="Idempotency-Key", description="Makes retries safe (e.g. a UUID).")
]

#: The example of a submission's `request` part in the OpenAPI document (estimates and tracks).
REQUEST_EXAMPLE = json.dumps(CREATE_EXAMPLE)
#: Retry-After of a submission refused because the key's cap of active jobs is reached, s.
ACTIVE_CAP_RETRY_AFTER_S = 15
#: Cache-Control of an artifact: its URL names one job's output, which never changes.
ARTIFACT_CACHE_CONTROL = "private, max-age=86400, immutable"
_JOB_ID = re.compile(r"^[0-9a-f]{32}$")
#: Idempotency keys: 1–255 printable ASCII characters without spaces (a UUID is typical).
_IDEMPOTENCY_KEY = re.compile(r"^[\x21-\x7e]{1,255}$")


def get_or_404(jobs: JobStore, job_id: str, settings: Settings, kind: str) -> JobRecord:
    """The caller's job of ``kind`` ('estimate', 'track'); another key's job, or one of another
    kind, is as absent as a job that never existed."""
    record = jobs.get(job_id) if _JOB_ID.match(job_id) else None
    if record is None or record.kind != kind:
        raise not_found(kind, job_id)
    return Reaper(jobs, settings.job_max_attempts).reconcile(record)


def check_idempotency_key(key: str | None) -> None:
    if key is not None and not _IDEMPOTENCY_KEY.match(key):
        raise field_error(
            422,
            ("header", "Idempotency-Key"),
            "must be 1 to 255 printable ASCII characters without spaces",
            "string_pattern_mismatch",
        )


def parse_request(
    part: str | UploadFile, max_bytes: int, model: type[RequestModel]
) -> RequestModel:
    """The ``request`` part (a form field or a file part) as ``model``; 413 / 422 naming it."""
    too_large = f"the request JSON is larger than {max_bytes} bytes"
    if isinstance(part, str):
        text = part
        if len(text.encode()) > max_bytes:
            raise field_error(413, ("body", "request"), too_large, "too_large")
    else:  # sent as a file part (curl -F request=@request.json)
        raw = part.file.read(max_bytes + 1)
        if len(raw) > max_bytes:
            raise field_error(413, ("body", "request"), too_large, "too_large")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise field_error(422, ("body", "request"), "not UTF-8 text", "unicode_error") from exc
    try:
        return model.model_validate_json(text)
    except ValidationError as exc:
        raise validation_failed(exc, ("body", "request")) from exc


def check_model(models: ModelStore, model_id: str) -> None:
    # demo-sat and demo-terrain are accepted before any worker registered them: the worker that
    # runs the job will have
    if model_id not in BUILTIN_MODEL_IDS and not models.exists(model_id):
        raise field_error(
            422,
            ("body", "request", "model_id"),
            f"no model '{model_id}' is registered (see GET /v1/models)",
            "model_not_found",
        )


def read_image(
    image: UploadFile,
    camera: Camera,
    max_bytes: int,
    max_px: int,
    loc: Sequence[str | int] = ("body", "image"),
    what: str = "the image",
) -> bytes:
    """The bytes of an uploaded image of exactly the camera's size; 413 / 422 naming ``loc``."""
    if image.size is not None and image.size > max_bytes:
        msg = f"{what} is {image.size} bytes, larger than the limit of {max_bytes} bytes"
        raise field_error(413, loc, msg, "too_large")
    data = image.file.read(max_bytes + 1)
    if len(data) > max_bytes:
        msg = f"{what} is larger than the limit of {max_bytes} bytes"
        raise field_error(413, loc, msg, "too_large")
    try:
        info = inspect_image(data, max_px)
    except UploadRejected as exc:
        msg = str(exc) if what == "the image" else f"{what}: {exc}"
        raise field_error(422, loc, msg, exc.code) from exc
    if (info.width, info.height) != (camera.width, camera.height):
        msg = (
            f"{what} is {info.width}×{info.height} px but request.camera is "
            f"{camera.width}×{camera.height} px"
        )
        raise field_error(422, loc, msg, "image_size_mismatch")
    return data


def fingerprint_of(*parts: bytes) -> str:
    """What makes two submissions the same request (for an Idempotency-Key's replay)."""
    return hashlib.sha256(b"\0".join(parts)).hexdigest()


def create_or_replay(
    create: Callable[[], JobRecord], jobs: JobStore, owner: str, key: str | None, fingerprint: str
) -> tuple[JobRecord, bool]:
    """``create()``, which claims the Idempotency-Key ``key`` (if any) as it reserves the job's
    place: (the new job, False). When an earlier use of the key has it: (that job, True); 422
    if it was used for another request, 409 while that one is still being stored.

    When the create fails, the key is given back, and the per-key cap of active jobs is
    answered 429 with a Retry-After."""
    try:
        return create(), False
    except IdempotencyKeyTaken as taken:
        return _earlier(jobs, taken.claim, fingerprint), True
    except BaseException as exc:
        if key is not None:
            jobs.release_idempotency(owner, key)
        if isinstance(exc, ActiveJobsLimitError):
            raise ApiError(
                429,
                detail=f"{exc}, the most allowed (max_active_jobs_per_key); wait for some to "
                "finish or cancel some",
                code="active_jobs_limit",
                headers={"Retry-After": str(ACTIVE_CAP_RETRY_AFTER_S)},
            ) from exc
        raise


def _earlier(jobs: JobStore, claim: dict[str, str], fingerprint: str) -> JobRecord:
    """The job of an Idempotency-Key's earlier use (``claim``)."""
    if claim["fingerprint"] != fingerprint:
        raise field_error(
            422,
            ("header", "Idempotency-Key"),
            "this key was already used with a different request; use a new key per request",
            "idempotency_key_reused",
        )
    record = jobs.get(claim["job_id"])
    if record is None:
        raise ApiError(
            409,
            detail="a request with this Idempotency-Key is still being processed; retry",
            code="idempotency_in_progress",
        )
    return record


def accepted(resource: BaseModel, location: str, replayed: bool = False) -> Response:
    """The 202 of a submission: the job ``resource`` serialised as FastAPI serialises the
    route's ``response_model`` (the same bytes), with ``Location`` (and ``Idempotent-Replayed``
    for an Idempotency-Key's replay).

    Returned as a Response, so FastAPI skips its own pass: for a sync route it validates the
    returned model once more, in a second thread-pool hop, before serialising it (~0.1 ms of
    CPU per submission, which a burst of them queues behind). The model is valid already."""
    response = Response(
        resource.model_dump_json(by_alias=True), status_code=202, media_type="application/json"
    )
    response.headers["Location"] = location
    if replayed:
        response.headers["Idempotent-Replayed"] = "true"
    return response


def cancel(jobs: JobStore, record: JobRecord, response: Response) -> JobRecord:
    """Cancel a queued job (200) or ask a running one to stop (202); 409 once it has ended."""
    after = None if record.terminal else jobs.request_cancel(record.id)
    if after is None or after.status in ("succeeded", "failed"):
        status = (after or record).status
        raise ApiError(
            409,
            detail=f"{record.kind} '{record.id}' has already ended ({status})",
            code="job_ended",
        )
    if after.status != "cancelled":
        response.status_code = 202
    return after


def _etag_matches(if_none_match: str | None, etag: str) -> bool:
    if if_none_match is None:
        return False
    tags = {t.strip().removeprefix("W/") for t in if_none_match.split(",")}
    return "*" in tags or etag in tags


def artifact_response(
    jobs: JobStore, record: JobRecord, stem: str, request: Request, media_type: str
) -> Response:
    """Artifact ``stem`` of a job, with its ETag (304 on a matching If-None-Match); 404 if the
    job has no such artifact."""
    headers = {"Cache-Control": ARTIFACT_CACHE_CONTROL}
    known = jobs.artifact_etag(record, stem)
    if known is not None and _etag_matches(request.headers.get("if-none-match"), f'"{known}"'):
        return Response(status_code=304, headers=headers | {"ETag": f'"{known}"'})
    data = jobs.get_artifact(record, stem)
    if data is None:
        names = ", ".join(record.artifacts) or "none yet"
        raise ApiError(
            404,
            detail=f"{record.kind} '{record.id}' has no artifact '{echo(stem)}' "
            f"(artifacts: {names})",
            code="not_found",
        )
    etag = f'"{known or hashlib.sha256(data).hexdigest()}"'
    if _etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers | {"ETag": etag})
    return Response(data, media_type=media_type, headers=headers | {"ETag": etag})
