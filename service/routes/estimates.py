"""``/v1/estimates``: submit, list, show, stream and cancel pose-estimate jobs."""

from __future__ import annotations

import hashlib
import logging
import re
import secrets
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, Header, Query, Request, Response, UploadFile
from fastapi.responses import StreamingResponse
from pydantic import ValidationError

from schemas.jobs import EstimateCreate, EstimateList, EstimatePublic, JobStatus
from schemas.models import MODEL_ID_PATTERN
from schemas.names import BUILTIN_MODEL_IDS
from schemas.settings import Settings
from service.auth import PrincipalDep
from service.deps import AsyncRedisDep, JobStoreDep, ModelStoreDep, Multipart, SettingsDep
from service.errors import ApiError, echo, field_error, not_found, validation_failed
from service.events import job_events
from service.resources import estimate_location, estimate_public, estimate_summary
from service.store import ActiveJobsLimitError, JobRecord, JobStore, ModelStore, Reaper
from service.uploads import UploadRejected, inspect_image

router = APIRouter(prefix="/v1/estimates", tags=["estimates"])
log = logging.getLogger(__name__)

#: Largest page of a listing.
MAX_PAGE_SIZE = 100
#: Retry-After of a submission refused because the key's cap of active jobs is reached, s.
ACTIVE_CAP_RETRY_AFTER_S = 15
_JOB_ID = re.compile(r"^[0-9a-f]{32}$")
#: Idempotency keys: 1–255 printable ASCII characters without spaces (a UUID is typical).
_IDEMPOTENCY_KEY = re.compile(r"^[\x21-\x7e]{1,255}$")

_REQUEST_EXAMPLE = (
    '{"model_id": "demo-sat", "camera": {"width": 512, "height": 512, "fx": 560, "fy": 560, '
    '"cx": 255.5, "cy": 255.5}, "initial_pose": {"t": [0.3, -0.2, 14.0], '
    '"quaternion": [0.57, 0.66, 0.40, 0.20]}}'
)


def _get_or_404(jobs: JobStore, job_id: str, settings: Settings) -> JobRecord:
    """The caller's job (another key's job is as absent as a job that never existed)."""
    record = jobs.get(job_id) if _JOB_ID.match(job_id) else None
    if record is None:
        raise not_found("estimate", job_id)
    return Reaper(jobs, settings.job_max_attempts).reconcile(record)


def _parse_request(part: str | UploadFile, max_bytes: int) -> EstimateCreate:
    if isinstance(part, str):
        text = part
        if len(text.encode()) > max_bytes:
            msg = f"the request JSON is larger than {max_bytes} bytes"
            raise field_error(413, ("body", "request"), msg, "too_large")
    else:  # sent as a file part (curl -F request=@request.json)
        raw = part.file.read(max_bytes + 1)
        if len(raw) > max_bytes:
            msg = f"the request JSON is larger than {max_bytes} bytes"
            raise field_error(413, ("body", "request"), msg, "too_large")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise field_error(422, ("body", "request"), "not UTF-8 text", "unicode_error") from exc
    try:
        return EstimateCreate.model_validate_json(text)
    except ValidationError as exc:
        raise validation_failed(exc, ("body", "request")) from exc


def _check_model(models: ModelStore, model_id: str) -> None:
    # demo-sat and demo-terrain are accepted before any worker registered them: the worker that
    # runs the job will have
    if model_id not in BUILTIN_MODEL_IDS and not models.exists(model_id):
        raise field_error(
            422,
            ("body", "request", "model_id"),
            f"no model '{model_id}' is registered (see GET /v1/models)",
            "model_not_found",
        )


def _read_image(image: UploadFile, body: EstimateCreate, max_bytes: int, max_px: int) -> bytes:
    if image.size is not None and image.size > max_bytes:
        msg = f"the image is {image.size} bytes, larger than the limit of {max_bytes} bytes"
        raise field_error(413, ("body", "image"), msg, "too_large")
    data = image.file.read(max_bytes + 1)
    if len(data) > max_bytes:
        msg = f"the image is larger than the limit of {max_bytes} bytes"
        raise field_error(413, ("body", "image"), msg, "too_large")
    try:
        info = inspect_image(data, max_px)
    except UploadRejected as exc:
        raise field_error(422, ("body", "image"), str(exc), exc.code) from exc
    cam = body.camera
    if (info.width, info.height) != (cam.width, cam.height):
        msg = (
            f"the image is {info.width}×{info.height} px but request.camera is "
            f"{cam.width}×{cam.height} px"
        )
        raise field_error(422, ("body", "image"), msg, "image_size_mismatch")
    return data


def _replay(earlier: dict[str, str], fingerprint: str, jobs: JobStore) -> JobRecord:
    if earlier["fingerprint"] != fingerprint:
        raise field_error(
            422,
            ("header", "Idempotency-Key"),
            "this key was already used with a different request; use a new key per request",
            "idempotency_key_reused",
        )
    record = jobs.get(earlier["job_id"])
    if record is None:
        raise ApiError(
            409,
            detail="a request with this Idempotency-Key is still being processed; retry",
            code="idempotency_in_progress",
        )
    return record


