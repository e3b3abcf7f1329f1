"""Track jobs of the service (``/v1/tracks``): the submission, its progress and its resource."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from schemas.jobs import CREATE_EXAMPLE, JobSummary
from schemas.models import MODEL_ID_PATTERN
from schemas.track import TrackFrame, TrackRequest, TrackResult

#: The job kind of a track in the job store (an estimate's is "estimate").
TRACK_KIND = "track"


class TrackCreate(TrackRequest):
    """The ``request`` part of ``POST /v1/tracks``: the CLI's REQUEST.json of ``proxpose
    track`` plus the model."""

    model_config = ConfigDict(json_schema_extra={"examples": [CREATE_EXAMPLE]})

    model_id: str = Field(
        pattern=MODEL_ID_PATTERN,
        description="Id of a registered model (see /v1/models), e.g. 'demo-sat'.",
        examples=["demo-sat"],
    )

    def engine_request(self) -> TrackRequest:
        """The request without ``model_id``, keeping which fields were given explicitly."""
        data = self.model_dump(exclude={"model_id"}, exclude_unset=True, by_alias=True)
        return TrackRequest.model_validate(data)


class TrackProgress(BaseModel):
    """How far a track job is: the frames done so far of all its frames."""

    frames_done: int = Field(default=0, description="Frames tracked so far.")
    frames_total: int = Field(description="Frames in the sequence.")


class TrackProgressEvent(TrackProgress):
    """The ``progress`` event of a track's event stream: one per frame, with that frame."""

    frame: TrackFrame


class TrackState(TrackProgress):
    """What the job store keeps of a running track: the progress and the frames so far."""

    frames: list[TrackFrame] = Field(default_factory=list)


class TrackPublic(JobSummary):
    """A track job (``GET /v1/tracks/{id}``): the frames so far while it runs, the result
    (the CLI's track.json) once it succeeded."""

    progress: TrackProgress
    frame_names: list[str] = Field(description="The uploaded frames' file names, in order.")
    frames: list[TrackFrame] = Field(
        default_factory=list, description="The frames tracked so far, in order."
    )
    request: dict[str, Any] | None = Field(
        default=None, description="The request as submitted, without model_id."
    )
    result: TrackResult | None = Field(
        default=None, description="track.json, once the job succeeded."
    )
    artifacts: dict[str, str] = Field(
        default_factory=dict,
        description="Artifacts by name → URL path, once succeeded: 'trajectory' (PNG), "
        "'track.csv', and 'overlay_<k>' (PNG) for the frames that have an overlay.",
    )
