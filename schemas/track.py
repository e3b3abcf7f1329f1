"""Tracking a sequence: the request (the CLI's REQUEST.json for ``proxpose track``) and the
result (OUT/track.json)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from schemas.camera import Camera
from schemas.estimate import Covariance, Errors, EstimateRequest
from schemas.lighting import Lighting
from schemas.options import EstimateOptions
from schemas.pose import Pose, PoseOut

FrameStatus = Literal["tracked", "reinitialised", "lost"]


class TrackRequest(BaseModel):
    """An estimate request for a sequence: ``initial_pose`` is the first frame's guess, and
    ``ground_truth``, when given, holds one true pose per frame (errors are then reported)."""

    model_config = ConfigDict(extra="forbid")

    camera: Camera
    initial_pose: Pose = Field(description="The initial guess of the first frame's pose.")
    lighting: Lighting = Field(default_factory=Lighting)
    options: EstimateOptions = Field(default_factory=EstimateOptions)
    ground_truth: list[Pose] | None = Field(
        default=None, description="The true pose of each frame, in frame order, when known."
    )

    def estimate_request(self) -> EstimateRequest:
        """The same request for one image (no truth)."""
        return EstimateRequest(
            camera=self.camera,
            initial_pose=self.initial_pose,
            lighting=self.lighting,
            options=self.options,
        )


class TrackFrame(BaseModel):
    """One frame's outcome."""

    image: str = Field(description="The frame's file name.")
    index: int = Field(description="0-based position in the sequence.")
    pose: PoseOut
    converged: bool
    status: FrameStatus = Field(
        description="'tracked' (went on from the previous frame), 'reinitialised' (a full "
        "estimate: the first frame, or one the referee rejected), 'lost' (no estimate "
        "converged; the pose is the motion prediction)."
    )
    reason: str = Field(default="", description="The stop rule of the frame's last LM pass.")
    seconds: float = Field(description="Engine time of the frame, s.")
    renders: int
    render_cost: float = Field(
        description="What the renders cost in full-resolution renders at the main spp."
    )
    alignment_score: float
    features: int
    relearned: bool = Field(
        default=False, description="Whether the Jacobian was learned again in this frame."
    )
    covariance: Covariance | None = None
    errors: Errors | None = None


class TrackSummary(BaseModel):
    """What the sequence cost and, with a truth, how accurate it was."""

    frames: int
    tracked: int
    reinitialised: int
    lost: int
    converged: int
    seconds: float = Field(description="Engine time of all frames, s.")
    median_seconds_per_tracked_frame: float | None = None
    frames_per_second: float = Field(description="Frames over the engine time.")
    renders: int
    render_cost: float
    median_rotation_error_deg: float | None = None
    max_rotation_error_deg: float | None = None
    median_translation_pct_of_range: float | None = None
    max_translation_pct_of_range: float | None = None


class TrackResult(BaseModel):
    """``track.json``: the frames in order and their summary."""

    frames: list[TrackFrame]
    summary: TrackSummary
    method: str
    variant: str = ""


def summarise(frames: list[TrackFrame]) -> TrackSummary:
    """The summary of ``frames``."""

    def median(xs: list[float]) -> float | None:
        if not xs:
            return None
        s = sorted(xs)
        n = len(s)
        return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])

    seconds = sum(f.seconds for f in frames)
    rot = [f.errors.rotation_deg for f in frames if f.errors is not None]
    tr = [f.errors.translation_pct_of_range for f in frames if f.errors is not None]
    return TrackSummary(
        frames=len(frames),
        tracked=sum(f.status == "tracked" for f in frames),
        reinitialised=sum(f.status == "reinitialised" for f in frames),
        lost=sum(f.status == "lost" for f in frames),
        converged=sum(f.converged for f in frames),
        seconds=round(seconds, 3),
        median_seconds_per_tracked_frame=median(
            [f.seconds for f in frames if f.status == "tracked"]
        ),
        frames_per_second=round(len(frames) / seconds, 3) if seconds > 0 else 0.0,
        renders=sum(f.renders for f in frames),
        render_cost=round(sum(f.render_cost for f in frames), 3),
        median_rotation_error_deg=median(rot),
        max_rotation_error_deg=max(rot) if rot else None,
        median_translation_pct_of_range=median(tr),
        max_translation_pct_of_range=max(tr) if tr else None,
    )