@router.post(
    "",
    status_code=202,
    response_model=EstimatePublic,
    summary="Submit a pose estimate",
    dependencies=[Multipart],
    description="Multipart: `image` (PNG, JPEG or TIFF of exactly the camera's size) and "
    "`request` (JSON: the CLI's REQUEST.json plus `model_id`). Answers 202 with the job and "
    "`Location: /v1/estimates/{id}`. With an `Idempotency-Key` header, a retry of the same "
    "request returns the first job (header `Idempotent-Replayed: true`) instead of a new one.",
    responses={
        409: {"description": "The same Idempotency-Key is being processed right now."},
        413: {"description": "The image is larger than max_image_bytes."},
        415: {"description": "The body is not multipart/form-data."},
        422: {"description": "A field is invalid; `detail[].loc` names it."},
        429: {
            "description": "The key submits too fast, or has max_active_jobs_per_key jobs "
            "queued or running; `Retry-After` says when to try again."
        },
    },
)
def create_estimate(
    image: Annotated[UploadFile, File(description="Reference image: PNG, JPEG or TIFF.")],
    request: Annotated[
        str | UploadFile,
        Form(
            description="JSON: EstimateCreate (REQUEST.json + model_id), as a form field or a "
            "file part.",
            examples=[_REQUEST_EXAMPLE],
        ),
    ],
    jobs: JobStoreDep,
    models: ModelStoreDep,
    settings: SettingsDep,
    principal: PrincipalDep,
    response: Response,
    idempotency_key: Annotated[
        str | None,
        Header(alias="Idempotency-Key", description="Makes retries safe (e.g. a UUID)."),
    ] = None,
) -> EstimatePublic:
    if idempotency_key is not None and not _IDEMPOTENCY_KEY.match(idempotency_key):
        raise field_error(
            422,
            ("header", "Idempotency-Key"),
            "must be 1 to 255 printable ASCII characters without spaces",
            "string_pattern_mismatch",
        )
    body = _parse_request(request, settings.max_request_json_bytes)
    _check_model(models, body.model_id)
    data = _read_image(image, body, settings.max_image_bytes, settings.max_image_pixels)
    engine_request = body.engine_request()
    request_json = engine_request.model_dump_json(exclude_unset=True, by_alias=True)
    fingerprint = hashlib.sha256(
        b"\0".join([body.model_id.encode(), request_json.encode(), data])
    ).hexdigest()
    job_id = secrets.token_hex(16)  # 128 random bits: ids cannot be guessed
    owner = principal.name
    if idempotency_key is not None:
        earlier = jobs.claim_idempotency(owner, idempotency_key, job_id, fingerprint)
        if earlier is not None:
            record = _replay(earlier, fingerprint, jobs)
            response.headers["Location"] = estimate_location(record.id)
            response.headers["Idempotent-Replayed"] = "true"
            return estimate_public(Reaper(jobs, settings.job_max_attempts).reconcile(record))
    max_iterations = engine_request.options.resolved().max_iterations
    try:
        record = jobs.create(
            job_id,
            body.model_id,
            request_json,
            max_iterations,
            data,
            fingerprint,
            owner=owner,
            timeout_s=settings.job_timeout_s,
            max_active=settings.max_active_jobs_per_key,
        )
    except BaseException as exc:
        if idempotency_key is not None:
            jobs.release_idempotency(owner, idempotency_key)
        if isinstance(exc, ActiveJobsLimitError):
            raise ApiError(
                429,
                detail=f"{exc}, the most allowed (max_active_jobs_per_key); wait for some to "
                "finish or cancel some",
                code="active_jobs_limit",
                headers={"Retry-After": str(ACTIVE_CAP_RETRY_AFTER_S)},
            ) from exc
        raise
    log.info(
        "estimate %s queued for '%s' (model %s)",
        job_id,
        owner,
        body.model_id,
        extra={"job_id": job_id, "owner": owner, "model_id": body.model_id},
    )
    response.headers["Location"] = estimate_location(job_id)
    return estimate_public(record)


@router.get(
    "",
    response_model=EstimateList,
    summary="List jobs, newest first (paged, filtered by status and model)",
)
def list_estimates(
    jobs: JobStoreDep,
    settings: SettingsDep,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE_SIZE, description="Page size.")] = 20,
    cursor: Annotated[
        str | None,
        Query(pattern=r"^[0-9]{1,18}$", description="`next_cursor` of the previous page."),
    ] = None,
    status: Annotated[
        list[JobStatus] | None,
        Query(description="Only jobs in these states (repeat for several)."),
    ] = None,
    model_id: Annotated[
        str | None, Query(pattern=MODEL_ID_PATTERN, description="Only jobs of this model.")
    ] = None,
) -> EstimateList:
    reaper = Reaper(jobs, settings.job_max_attempts)
    wanted = set(status) if status else None

    def where(record: JobRecord) -> bool:
        if model_id is not None and record.model_id != model_id:
            return False
        return wanted is None or reaper.reconcile(record).status in wanted

    filtered = wanted is not None or model_id is not None
    records, next_seq = jobs.list_page(
        limit, int(cursor) if cursor is not None else None, where if filtered else None
    )
    items = [estimate_summary(reaper.reconcile(record)) for record in records]
    return EstimateList(items=items, next_cursor=str(next_seq) if next_seq is not None else None)


