"""Stored job records → the public resources (URLs are paths relative to the API root)."""

from __future__ import annotations

import json
import math
from typing import Any

from schemas.estimate import EstimateResult
from schemas.jobs import EstimateOutcome, EstimatePublic, EstimateSummary, JobError
from schemas.track import TrackResult
from schemas.track_jobs import TrackProgress, TrackPublic, TrackState
from service.store import JobRecord

ESTIMATES_PATH = "/v1/estimates"


def estimate_location(job_id: str) -> str:
    return f"{ESTIMATES_PATH}/{job_id}"


def _result(record: JobRecord) -> EstimateResult | None:
    return EstimateResult.model_validate_json(record.result) if record.result else None


def estimate_outcome(result: EstimateResult) -> EstimateOutcome:
    """The listing's figures: how far the estimate moved from the initial guess.

    The rotation is the angle of R₀ᵀR, 2·arccos|⟨q₀, q⟩| for unit quaternions.
    """
    q0, q = result.initial_pose.quaternion, result.pose.quaternion
    cos_half = min(1.0, abs(sum(a * b for a, b in zip(q0, q, strict=True))))
    t0, t = result.initial_pose.t, result.pose.t
    return EstimateOutcome(
        converged=result.converged,
        reason=result.reason,
        rotation_change_deg=math.degrees(2.0 * math.acos(cos_half)),
        translation_change=math.dist(t0, t),
    )


def job_fields(record: JobRecord) -> dict[str, Any]:
    """The fields of JobSummary, which every job resource has."""
    return {
        "id": record.id,
        "status": record.status,
        "model_id": record.model_id,
        "created_at": record.created_at,
        "started_at": record.started_at,
        "finished_at": record.finished_at,
        "error": JobError.model_validate(record.error) if record.error else None,
        "cancel_requested": record.cancel_requested,
        "attempts": record.attempts,
    }


def _summary_fields(record: JobRecord, result: EstimateResult | None) -> dict[str, Any]:
    return {
        **job_fields(record),
        "progress": record.progress_model(),
        "outcome": estimate_outcome(result) if result is not None else None,
    }


def estimate_summary(record: JobRecord, result: EstimateResult | None = None) -> EstimateSummary:
    if result is None:
        result = _result(record)
    return EstimateSummary(**_summary_fields(record, result))


def estimate_public(record: JobRecord) -> EstimatePublic:
    result = _result(record)
    return EstimatePublic(
        **_summary_fields(record, result),
        request=json.loads(record.request) if record.request else None,
        result=result,
        artifacts={
            name: f"{estimate_location(record.id)}/artifacts/{name}" for name in record.artifacts
        },
    )


TRACKS_PATH = "/v1/tracks"


def track_location(job_id: str) -> str:
    return f"{TRACKS_PATH}/{job_id}"


def track_state(record: JobRecord) -> TrackState:
    """A track's progress and frames so far (none before a worker started it)."""
    if record.progress:
        return TrackState.model_validate(record.progress)
    return TrackState(frames_total=record.max_iterations)


def track_public(record: JobRecord) -> TrackPublic:
    result = TrackResult.model_validate_json(record.result) if record.result else None
    state = track_state(record)
    if result is not None:
        state = TrackState(
            frames_done=len(result.frames), frames_total=len(result.frames), frames=result.frames
        )
    return TrackPublic(
        **job_fields(record),
        progress=TrackProgress(frames_done=state.frames_done, frames_total=state.frames_total),
        frame_names=[ref["name"] for ref in record.inputs],
        frames=state.frames,
        request=json.loads(record.request) if record.request else None,
        result=result,
        artifacts={
            name: f"{track_location(record.id)}/artifacts/{name}" for name in record.artifacts
        },
    )
