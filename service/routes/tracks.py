"""``/v1/tracks``: submit, show, stream and cancel tracking jobs (an image sequence, in order),
and fetch their track.json, CSV and PNG artifacts. A track runs as a job of the estimate
queue, with the same leases, cancel, idempotency and artifacts as an estimate."""

from __future__ import annotations

import logging
import secrets
from pathlib import PurePath
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, Header, Request, Response, UploadFile
from fastapi.responses import StreamingResponse

from schemas.settings import Settings
from schemas.track_jobs import TRACK_KIND, TrackCreate, TrackProgressEvent, TrackPublic
from service.auth import PrincipalDep
from service.deps import AsyncRedisDep, JobStoreDep, ModelStoreDep, Multipart, SettingsDep
from service.errors import ApiError, field_error
from service.events import EventShape, event_stream
from service.resources import track_location, track_public, track_state
from service.store import JobRecord, JobStore, Reaper
from service.store.blobs import artifact_media_type
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

router = APIRouter(prefix="/v1/tracks", tags=["tracks"])
log = logging.getLogger(__name__)

#: A track's job timeout is the settings' job_timeout_s plus this much per frame, s.
TRACK_TIMEOUT_PER_FRAME_S = 30
#: Longest frame file name kept (the rest of a longer one is cut), characters.
FRAME_NAME_MAX_CHARS = 200


def _backlog(record: JobRecord, after: int) -> list[tuple[dict[str, Any], int]]:
    state = track_state(record)
    return [
        (
            TrackProgressEvent(
                frames_done=frame.index + 1, frames_total=state.frames_total, frame=frame
            ).model_dump(mode="json"),
            frame.index + 1,
        )
        for frame in state.frames
        if frame.index + 1 > after
    ]


#: The stream of a track: one progress event per frame, carrying it.
TRACK_EVENTS = EventShape(
    public=lambda record: track_public(record).model_dump_json(by_alias=True),
    backlog=_backlog,
    position=lambda data: int(data["frames_done"]),
)


def _get_or_404(jobs: JobStore, job_id: str, settings: Settings) -> JobRecord:
    return get_or_404(jobs, job_id, settings, TRACK_KIND)


def _frame_name(upload: UploadFile, index: int) -> str:
    name = PurePath(upload.filename or "").name[:FRAME_NAME_MAX_CHARS]
    return name or f"frame_{index:05d}.png"


def _read_frames(
    frames: list[UploadFile], body: TrackCreate, settings: Settings
) -> list[tuple[str, bytes]]:
    """The frames (name, bytes) in order; 413 over the count or the total bytes, 413 / 422
    naming the frame that cannot be used, 422 when the truth is not one pose per frame."""
    if len(frames) > settings.max_track_frames:
        msg = f"{len(frames)} frames, more than the limit of {settings.max_track_frames}"
        raise field_error(413, ("body", "frames"), msg, "too_many_frames")
    total = sum(f.size or 0 for f in frames)
    if total > settings.max_track_bytes:
        msg = f"the frames are {total} bytes, more than the limit of {settings.max_track_bytes}"
        raise field_error(413, ("body", "frames"), msg, "too_large")
    truth = body.ground_truth
    if truth is not None and len(truth) != len(frames):
        msg = f"{len(truth)} poses for {len(frames)} frames (need one per frame)"
        raise field_error(422, ("body", "request", "ground_truth"), msg, "length_mismatch")
    out = []
    for k, upload in enumerate(frames):
        name = _frame_name(upload, k)
        data = read_image(
            upload,
            body.camera,
            settings.max_image_bytes,
            settings.max_image_pixels,
            ("body", "frames", k),
            f"frame {k} ({name})",
        )
        out.append((name, data))
    return out