@router.get(
    "/{job_id}",
    response_model=EstimatePublic,
    summary="Show a job: status, progress, result, error, artifact URLs",
    responses={404: {"description": "No such job (or it expired)."}},
)
def get_estimate(job_id: str, jobs: JobStoreDep, settings: SettingsDep) -> EstimatePublic:
    return estimate_public(_get_or_404(jobs, job_id, settings))


@router.delete(
    "/{job_id}",
    response_model=EstimatePublic,
    summary="Cancel a queued or running job",
    description="A queued job is cancelled at once (200). A running job is asked to stop (202, "
    "`cancel_requested: true`); it turns `cancelled` before its next render.",
    responses={
        202: {"model": EstimatePublic, "description": "Running: asked to stop."},
        404: {"description": "No such job."},
        409: {"description": "The job has already ended."},
    },
)
def cancel_estimate(
    job_id: str, jobs: JobStoreDep, settings: SettingsDep, response: Response
) -> EstimatePublic:
    record = _get_or_404(jobs, job_id, settings)
    after = None if record.terminal else jobs.request_cancel(job_id)
    if after is None or after.status in ("succeeded", "failed"):
        status = (after or record).status
        raise ApiError(
            409, detail=f"estimate '{job_id}' has already ended ({status})", code="job_ended"
        )
    if after.status != "cancelled":
        response.status_code = 202
    return estimate_public(after)


#: Cache-Control of an artifact: its URL names one job's output, which never changes.
ARTIFACT_CACHE_CONTROL = "private, max-age=86400, immutable"


def _etag_matches(if_none_match: str | None, etag: str) -> bool:
    if if_none_match is None:
        return False
    tags = {t.strip().removeprefix("W/") for t in if_none_match.split(",")}
    return "*" in tags or etag in tags


@router.get(
    "/{job_id}/artifacts/{name}",
    response_class=Response,
    summary="Download a PNG artifact of a finished job",
    description="Answers with an `ETag` (the PNG's SHA-256); `If-None-Match` with it answers "
    "304. An artifact whose job has expired (after the retention) is 404.",
    responses={
        200: {"content": {"image/png": {}}},
        304: {"description": "Not modified (If-None-Match)."},
        404: {"description": "No such artifact (or it expired)."},
        503: {"description": "The blob store is unavailable."},
    },
)
def get_artifact(
    job_id: str, name: str, request: Request, jobs: JobStoreDep, settings: SettingsDep
) -> Response:
    record = _get_or_404(jobs, job_id, settings)
    stem = name.removesuffix(".png")
    headers = {"Cache-Control": ARTIFACT_CACHE_CONTROL}
    known = jobs.artifact_etag(record, stem)
    if known is not None and _etag_matches(request.headers.get("if-none-match"), f'"{known}"'):
        return Response(status_code=304, headers=headers | {"ETag": f'"{known}"'})
    png = jobs.get_artifact(record, stem)
    if png is None:
        names = ", ".join(record.artifacts) or "none yet"
        raise ApiError(
            404,
            detail=f"estimate '{job_id}' has no artifact '{echo(name)}' (artifacts: {names})",
            code="not_found",
        )
    etag = f'"{known or hashlib.sha256(png).hexdigest()}"'
    if _etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers | {"ETag": etag})
    return Response(png, media_type="image/png", headers=headers | {"ETag": etag})


_EVENTS_DOC: dict[int | str, dict[str, Any]] = {
    200: {
        "content": {"text/event-stream": {}},
        "description": "Events `status`, `progress` (after every iteration) and a final `end` "
        "carrying the job resource; the stream closes after `end`.",
    },
    404: {"description": "No such job."},
}


@router.get(
    "/{job_id}/events",
    response_class=StreamingResponse,
    summary="Stream a job's progress (Server-Sent Events)",
    responses=_EVENTS_DOC,
)
def stream_events(
    job_id: str,
    jobs: JobStoreDep,
    aredis: AsyncRedisDep,
    settings: SettingsDep,
    last_event_id: Annotated[
        str | None,
        Header(
            alias="Last-Event-ID",
            description="Id of the last event received (an iteration number): a reconnecting "
            "stream resumes after it.",
        ),
    ] = None,
) -> StreamingResponse:
    _get_or_404(jobs, job_id, settings)
    after = int(last_event_id) if last_event_id and last_event_id.isdigit() else 0
    return StreamingResponse(
        job_events(
            jobs, aredis, job_id, settings.sse_keepalive_s, settings.job_max_attempts, after
        ),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
