"""``/v1/estimates``: submit, list, show, stream and cancel pose-estimate jobs."""

from __future__ import annotations

import logging
import secrets
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, Header, Query, Request, Response, UploadFile
from fastapi.responses import StreamingResponse

from schemas.jobs import EstimateCreate, EstimateList, EstimatePublic, JobStatus
from schemas.models import MODEL_ID_PATTERN
from schemas.settings import Settings
from service.deps import (
    AsyncRedisDep,
    Caller,
    CallerDep,
    JobStoreDep,
    Multipart,
    SettingsDep,
    caller_on,
)
from service.events import event_stream
from service.inline import INLINE_MAX_IMAGE_BYTES, InlineSubmissions
from service.resources import estimate_location, estimate_public, estimate_summary
from service.store import JobRecord, JobStore, Reaper
from service.submissions import (
    REQUEST_EXAMPLE,
    IdempotencyKey,
    accepted,
    artifact_response,
    cancel,
    check_idempotency_key,
    check_model,
    create_or_replay,
    fingerprint_of,
    get_or_404,
    parse_request,
    read_image,
)

router = APIRouter(prefix="/v1/estimates", tags=["estimates"])
log = logging.getLogger(__name__)

#: Largest page of a listing.
MAX_PAGE_SIZE = 100


def _get_or_404(jobs: JobStore, job_id: str, settings: Settings) -> JobRecord:
    return get_or_404(jobs, job_id, settings, "estimate")


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
async def create_estimate(
    image: Annotated[UploadFile, File(description="Reference image: PNG, JPEG or TIFF.")],
    request: Annotated[
        str | UploadFile,
        Form(
            description="JSON: EstimateCreate (REQUEST.json + model_id), as a form field or a "
            "file part.",
            examples=[REQUEST_EXAMPLE],
        ),
    ],
    caller: CallerDep,
    http: Request,
    idempotency_key: IdempotencyKey = None,
) -> Response:
    # on the event loop when the submission is small and Redis quick (service/inline.py)
    inline: InlineSubmissions = http.app.state.inline
    size = image.size if image.size is not None else INLINE_MAX_IMAGE_BYTES + 1
    return await inline.run(
        size,
        lambda r: _create_estimate(image, request, caller_on(http, caller, r), idempotency_key),
        lambda: _create_estimate(image, request, caller, idempotency_key),
    )


def _create_estimate(
    image: UploadFile, request: str | UploadFile, caller: Caller, idempotency_key: str | None
) -> Response:
    settings, jobs = caller.settings, caller.jobs
    check_idempotency_key(idempotency_key)
    body = parse_request(request, settings.max_request_json_bytes, EstimateCreate)
    check_model(caller.models, body.model_id)
    data = read_image(image, body.camera, settings.max_image_bytes, settings.max_image_pixels)
    engine_request = body.engine_request()
    request_json = engine_request.model_dump_json(exclude_unset=True, by_alias=True)
    fingerprint = fingerprint_of(body.model_id.encode(), request_json.encode(), data)
    job_id = secrets.token_hex(16)  # 128 random bits: ids cannot be guessed
    owner = caller.principal.name
    max_iterations = engine_request.options.resolved().max_iterations
    record, replayed = create_or_replay(
        lambda: jobs.create(
            job_id,
            body.model_id,
            request_json,
            max_iterations,
            data,
            fingerprint,
            owner=owner,
            timeout_s=settings.job_timeout_s,
            max_active=settings.max_active_jobs_per_key,
            idempotency_key=idempotency_key,
        ),
        jobs,
        owner,
        idempotency_key,
        fingerprint,
    )
    if replayed:
        record = Reaper(jobs, settings.job_max_attempts).reconcile(record)
        return accepted(estimate_public(record), estimate_location(record.id), replayed=True)
    log.info(
        "estimate %s queued for '%s' (model %s)",
        job_id,
        owner,
        body.model_id,
        extra={"job_id": job_id, "owner": owner, "model_id": body.model_id},
    )
    return accepted(estimate_public(record), estimate_location(job_id))


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
    return estimate_public(cancel(jobs, _get_or_404(jobs, job_id, settings), response))


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
    return artifact_response(jobs, record, name.removesuffix(".png"), request, "image/png")


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
    return event_stream(jobs, aredis, job_id, settings, last_event_id)