@router.post(
    "",
    status_code=202,
    response_model=TrackPublic,
    summary="Submit an image sequence to track",
    dependencies=[Multipart],
    description="Multipart: `frames` (repeated, in order: PNG, JPEG or TIFF files of exactly "
    "the camera's size) and `request` (JSON: the REQUEST.json of `proxpose track` plus "
    "`model_id`; `initial_pose` is the first frame's guess, `ground_truth` optionally one pose "
    "per frame). At most max_track_frames frames of max_track_bytes in all. Answers 202 with "
    "the job and `Location: /v1/tracks/{id}`; an `Idempotency-Key` makes retries safe as for "
    "estimates.",
    responses={
        409: {"description": "The same Idempotency-Key is being processed right now."},
        413: {
            "description": "Too many frames (max_track_frames), frames too large in all "
            "(max_track_bytes), or one over max_image_bytes; `errors[].loc` names which."
        },
        415: {"description": "The body is not multipart/form-data."},
        422: {"description": "A field or a frame is invalid; `errors[].loc` names it."},
        429: {
            "description": "The key submits too fast, or has max_active_jobs_per_key jobs "
            "queued or running; `Retry-After` says when to try again."
        },
    },
)
def create_track(
    frames: Annotated[
        list[UploadFile], File(description="The frames in order (repeat the field).")
    ],
    request: Annotated[
        str | UploadFile,
        Form(
            description="JSON: TrackCreate (REQUEST.json + model_id), as a form field or a "
            "file part.",
            examples=[REQUEST_EXAMPLE],
        ),
    ],
    jobs: JobStoreDep,
    models: ModelStoreDep,
    settings: SettingsDep,
    principal: PrincipalDep,
    idempotency_key: IdempotencyKey = None,
) -> Response:
    check_idempotency_key(idempotency_key)
    body = parse_request(request, settings.max_request_json_bytes, TrackCreate)
    check_model(models, body.model_id)
    named = _read_frames(frames, body, settings)
    request_json = body.engine_request().model_dump_json(exclude_unset=True, by_alias=True)
    fingerprint = fingerprint_of(
        body.model_id.encode(), request_json.encode(), *(n.encode() + b"/" + d for n, d in named)
    )
    job_id = secrets.token_hex(16)
    owner = principal.name
    timeout_s = settings.job_timeout_s + TRACK_TIMEOUT_PER_FRAME_S * len(named)
    record, replayed = create_or_replay(
        lambda: jobs.create_track(
            job_id,
            body.model_id,
            request_json,
            named,
            fingerprint,
            owner=owner,
            timeout_s=timeout_s,
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
        return accepted(track_public(record), track_location(record.id), replayed=True)
    log.info(
        "track %s queued for '%s' (model %s, %d frames)",
        *(job_id, owner, body.model_id, len(named)),
        extra={"job_id": job_id, "owner": owner, "model_id": body.model_id},
    )
    return accepted(track_public(record), track_location(job_id))


@router.get(
    "/{job_id}",
    response_model=TrackPublic,
    summary="Show a track: status, the frames so far, result, artifact URLs",
    responses={404: {"description": "No such track (or it expired)."}},
)
def get_track(job_id: str, jobs: JobStoreDep, settings: SettingsDep) -> TrackPublic:
    return track_public(_get_or_404(jobs, job_id, settings))


@router.delete(
    "/{job_id}",
    response_model=TrackPublic,
    summary="Cancel a queued or running track",
    description="A queued track is cancelled at once (200). A running one is asked to stop "
    "(202, `cancel_requested: true`); it turns `cancelled` before its next render.",
    responses={
        202: {"model": TrackPublic, "description": "Running: asked to stop."},
        404: {"description": "No such track."},
        409: {"description": "The track has already ended."},
    },
)
def cancel_track(
    job_id: str, jobs: JobStoreDep, settings: SettingsDep, response: Response
) -> TrackPublic:
    return track_public(cancel(jobs, _get_or_404(jobs, job_id, settings), response))


@router.get(
    "/{job_id}/track.json",
    response_class=Response,
    summary="Download the track.json of a succeeded track",
    responses={
        200: {"content": {"application/json": {}}},
        404: {"description": "No such track, or it has no result (yet)."},
    },
)
def get_track_json(job_id: str, jobs: JobStoreDep, settings: SettingsDep) -> Response:
    record = _get_or_404(jobs, job_id, settings)
    if not record.result:
        raise ApiError(
            404, detail=f"track '{job_id}' has no result ({record.status})", code="not_found"
        )
    disposition = f'attachment; filename="track-{job_id[:8]}.json"'
    return Response(
        record.result, media_type="application/json", headers={"Content-Disposition": disposition}
    )


@router.get(
    "/{job_id}/artifacts/{name}",
    response_class=Response,
    summary="Download an artifact of a succeeded track (PNG or CSV)",
    description="`trajectory.png`, `track.csv`, `overlay_<k>.png`; with an `ETag` "
    "(`If-None-Match` answers 304).",
    responses={
        200: {"content": {"image/png": {}, "text/csv": {}}},
        304: {"description": "Not modified (If-None-Match)."},
        404: {"description": "No such artifact (or it expired)."},
        503: {"description": "The blob store is unavailable."},
    },
)
def get_track_artifact(
    job_id: str, name: str, request: Request, jobs: JobStoreDep, settings: SettingsDep
) -> Response:
    record = _get_or_404(jobs, job_id, settings)
    stem = name.removesuffix(".png")
    return artifact_response(jobs, record, stem, request, artifact_media_type(stem))


@router.get(
    "/{job_id}/events",
    response_class=StreamingResponse,
    summary="Stream a track's progress, frame by frame (Server-Sent Events)",
    responses={
        200: {
            "content": {"text/event-stream": {}},
            "description": "Events `status`, `progress` (after every frame, carrying it; the "
            "event id is the frames done) and a final `end` carrying the track resource.",
        },
        404: {"description": "No such track."},
    },
)
def stream_track_events(
    job_id: str,
    jobs: JobStoreDep,
    aredis: AsyncRedisDep,
    settings: SettingsDep,
    last_event_id: Annotated[
        str | None,
        Header(
            alias="Last-Event-ID",
            description="Id of the last event received (frames done): a reconnecting stream "
            "resumes after it.",
        ),
    ] = None,
) -> StreamingResponse:
    _get_or_404(jobs, job_id, settings)
    return event_stream(jobs, aredis, job_id, settings, last_event_id, TRACK_EVENTS)
