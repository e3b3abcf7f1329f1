"""Jobs of the service: estimate submissions, their public resource, and render requests."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from schemas.estimate import EstimateRequest, EstimateResult, Stage, StopReason
from schemas.models import MODEL_ID_PATTERN
from schemas.names import JobErrorCode
from schemas.render import RenderRequest

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
#: States a job never leaves.
TERMINAL_STATUSES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})


#: A submission's ``request`` part, the documents' example (an estimate's or a track's).
CREATE_EXAMPLE: dict[str, Any] = {
    "model_id": "demo-sat",
    "camera": {"width": 512, "height": 512, "fx": 560, "fy": 560, "cx": 255.5, "cy": 255.5},
    "initial_pose": {"t": [0.3, -0.2, 14.0], "quaternion": [0.5816, 0.6734, 0.4081, 0.2041]},
}


class EstimateCreate(EstimateRequest):
    """The ``request`` part of ``POST /v1/estimates``: the CLI's REQUEST.json plus the model."""

    model_config = ConfigDict(json_schema_extra={"examples": [CREATE_EXAMPLE]})

    model_id: str = Field(
        pattern=MODEL_ID_PATTERN,
        description="Id of a registered model (see /v1/models), e.g. 'demo-sat'.",
        examples=["demo-sat"],
    )

    def engine_request(self) -> EstimateRequest:
        """The request without ``model_id``, keeping which fields were given explicitly (the
        method presets fill only the fields a request leaves unset)."""
        data = self.model_dump(exclude={"model_id"}, exclude_unset=True, by_alias=True)
        return EstimateRequest.model_validate(data)


class RenderCreate(RenderRequest):
    """Body of ``POST /v1/renders``: camera, pose and lighting of one render, and the model."""

    model_id: str = Field(
        pattern=MODEL_ID_PATTERN,
        description="Id of a registered model (see /v1/models).",
        examples=["demo-sat"],
    )

    def engine_request(self) -> RenderRequest:
        """The request without ``model_id``."""
        data = self.model_dump(exclude={"model_id"}, exclude_unset=True, by_alias=True)
        return RenderRequest.model_validate(data)


class Progress(BaseModel):
    """Where a job is: the last finished iteration (0 before the first) and its cost."""

    iteration: int = Field(default=0, description="Iterations done (1-based count).")
    max_iterations: int = Field(description="Iteration cap of this estimate.")
    cost: float | None = Field(
        default=None, description="Mean squared feature residual after the last iteration, px²."
    )
    stage: Stage | None = Field(default=None, description="Stage of the last iteration.")


class JobError(BaseModel):
    """Why a job failed: a stable code and a sentence (never a traceback)."""

    code: JobErrorCode = Field(
        description="Engine codes (invalid_image, image_size_mismatch, invalid_model, "
        "empty_render, too_few_features, render_failed, ...) or service codes (model_not_found, "
        "timeout, worker_lost: the workers running it died job_max_attempts times, "
        "internal_error).",
        examples=["too_few_features"],
    )
    message: str


class EstimateOutcome(BaseModel):
    """Headline figures of a succeeded estimate, for listings (the result has them all)."""

    converged: bool
    reason: StopReason
    rotation_change_deg: float = Field(
        description="Angle between the initial guess's attitude and the estimate's, degrees."
    )
    translation_change: float = Field(
        description="‖t − t₀‖ between the initial guess and the estimate, scene units."
    )


class JobSummary(BaseModel):
    """What every job resource (an estimate, a track) shows of the job itself."""

    id: str
    status: JobStatus
    model_id: str
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    error: JobError | None = None
    cancel_requested: bool = Field(
        default=False, description="A DELETE asked the running job to stop; it stops shortly."
    )
    attempts: int = Field(
        default=0,
        description="Times a worker started the job: more than 1 when a worker died running it "
        "and the job was queued again.",
    )


class EstimateSummary(JobSummary):
    """One job in a listing (the full resource adds the result and the artifacts)."""

    progress: Progress
    outcome: EstimateOutcome | None = Field(
        default=None, description="Headline figures of the result, once succeeded."
    )


class EstimatePublic(EstimateSummary):
    """An estimate job (``GET /v1/estimates/{id}``)."""

    request: dict[str, Any] | None = Field(
        default=None,
        description="The request as submitted, without model_id (the fields it gave, as the "
        "engine read them).",
    )
    result: EstimateResult | None = Field(
        default=None, description="The CLI's result.json, once the job succeeded."
    )
    artifacts: dict[str, str] = Field(
        default_factory=dict, description="PNG artifacts by name → URL path, once succeeded."
    )


class EstimateList(BaseModel):
    """A page of jobs, newest first."""

    items: list[EstimateSummary]
    next_cursor: str | None = Field(
        default=None, description="Pass as ?cursor= for the next page; null on the last page."
    )
