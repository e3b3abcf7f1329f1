"""A tracked frame's outcome (worker.align.tracker)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.estimate import Covariance, Errors
from worker.engine.posemath import pose_to_schema

Array = NDArray[np.float64]


@dataclass
class FrameResult:
    """One frame's outcome."""

    index: int
    R: Array
    t: Array
    status: str  # tracked | reinitialised | lost
    converged: bool
    seconds: float
    renders: int
    render_cost: float
    alignment_score: float
    features: int
    covariance: Covariance | None = None
    errors: Errors | None = None
    relearned: bool = False
    reason: str = ""  # the LM's stop rule (a full estimate's reason for a re-initialised frame)

    def pose_json(self) -> dict[str, object]:
        return pose_to_schema(self.R, self.t).model_dump()
