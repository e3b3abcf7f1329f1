"""A single render of a model at a pose (the CLI's ``render`` and ``POST /v1/renders``)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from schemas.camera import Camera
from schemas.lighting import Lighting
from schemas.pose import Pose


class RenderRequest(BaseModel):
    """Camera, lighting and pose of one render."""

    model_config = ConfigDict(extra="forbid")

    camera: Camera
    pose: Pose
    lighting: Lighting = Field(default_factory=Lighting)
    spp: int = Field(default=16, ge=1, le=1024, description="Samples per pixel.")
    seed: int = Field(default=0, ge=0, le=2**31 - 1, description="Sampler seed.")
