"""Stored job records → the public resources (URLs are paths relative to the API root)."""

from __future__ import annotations

import json
import math

from schemas.estimate import EstimateResult
from schemas.jobs import EstimateOutcome, EstimatePublic, EstimateSummary, JobError
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


def estimate_summary(record: JobRecord, result: EstimateResult | None = None) -> EstimateSummary:
    if result is None:
        result = _result(record)
    return EstimateSummary(
        id=record.id,
        status=record.status,  # type: ignore[arg-type]
        model_id=record.model_id,
        created_at=record.created_at,  # type: ignore[arg-type]
        started_at=record.started_at,  # type: ignore[arg-type]
        finished_at=record.finished_at,  # type: ignore[arg-type]
        progress=record.progress_model(),
        error=JobError.model_validate(record.error) if record.error else None,
        cancel_requested=record.cancel_requested,
        attempts=record.attempts,
        outcome=estimate_outcome(result) if result is not None else None,
    )


def estimate_public(record: JobRecord) -> EstimatePublic:
    result = _result(record)
    summary = estimate_summary(record, result)
    return EstimatePublic(
        **dict(summary),
        request=json.loads(record.request) if record.request else None,
        result=result,
        artifacts={
            name: f"{estimate_location(record.id)}/artifacts/{name}" for name in record.artifacts
        },
    )
