"""The contract between the API, the worker, the CLI and clients (pydantic v2 models)."""

from schemas.camera import Camera
from schemas.estimate import (
    Covariance,
    Errors,
    EstimateRequest,
    EstimateResult,
    IterationRecord,
)
from schemas.lighting import Lighting
from schemas.options import METHOD_PRESETS, EstimateOptions
from schemas.pose import Pose, PoseOut
from schemas.render import RenderRequest

__all__ = [
    "METHOD_PRESETS",
    "Camera",
    "Covariance",
    "Errors",
    "EstimateOptions",
    "EstimateRequest",
    "EstimateResult",
    "IterationRecord",
    "Lighting",
    "Pose",
    "PoseOut",
    "RenderRequest",
]
